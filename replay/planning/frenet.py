"""Frenet sampling planners from fiss-planner (PyPI, Apache-2.0; an optional extra).

``FrenetPlanner("fop")`` is Werling et al.'s Frenet optimal planner (ICRA 2010: every
candidate generated, the cheapest valid one kept); ``"fiss"`` and ``"fiss_plus"`` are Sun
et al.'s iterative search (RA-L 2022) and its refinement (IROS 2023) over the same
candidates, costs and checks.

The adapter:

- reference line: ``request.reference`` (the ego's lane centre line, no kink at the
  ego); corridor: ``lanes_right`` + the ego's lane + ``lanes_left`` parallel lanes of
  ``lane_width_m`` (``fp.Corridor.parallel_lanes``);
- ego: projected onto the reference (arc ``s``, offset ``d``: the ego at its lateral
  offset from its lane centre; speed split along and across the path by the heading's
  angle to it, so the heading error is in the initial state);
- limits from the scene: the vehicle's top speed is the larger of the target speed (the
  fastest the recorded driver drove over the horizon) and the ego's speed, times
  TOP_SPEED_FACTOR plus TOP_SPEED_MARGIN_MPS, rounded up to TOP_SPEED_STEP_MPS
  (fiss-planner's default 30 m/s rejected every candidate of an ego at motorway speed);
- a failure names its cause (:func:`failure_reason`): fiss-planner's rejection counts,
  and whether the request has a plan without its agents (planned once more, on failures
  only, outside ``plan_ms``);
- obstacles: each agent's forecast, time-stamped, with its box (static when it never
  moves); the binding takes one ``fp.Obstacle`` per agent, so this conversion is the one
  loop over agents (about 2 us each, measured in benchmarks/bench_planner.py);
- the planner is reset before every call: FISS starts its search from the previous
  solution, and a counterfactual plan must not depend on the plan made before it;
- the trajectory: fiss-planner samples end times between ``min_t`` (3 s) and the horizon,
  so a plan can end before the horizon (a braking plan often does). It is resampled onto
  the request's times up to its own end and not continued beyond: a continuation would
  be a trajectory the planner never checked. ``compare_plans`` compares plans over their
  common times;
- ``plan_ms``: wall time of the whole call (obstacle conversion and planning);
  ``extras["core_ms"]`` is the planner's own ``stats.time_ms``.
"""

from __future__ import annotations

import math
import time
from types import ModuleType
from typing import Any

import numpy as np

from replay.planning.errors import PlannerUnavailable, PlanningError
from replay.planning.path_coords import path_coords, project
from replay.planning.types import STOP_SPEED_MPS, Plan, PlanRequest

VARIANTS: tuple[str, ...] = ("fop", "fiss", "fiss_plus")
INSTALL_HINT = "pip install 'riskreplay[planner]'"

#: Slack (m) added to every range in ``may_matter``: covers the lateral overshoot of the
#: quintic lateral profiles and the spline fit of the reference line.
MAY_MATTER_SLACK_M = 2.0

#: The top speed from the scene: the fastest of target, ego and agents, times this, plus
#: the margin, rounded up to the step (so that few planner instances are made: one per
#: top speed).
TOP_SPEED_FACTOR = 1.1
TOP_SPEED_MARGIN_MPS = 2.0
TOP_SPEED_STEP_MPS = 5.0

#: The ego's lane is widened to hold the ego's footprint now, plus fiss-planner's lane
#: margin and this slack (m), tapering back to the lane over the horizon's driving.
EGO_LANE_SLACK_M = 0.05

#: fiss-planner's rejection classes: limits of the vehicle and the road, and obstacles.
KINEMATIC_REJECTIONS = ("invalid", "speed", "accel", "curvature", "lat_accel", "off_road")
OBSTACLE_REJECTIONS = ("collision", "safety_distance")


def top_speed_mps(request: PlanRequest) -> float:
    """The vehicle's top speed for this request (see the module docstring). The agents'
    speeds do not count: a filter's or the planner truth's subset of the agents must not
    change the vehicle (and the ego need not outrun anyone to follow them)."""
    fastest = max(request.target_speed_mps, request.ego.speed_mps, 0.0)
    top = fastest * TOP_SPEED_FACTOR + TOP_SPEED_MARGIN_MPS
    return float(math.ceil(top / TOP_SPEED_STEP_MPS) * TOP_SPEED_STEP_MPS)


#: Scales tried for the box of an agent that overlaps the ego now (see box_scales).
BOX_SCALES = (0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.1)


def box_scales(request: PlanRequest, margin_lon_m: float, margin_lat_m: float) -> np.ndarray:
    """``(K,)``: the factor for each agent's length and width given to fiss-planner: 1,
    or for an agent whose recorded box overlaps the ego's now (inflated by fiss-planner's
    collision margins) the largest of BOX_SCALES that clears it, 0 when none does (the
    agent is then left out).

    Every candidate starts in collision with such an agent, so fiss-planner rejected them
    all (in MONA, where recorded boxes of queued cars overlap, a third of the failures of
    a sample), although no plan can undo a collision already in progress (nuPlan counts a
    collision with an agent once, when it starts). The smaller box still blocks the way.
    ``Plan.extras["shrunk_agents"]`` counts them.
    """
    a, e = request.agents, request.ego
    scale = np.ones(a.n)
    # Only boxes whose circumscribed circles meet can overlap: the test on those alone.
    reach = 0.5 * np.hypot(e.length_m + 2 * margin_lon_m, e.width_m + 2 * margin_lat_m)
    near = np.hypot(*(a.xy[:, 0] - e.xy).T) <= reach + 0.5 * np.hypot(a.length_m, a.width_m)
    if not near.any():
        return scale
    hit = near.copy()
    hit[near] = overlapping_now(
        request.with_agents(a.subset(near)), margin_lon_m, margin_lat_m, scale[near]
    )
    for factor in BOX_SCALES:
        if not hit.any():
            break
        scale = np.where(hit, factor, scale)
        sub = request.with_agents(a.subset(hit))
        hit[hit] = overlapping_now(sub, margin_lon_m, margin_lat_m, scale[hit])
    return np.where(hit, 0.0, scale)


def overlapping_now(
    request: PlanRequest, margin_lon_m: float, margin_lat_m: float, scale: np.ndarray
) -> np.ndarray:
    """``(K,)`` bool: the agent's box at t = 0, its length and width times ``scale``,
    overlaps the ego's box inflated by the margins (separating-axis test, vectorised)."""
    a = request.agents
    if a.n == 0:
        return np.zeros(0, dtype=bool)
    e = request.ego

    def corners(xy: np.ndarray, heading: np.ndarray, half_l: np.ndarray, half_w: np.ndarray):
        c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
        u = np.array([1.0, -1.0, -1.0, 1.0])[None] * half_l[:, None]
        v = np.array([1.0, 1.0, -1.0, -1.0])[None] * half_w[:, None]
        return np.stack([xy[:, None, 0] + c * u - s * v, xy[:, None, 1] + s * u + c * v], -1)

    ego = corners(
        e.xy[None], np.array([e.heading_rad]),
        np.array([e.length_m / 2 + margin_lon_m]), np.array([e.width_m / 2 + margin_lat_m]),
    )  # fmt: skip
    other = corners(a.xy[:, 0], a.heading_rad[:, 0], scale * a.length_m / 2, scale * a.width_m / 2)
    axes_ego = np.array([[math.cos(e.heading_rad), math.sin(e.heading_rad)]])
    axes_ego = np.concatenate([axes_ego, axes_ego[:, ::-1] * [-1.0, 1.0]])  # (2, 2)
    h = a.heading_rad[:, 0]
    axes_other = np.stack(
        [np.stack([np.cos(h), np.sin(h)], -1), np.stack([-np.sin(h), np.cos(h)], -1)], 1
    )  # (K, 2, 2)
    axes = np.concatenate([np.broadcast_to(axes_ego, (a.n, 2, 2)), axes_other], 1)  # (K, 4, 2)
    pe = np.einsum("kad,pd->kap", axes, ego[0])  # (K, 4 axes, 4 corners)
    po = np.einsum("kad,kpd->kap", axes, other)
    apart = (pe.max(-1) < po.min(-1)) | (po.max(-1) < pe.min(-1))
    return np.asarray(~apart.any(axis=1))


def failure_reason(
    rejections: dict[str, int], n_agents: int, feasible_without_agents: bool | None = None
) -> str:
    """Why fiss-planner found no plan, from its rejection counts per class and, with
    agents, whether the same request without any agent has a plan:

    - "no candidate generated";
    - "no feasible path (no agents)": no agent, and every candidate broke a limit of the
      vehicle or the road;
    - "no feasible path (also without agents)": the request fails without its agents too
      (the reference, the lanes or the ego's state: no agent is to blame);
    - "all candidates collide": every rejection was a collision or a safety distance;
    - "blocked by agents": a plan exists without the agents, and with them every
      candidate collided or broke a limit (e.g. avoiding one swerves too hard);

    followed by the counts, largest first (e.g. ``": collision 80, lat_accel 45"``).
    """
    counts = {k: int(n) for k, n in rejections.items() if int(n) > 0}
    if not counts:
        return "no candidate generated"
    kinematic = sum(counts.get(k, 0) for k in KINEMATIC_REJECTIONS)
    if n_agents == 0:
        what = "no feasible path (no agents)"
    elif feasible_without_agents is False:
        what = "no feasible path (also without agents)"
    elif kinematic == 0:
        what = "all candidates collide"
    else:
        what = "blocked by agents"
    detail = ", ".join(f"{k} {n}" for k, n in sorted(counts.items(), key=lambda kv: -kv[1]))
    return f"{what}: {detail}"


def load_fiss_planner() -> ModuleType:
    """The ``fiss_planner`` module, or PlannerUnavailable naming the extra to install."""
    try:
        import fiss_planner  # the optional extra: loaded only when a Frenet planner is made
    except ImportError:
        raise PlannerUnavailable(
            f"the Frenet planners need the optional package fiss-planner; {INSTALL_HINT}"
        ) from None
    return fiss_planner


class FrenetPlanner:
    """fiss-planner behind the :class:`~replay.planning.types.Planner` interface.

    ``overrides``: attribute paths of ``fp.PlannerConfig`` to set, e.g.
    ``{"sampling.num_width": 7}``.
    """

    def __init__(self, variant: str = "fop", *, overrides: dict[str, Any] | None = None) -> None:
        if variant not in VARIANTS:
            raise PlanningError(
                f"unknown Frenet planner variant {variant!r}; expected one of {', '.join(VARIANTS)}"
            )
        self.fp = load_fiss_planner()
        self.variant = variant
        self.name = variant
        self.overrides = dict(overrides or {})
        self._planners: dict[tuple[float, float, float, float, float], Any] = {}
        self._config_made: Any = None

    # ------------------------------------------------------------------ the planner
    def _corridor(
        self, request: PlanRequest, length_m: float, s0: float, d0: float, rel: float
    ) -> Any:
        """``lanes_right`` + the ego's lane + ``lanes_left`` parallel lanes of
        ``lane_width_m``, the ego's lane widened where the ego's footprint now sticks out
        of it (its offset ``d0`` and heading ``rel`` to the reference), back to the lane
        over the horizon at the ego's speed, and never narrower than the ego plus the
        slack: otherwise an ego astride a lane line, turned in its lane, or wider than a
        3.5 m lane less fiss-planner's margins (a 2.8 m truck, a 3.4 m bus) is off the
        road in every candidate."""
        fp = self.fp
        w = request.lane_width_m
        ego = request.ego
        taper = max(request.horizon_s * max(ego.speed_mps, request.target_speed_mps), 10.0)
        # The bands are linear between stations (and held beyond them): the fade needs
        # its two ends; a few between follow the max() of the widened and the lane edge.
        stations = np.unique(
            np.clip(np.r_[0.0, s0 + taper * np.linspace(0.0, 1.0, 9), length_m], 0.0, length_m)
        )
        across = 0.5 * ego.length_m * abs(math.sin(rel)) + 0.5 * ego.width_m * abs(math.cos(rel))
        slack = self._config().sampling.lane_margin + EGO_LANE_SLACK_M
        half = max(0.5 * w, 0.5 * ego.width_m + slack)  # the ego's lane holds the ego
        fade = np.clip(1.0 - (stations - s0) / taper, 0.0, 1.0)  # 1 up to the ego, then 0
        corridor = fp.Corridor(stations.tolist())
        for k in range(-request.lanes_right, request.lanes_left + 1):
            centre = np.full(stations.size, k * w)
            left, right = centre + 0.5 * w, centre - 0.5 * w
            if k == 0:
                centre = fade * d0  # where the ego is, then its lane's centre
                left = np.maximum(centre + half, fade * (d0 + across + slack))
                right = np.minimum(centre - half, fade * (d0 - across - slack))
            band = fp.LaneBand()
            band.lane_id, band.offset = k, k
            band.left, band.right = left.tolist(), right.tolist()
            band.center = centre.tolist()
            corridor.add_lane(band)
        return corridor

    def _config(self) -> Any:
        """The configuration (:meth:`_make_config`), made once; read, never changed."""
        if self._config_made is None:
            self._config_made = self._make_config()
        return self._config_made

    def _make_config(self) -> Any:
        """The variant's configuration with the overrides applied. Collisions with an
        agent behind the ego in its lane are ignored (``collision.ignore_rear_in_lane``):
        a follower that hits the ego is at fault (nuPlan's rule), and a queued follower
        within fiss-planner's safety gap otherwise rejects every candidate."""
        config = self.fp.make_config(self.variant)
        config.collision.ignore_rear_in_lane = True
        for path, value in self.overrides.items():
            *parents, last = path.split(".")
            target = config
            for part in parents:
                target = getattr(target, part)
            setattr(target, last, value)
        return config

    def _vehicle(self, request: PlanRequest) -> Any:
        """fiss-planner's vehicle: the ego's size, the top speed from the scene."""
        vehicle = self.fp.VehicleParams()
        if request.ego.length_m > 0 and request.ego.width_m > 0:
            vehicle.length = request.ego.length_m
            vehicle.width = request.ego.width_m
        vehicle.max_speed = top_speed_mps(request)
        return vehicle

    def _planner(self, request: PlanRequest) -> Any:
        """One fiss-planner instance per (dt, horizon, ego size, top speed), reset for
        each call."""
        vehicle = self._vehicle(request)
        key = (
            request.dt_s, request.horizon_s, float(vehicle.length), float(vehicle.width),
            float(vehicle.max_speed),
        )  # fmt: skip
        planner = self._planners.get(key)
        if planner is None:
            config = self._make_config()  # its own: the sampling is set per instance
            config.sampling.dt = request.dt_s
            config.sampling.max_t = request.horizon_s
            config.sampling.min_t = min(config.sampling.min_t, request.horizon_s)
            planner = self.fp.make_planner(config, vehicle)
            self._planners[key] = planner
        planner.reset()
        return planner

    def _obstacles(self, request: PlanRequest, scale: np.ndarray) -> list[Any]:
        """fiss-planner's obstacles: every agent's forecast, its box times ``scale``
        (``box_scales``; agents with scale 0 left out)."""
        keep = scale > 0.0
        a = request.agents.subset(keep) if not keep.all() else request.agents
        scale = scale[keep]
        times = a.times_s.tolist()
        moves = np.asarray((np.abs(np.diff(a.xy, axis=1)) > 1e-9).any(axis=(1, 2)), dtype=bool)
        static = (~moves).tolist()
        make = self.fp.Obstacle.from_arrays
        return [
            make(int(i), float(ln), float(w), times, x, y, h, bool(still))
            for i, ln, w, x, y, h, still in zip(
                a.ids.tolist(),
                (scale * a.length_m).tolist(),
                (scale * a.width_m).tolist(),
                a.xy[..., 0].tolist(),
                a.xy[..., 1].tolist(),
                a.heading_rad.tolist(),
                static,
                strict=True,
            )
        ]

    def plan(self, request: PlanRequest) -> Plan:
        fp = self.fp
        start = time.perf_counter()
        ref = fp.ReferenceLine(request.reference[:, 0], request.reference[:, 1])
        ego = request.ego
        proj = ref.project(float(ego.xy[0]), float(ego.xy[1]))
        rel = ego.heading_rad - ref.at(proj.s).yaw
        corridor = self._corridor(request, float(ref.length), float(proj.s), float(proj.d), rel)
        state = fp.FrenetState(
            s=proj.s,
            s_d=ego.speed_mps * math.cos(rel),
            s_dd=ego.accel_mps2 * math.cos(rel),
            d=proj.d,
            d_d=ego.speed_mps * math.sin(rel),
        )
        config = self._config()
        scale = box_scales(request, config.collision.margin_lon, config.collision.margin_lat)
        obstacles = self._obstacles(request, scale)
        planner = self._planner(request)
        result = planner.plan(
            state, ref, corridor, obstacles, target_speed=float(request.target_speed_mps)
        )
        stats = result.stats
        blocking = int(stats.blocking_id)
        if not result.success:
            plan_ms = (time.perf_counter() - start) * 1e3  # without the diagnosis below
            rejections = dict(stats.rejections)
            alone = None
            if request.agents.n:  # the same request without agents: who is to blame?
                planner.reset()
                alone = bool(
                    planner.plan(
                        state, ref, corridor, [], target_speed=float(request.target_speed_mps)
                    ).success
                )
            return Plan.failed(
                failure_reason(rejections, request.agents.n, alone),
                plan_ms=plan_ms,
                blocking_id=blocking,
            )
        times, xy, heading, speed = self._resample(result.trajectory, request.times_s)
        plan_ms = (time.perf_counter() - start) * 1e3
        return Plan(
            ok=True,
            times_s=times,
            xy=xy,
            heading_rad=heading,
            speed_mps=speed,
            plan_ms=plan_ms,
            lane=int(result.trajectory.lane),
            stops=bool((speed < STOP_SPEED_MPS).any()),
            blocking_id=blocking,
            extras={
                "core_ms": float(stats.time_ms),
                "candidates": float(stats.num_generated),
                "shrunk_agents": float((scale < 1.0).sum()),
            },
        )

    @staticmethod
    def _resample(
        traj: Any, times: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The trajectory on the request's times (T,) up to its own end time: times
        ``(T',)``, points ``(T', 2)``, headings and speeds ``(T',)``."""
        t = np.asarray(traj.t, dtype=np.float64)
        keep = times <= t[-1] + 1e-9
        out_t = times[keep]
        yaw = np.unwrap(np.asarray(traj.yaw, dtype=np.float64))
        xy = np.stack(
            [np.interp(out_t, t, np.asarray(traj.x)), np.interp(out_t, t, np.asarray(traj.y))],
            axis=1,
        )
        heading = (np.interp(out_t, t, yaw) + np.pi) % (2 * np.pi) - np.pi
        return out_t, xy, heading, np.interp(out_t, t, np.asarray(traj.v, dtype=np.float64))

    # ------------------------------------------------------------------ may_matter
    def may_matter(self, request: PlanRequest) -> np.ndarray:
        """``(K,)`` bool: False for agents that stay out of every range at which
        fiss-planner looks at an obstacle, around every trajectory it can generate.

        The argument. Every candidate is a Frenet trajectory along the reference: its
        lateral offset moves between the ego's offset and a sampled lane offset within the
        corridor (quintic, with a small overshoot), its arc length grows at most at the
        vehicle's maximum speed (``VehicleParams.max_speed``) plus its maximum acceleration
        over the horizon. fiss-planner reads an obstacle in four places, all documented as
        functions of the ego-obstacle distance at equal times: the collision check (boxes
        inflated by ``collision.margin_lon``/``margin_lat``), the safety envelope
        (``safety.min_gap`` plus ``min_time_headway`` and ``min_ttc`` times speeds), the
        costs (``cost.desired_clearance`` across; ``desired_gap`` + ``desired_time_headway``
        x speed, ``desired_ttc`` x closing speed and ``follow_time`` x speed along) and the
        lead gap. So an obstacle whose boxes, at every forecast time, lie farther from the
        reachable region than the largest of those ranges (with both speeds at their
        maximum, plus MAY_MATTER_SLACK_M) can change neither a check nor a cost, hence not
        the plan. Across the path the range is the clearance/margin/gap range; along it
        (ahead of and behind the region) the headway/TTC/follow range. Points that project
        onto the reference's ends are measured with the longer range in every direction.

        This rests on the package's documented parameters, not on a reading of its C++
        source (v1.0's core is not in the stored sources); tests/test_planning.py checks
        it empirically (an agent with may_matter False never changes the plan).
        """
        a = request.agents
        if a.n == 0:
            return np.zeros(0, dtype=bool)
        config = self._config()
        vehicle = self._vehicle(request)
        cost, safety, coll = config.cost, config.safety, config.collision
        horizon = request.horizon_s
        ego = request.ego
        v_ego = max(ego.speed_mps, request.target_speed_mps, vehicle.max_speed)
        reach_m = v_ego * horizon + 0.5 * vehicle.max_accel * horizon**2

        c = path_coords(request.reference, a)
        ego_d, s0 = (float(v[0]) for v in project(request.reference, ego.xy[None]))
        ref_len = float(np.sum(np.linalg.norm(np.diff(request.reference, axis=0), axis=1)))
        w = request.lane_width_m
        road = max((request.lanes_left + 0.5) * w, (request.lanes_right + 0.5) * w)
        half_ego = 0.5 * max(ego.length_m, ego.width_m, vehicle.length, vehicle.width)
        band = max(road, abs(ego_d)) + half_ego + MAY_MATTER_SLACK_M  # candidates' reach across
        across = max(coll.margin_lat, cost.desired_clearance, safety.min_gap) + MAY_MATTER_SLACK_M
        v_agent = np.abs(c.speed_along_mps).max(axis=1) + np.abs(
            np.diff(a.xy, axis=1) / np.diff(a.times_s)[None, :, None]
        ).max(axis=(1, 2), initial=0.0)  # (K,), generous: along-path rate + any axis rate
        closing = v_ego + v_agent
        along = (
            np.maximum.reduce(
                [
                    np.full(a.n, cost.desired_gap + cost.desired_time_headway * v_ego),
                    np.full(a.n, cost.follow_time * v_ego),
                    cost.desired_ttc * closing,
                    safety.min_gap + safety.min_time_headway * v_ego + safety.min_ttc * closing,
                    np.full(a.n, coll.margin_lon),
                ]
            )
            + 2 * half_ego
            + MAY_MATTER_SLACK_M
        )[:, None]  # (K, 1)
        lo = s0 - along - c.half_along_m
        hi = s0 + reach_m + along + c.half_along_m
        near_along = (c.arc_m >= lo) & (c.arc_m <= hi)
        at_end = (c.arc_m >= ref_len - 1e-6) | (c.arc_m <= 1e-6)
        gap = c.lateral_m - c.half_across_m
        near_across = np.where(at_end, gap <= band + along, gap <= band + across)
        return np.asarray((near_along & near_across).any(axis=1))
