"""IDM along the reference path: a planner that needs nothing beyond numpy.

The Intelligent Driver Model (Treiber, Hennecke, Helbing, Phys. Rev. E 62, 2000)::

    a = a0 * (1 - (v / v0)^delta - (s*(v, dv) / s)^2),
    s*(v, dv) = s0 + max(0, v * T + v * dv / (2 * sqrt(a0 * b)))

with ``v`` the ego's speed, ``v0`` the target speed, ``s`` the bumper-to-bumper gap to the
leader and ``dv = v - v_leader`` (:mod:`replay.planning.idm_law`, shared with the
reactive agents). The ego is simulated forward along its reference path at
the request's ``dt_s`` over the horizon (a ballistic update that never reverses).

The ego's path: the reference (its lane's centre line) with the ego's lateral offset
from it now, returning to the centre line along a half-cosine over ``lane_return_s`` at
the ego's speed (at least ``lane_return_min_m``), so that a plan starts where the ego is.

Who counts, at each step (vectorised over agents; the loop runs over time steps only):

- **The corridor** is the ego's swept path: an agent is in it when its predicted box,
  projected inside the reference (not beyond either end), comes within the ego's half
  width plus ``corridor_margin_m`` of the ego's path (its centre's offset from the path
  below that plus the rotated box's half extent across the path). This is nuPlan's test
  (the path to go buffered by the ego's half width, intersected with the agents' boxes)
  with a margin for the reference's chords and smoothing; docs/planners.md says why.
- **Leaders**: agents in the corridor whose centre lies ahead of the ego's centre along
  the path and which move along the path (heading within 45 degrees of it). Gap and speed
  are measured along the path.
- **Conflicts** (crossing or oncoming agents in the corridor ahead): the first point ahead
  where the agent's box is in the corridor is a conflict point. When the ego would occupy
  that point within ``time_margin_s`` of the agent's stay in the corridor, the agent acts
  as a stopped leader there: the ego yields. When the ego would get there is timed on the
  free-road IDM speed profile from its speed now (a stopped ego moves off; timed at its
  current speed it would never arrive, and never yield).

Each agent gives one IDM acceleration; the least counts (clipped to ``[-max_decel, a0]``).
``blocking_id``: the agent with the least acceleration at the first step where it lies
more than ``blocking_margin_mps2`` below the free-road acceleration.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from converters.lanegraph import simplify
from replay.planning.idm_law import IdmLaw, free_road_acceleration, idm_acceleration
from replay.planning.path_coords import CoordsCache, PathCoords, project
from replay.planning.types import STOP_SPEED_MPS, Plan, PlanRequest
from risk import geometry


@dataclass(frozen=True, kw_only=True)
class IdmSettings:
    """IDM parameters (Treiber et al. 2000, their Table I for a city car where given).

    ``a0_mps2``: maximum acceleration; ``b_mps2``: comfortable deceleration;
    ``headway_s``: desired time headway ``T``; ``s0_m``: jam distance; ``delta``:
    acceleration exponent; ``max_decel_mps2``: the physical braking limit the IDM's
    acceleration is clipped to; ``time_margin_s``: how close in time the ego may pass a
    crossing agent's stay in its corridor before it yields; ``blocking_margin_mps2``: how
    far below the free-road acceleration an agent must push the ego to be reported as
    blocking; ``corridor_margin_m``: added to the ego's half width for the corridor;
    ``lane_return_s`` / ``lane_return_min_m``: how far (time at the ego's speed, least
    distance) the ego's path takes to return from its offset to the lane centre;
    ``reference_tolerance_m``: the planner works on the reference thinned by
    Ramer-Douglas-Peucker to this tolerance (every agent at every step is projected onto
    it: a straight motorway reference of 140 points becomes 2, and a longer reference
    costs nothing where it is straight).
    """

    a0_mps2: float = 1.0
    b_mps2: float = 1.5
    headway_s: float = 1.5
    s0_m: float = 2.0
    delta: float = 4.0
    max_decel_mps2: float = 8.0
    time_margin_s: float = 1.5
    blocking_margin_mps2: float = 0.1
    corridor_margin_m: float = 0.2
    lane_return_s: float = 3.0
    lane_return_min_m: float = 15.0
    reference_tolerance_m: float = 0.02

    @property
    def law(self) -> IdmLaw:
        """The IDM's parameters for :mod:`replay.planning.idm_law`."""
        return IdmLaw(
            accel_mps2=self.a0_mps2, decel_mps2=self.b_mps2, headway_s=self.headway_s,
            min_gap_m=self.s0_m, exponent=self.delta,
        )  # fmt: skip


class IdmPlanner:
    """IDM longitudinal control along the ego's reference path, with yielding at conflict
    points of crossing agents (see the module's docstring)."""

    name = "idm"

    def __init__(self, settings: IdmSettings | None = None) -> None:
        self.settings = IdmSettings() if settings is None else settings
        self._coords = CoordsCache()
        self._thinned: tuple[np.ndarray, np.ndarray] | None = None

    def forget(self) -> None:
        """Drop the cached thinned reference and path coordinates, so that the next call
        pays for its own (a timed comparison of two calls must not let one reuse the
        other's work: see replay.planning.types.cold)."""
        self._coords = CoordsCache()
        self._thinned = None

    def _reference(self, request: PlanRequest) -> np.ndarray:
        """The request's reference thinned (see IdmSettings), the same object for the
        same reference (so that the coordinates cache serves a filter's and the
        counterfactual plans of one request)."""
        ref = request.reference
        if self._thinned is None or self._thinned[0] is not ref:
            thin = np.ascontiguousarray(ref[simplify(ref, self.settings.reference_tolerance_m)])
            self._thinned = (ref, thin)
        return self._thinned[1]

    # ------------------------------------------------------------------ may_matter
    def may_matter(self, request: PlanRequest) -> np.ndarray:
        """``(K,)`` bool: False for agents the simulation provably never reads.

        The argument. The planner reads an agent at step ``k`` only through ``gap`` (NaN
        means no constraint, and its acceleration term is then +inf, which leaves the
        minimum over agents unchanged):

        - as a leader: its box is in the corridor at step ``k`` (see :func:`_corridor`;
          the corridor depends on the request alone, not on the simulation), it moves
          along the path, and its arc exceeds the ego's arc ``s_k``;
        - as a conflict: it crosses or comes towards the ego, and at some step ``j >= k``
          its box is in the corridor with its arc beyond ``s_k``.

        The acceleration is clipped at ``-max_decel_mps2``, so ``s_k`` is at least the arc
        reached by braking at that limit from the start, ``s_min(t_k)``, and at least the
        start arc ``s_0``. An along-path agent that is never in the corridor beyond
        ``s_min(t_k)`` at any step ``k``, and a crossing agent never in the corridor beyond
        ``s_0``, are therefore never read, and the plan is the same without them.
        """
        a = request.agents.on_times(request.times_s)
        if a.n == 0:
            return np.zeros(0, dtype=bool)
        ref = self._reference(request)
        c = self._coords.get(ref, a)
        lane = _EgoLane.of(request, ref, self.settings)
        inside = _corridor(c, lane, request.ego.width_m, self.settings)
        s0 = lane.s0
        v = max(request.ego.speed_mps, 0.0)
        b = self.settings.max_decel_mps2
        t = np.minimum(a.times_s, v / b)  # braking at the limit stops at v / b
        s_min = s0 + v * t - 0.5 * b * t * t
        leader = inside & c.along & (c.arc_m > s_min[None, :])
        conflict = inside & ~c.along & (c.arc_m > s0)
        return np.asarray((leader | conflict).any(axis=1))

    # ------------------------------------------------------------------ plan
    def plan(self, request: PlanRequest) -> Plan:
        start = time.perf_counter()
        p = self.settings
        times = request.times_s
        dt = request.dt_s
        n_steps = times.size
        ref = self._reference(request)
        ego = request.ego
        half_ego = ego.length_m / 2.0
        v0 = max(request.target_speed_mps, 0.1)
        law = p.law
        lane = _EgoLane.of(request, ref, p)

        agents = request.agents.on_times(times)  # the plan's steps
        ids = agents.ids
        if agents.n:
            coords = self._coords.get(ref, agents)
            inside = _corridor(coords, lane, ego.width_m, p)
            # Only agents that are ever in the corridor can constrain (see may_matter):
            # the loop over steps works on those alone.
            ever = np.asarray(inside.any(axis=1))
            coords, inside, ids = coords.rows(ever), inside[ever], ids[ever]
            # Time of the last forecast step each agent is in the corridor.
            t_out = times[n_steps - 1 - np.argmax(inside[:, ::-1], axis=1)]
            crossing = inside & ~coords.along
            any_crossing = bool(crossing.any())
        s = np.empty(n_steps)
        v = np.empty(n_steps)
        s[0] = lane.s0
        v[0] = max(ego.speed_mps, 0.0)
        blocking_id = -1
        # Agents that alone set a step's acceleration (see plan's docstring): the only
        # ones whose removal can change this plan.
        sole = np.zeros(ids.size, dtype=bool)
        for k in range(n_steps - 1):
            a_free = float(free_road_acceleration(v[k], v0, law))
            accel = a_free
            if ids.size:
                gap, v_lead = self._constraints(
                    coords, inside, crossing if any_crossing else None, t_out, k, times,
                    s[k], v[k], half_ego, v0,
                )  # fmt: skip
                a_agent = idm_acceleration(v[k], v0, gap, v_lead, law)
                a_agent = np.where(gap > 0.0, a_agent, -np.inf)  # overlap: full braking
                a_agent = np.where(np.isnan(gap), np.inf, a_agent)  # no constraint
                worst = int(np.argmin(a_agent))
                accel = min(a_free, float(a_agent[worst]))
                if blocking_id < 0 and accel < a_free - p.blocking_margin_mps2:
                    blocking_id = int(ids[worst])
                # Without the worst agent the step takes the next worst (or a_free);
                # when the clipped accelerations differ, the worst alone sets this step.
                # (Ties: the next worst equals the worst, so no agent alone does.)
                rest = np.partition(a_agent, 1)[1] if a_agent.size > 1 else np.inf
                if _clip(min(a_free, float(rest)), p) != _clip(accel, p):
                    sole[worst] = True
            accel = min(max(accel, -p.max_decel_mps2), p.a0_mps2)
            v_next = v[k] + accel * dt
            if v_next >= 0.0:
                s[k + 1] = s[k] + v[k] * dt + 0.5 * accel * dt * dt
                v[k + 1] = v_next
            else:  # stops within the step
                s[k + 1] = s[k] + v[k] ** 2 / (2.0 * -accel)
                v[k + 1] = 0.0
        xy, heading = lane.points(ref, s)
        return Plan(
            ok=True,
            times_s=times,
            xy=xy,
            heading_rad=heading,
            speed_mps=v,
            plan_ms=(time.perf_counter() - start) * 1e3,
            lane=0,
            stops=bool((v < STOP_SPEED_MPS).any()),
            blocking_id=blocking_id,
            sole_constraints=ids[sole].astype(np.int64),
        )

    def _constraints(
        self,
        c: PathCoords,
        inside: np.ndarray,
        crossing: np.ndarray | None,
        t_out: np.ndarray,
        k: int,
        times: np.ndarray,
        s_ego: float,
        v_ego: float,
        half_ego: float,
        v0: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gap ``(K,)`` (m, NaN: not constraining) and leader speed along the path ``(K,)``
        for every agent at step ``k``."""
        # Leaders: in the corridor now, ahead of the ego, moving along the path.
        now_in = inside[:, k] & (c.arc_m[:, k] > s_ego)
        leader = now_in & c.along[:, k]
        gap = np.where(leader, c.arc_m[:, k] - c.half_along_m[:, k] - s_ego - half_ego, np.nan)
        v_lead = np.where(leader, c.speed_along_mps[:, k], 0.0)

        # Conflicts: the first future step at which a crossing / oncoming agent is in the
        # corridor ahead of the ego, if the ego would be there near that time.
        if crossing is None:
            return gap, v_lead
        future = crossing[:, k:] & (c.arc_m[:, k:] > s_ego)
        has = future.any(axis=1)
        if has.any():
            first = k + np.argmax(future, axis=1)
            rows = np.arange(first.size)
            s_c = c.arc_m[rows, first]
            half = c.half_along_m[rows, first]
            t_in = times[first]
            p = self.settings
            reach = s_c - half - s_ego - half_ego
            clear = s_c + half - s_ego + half_ego
            t_arrive = times[k] + free_road_time_s(reach, v_ego, v0, p.a0_mps2, p.delta)
            t_clear = times[k] + free_road_time_s(clear, v_ego, v0, p.a0_mps2, p.delta)
            m = p.time_margin_s
            conflict = has & (t_arrive <= t_out + m) & (t_clear >= t_in - m)
            use = conflict & ~(reach >= gap)  # the nearer constraint of the two
            gap = np.where(use, reach, gap)
            v_lead = np.where(use, 0.0, v_lead)
        return gap, v_lead


def _clip(accel: float, p: IdmSettings) -> float:
    return min(max(accel, -p.max_decel_mps2), p.a0_mps2)


@dataclass(frozen=True)
class _EgoLane:
    """The ego's path: the reference with a lateral offset ``d0`` (m, + left) at the
    ego's arc ``s0`` that returns to 0 along a half-cosine over ``return_m``."""

    s0: float
    d0: float
    return_m: float

    @classmethod
    def of(cls, request: PlanRequest, reference: np.ndarray, p: IdmSettings) -> _EgoLane:
        ego = request.ego
        dist, arc = project(reference, ego.xy[None])
        d = np.diff(reference, axis=0)
        cum = geometry.cumulative_lengths(reference[None])[0]
        seg = int(np.clip(np.searchsorted(cum, arc[0], side="right") - 1, 0, len(d) - 1))
        foot = np.array([np.interp(arc[0], cum, reference[:, c]) for c in (0, 1)])
        rel = ego.xy - foot
        side = 1.0 if d[seg, 0] * rel[1] - d[seg, 1] * rel[0] >= 0.0 else -1.0
        speed = max(ego.speed_mps, request.target_speed_mps, 0.0)
        return cls(
            s0=float(arc[0]),
            d0=side * float(dist[0]),
            return_m=max(p.lane_return_s * speed, p.lane_return_min_m),
        )

    def offset_at(self, arc: np.ndarray) -> np.ndarray:
        """The path's lateral offset (m) at arc lengths ``arc`` (any shape)."""
        x = np.clip((np.asarray(arc) - self.s0) / self.return_m, 0.0, 1.0)
        return self.d0 * 0.5 * (1.0 + np.cos(np.pi * x))

    def points(self, reference: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points ``(T, 2)`` and headings ``(T,)`` of the path at arc lengths ``s``."""
        path = reference[None]
        cum = geometry.cumulative_lengths(path)
        xy, seg = geometry.interpolate(path, cum, s[None])
        d = np.diff(reference, axis=0)
        base = np.arctan2(d[:, 1], d[:, 0])[np.minimum(seg[0], len(d) - 1)]
        normal = np.stack([-np.sin(base), np.cos(base)], axis=1)
        x = np.clip((s - self.s0) / self.return_m, 0.0, 1.0)
        slope = -self.d0 * 0.5 * np.pi / self.return_m * np.sin(np.pi * x)
        return xy[0] + normal * self.offset_at(s)[:, None], base + np.arctan(slope)


def _corridor(c: PathCoords, lane: _EgoLane, ego_width_m: float, p: IdmSettings) -> np.ndarray:
    """``(K, T)``: the box, projected inside the reference, comes within the ego's half
    width plus the margin of the ego's path (the module's docstring)."""
    reach = ego_width_m / 2.0 + p.corridor_margin_m + c.half_across_m
    return np.asarray(c.on_path & (np.abs(c.offset_m - lane.offset_at(c.arc_m)) < reach))


@functools.lru_cache(maxsize=4)
def _free_road_profile(delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IDM on a free road from standstill in units of the target speed ``v0`` and the
    acceleration ``a0`` (``du/dtau = 1 - u^delta``, ``dxi/dtau = u`` with ``u = v / v0``,
    ``tau = t a0 / v0``, ``xi = x a0 / v0^2``): the same curve for every v0 and a0.
    Returns ``tau``, ``u`` and ``xi`` on a grid of 0.01 up to tau = 20 (u > 0.9999)."""
    step = 0.01
    n = 2001
    u = np.zeros(n)
    xi = np.zeros(n)
    for i in range(n - 1):  # once per process: RK4 of an autonomous ODE
        ui = u[i]
        k1 = 1.0 - ui**delta
        k2 = 1.0 - (ui + 0.5 * step * k1) ** delta
        k3 = 1.0 - (ui + 0.5 * step * k2) ** delta
        k4 = 1.0 - (ui + step * k3) ** delta
        u[i + 1] = ui + step * (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
        xi[i + 1] = xi[i] + 0.5 * step * (ui + u[i + 1])
    return np.arange(n) * step, u, xi


def free_road_time_s(
    distance_m: np.ndarray, v_mps: float, v0_mps: float, a0_mps2: float, delta: float
) -> np.ndarray:
    """Time (s) the ego needs to cover ``distance_m`` (any shape; 0 where not positive)
    on a free road under IDM from speed ``v_mps`` towards ``v0_mps``. At or above the
    target speed it keeps its speed (IDM would slow it towards v0: a little later)."""
    dist = np.maximum(np.asarray(distance_m, dtype=np.float64), 0.0)
    tau, u, xi = _free_road_profile(float(delta))
    ratio = v_mps / v0_mps
    if ratio >= u[-1]:
        return dist / max(v_mps, 1e-9)
    tau0 = float(np.interp(ratio, u, tau))
    xi0 = float(np.interp(tau0, tau, xi))
    target = xi0 + dist * a0_mps2 / v0_mps**2
    beyond = tau[-1] + (target - xi[-1]) / u[-1]  # past the table: at u[-1]
    tau_end = np.where(target <= xi[-1], np.interp(target, xi, tau), beyond)
    return (tau_end - tau0) * v0_mps / a0_mps2
