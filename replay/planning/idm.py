"""IDM along the reference path: a planner that needs nothing beyond numpy.

The Intelligent Driver Model (Treiber, Hennecke, Helbing, Phys. Rev. E 62, 2000)::

    a = a0 * (1 - (v / v0)^delta - (s*(v, dv) / s)^2),
    s*(v, dv) = s0 + max(0, v * T + v * dv / (2 * sqrt(a0 * b)))

with ``v`` the ego's speed, ``v0`` the target speed, ``s`` the bumper-to-bumper gap to the
leader and ``dv = v - v_leader``. The ego is simulated forward along its reference path at
the request's ``dt_s`` over the horizon (a ballistic update that never reverses).

Who counts, at each step (vectorised over agents; the loop runs over time steps only):

- **Leaders**: agents whose predicted box overlaps the ego's lane corridor (lateral offset
  of the centre from the reference below half the lane width plus the box's half extent
  across the path), whose centre lies ahead of the ego's centre along the path, and which
  move along the path (heading within 45 degrees of it). Gap and speed are measured along
  the path.
- **Conflicts** (crossing or oncoming agents in the corridor ahead): the first point ahead
  where the agent's box is in the corridor is a conflict point. When the ego, at its
  current speed, would occupy that point within ``time_margin_s`` of the agent's stay in
  the corridor, the agent acts as a stopped leader there: the ego yields.

Each agent gives one IDM acceleration; the least counts (clipped to ``[-max_decel, a0]``).
``blocking_id``: the agent with the least acceleration at the first step where it lies
more than ``blocking_margin_mps2`` below the free-road acceleration.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from replay.planning.path_coords import PathCoords, path_coords, project
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
    blocking.
    """

    a0_mps2: float = 1.0
    b_mps2: float = 1.5
    headway_s: float = 1.5
    s0_m: float = 2.0
    delta: float = 4.0
    max_decel_mps2: float = 8.0
    time_margin_s: float = 1.5
    blocking_margin_mps2: float = 0.1


class IdmPlanner:
    """IDM longitudinal control along the ego's reference path, with yielding at conflict
    points of crossing agents (see the module's docstring)."""

    name = "idm"

    def __init__(self, settings: IdmSettings | None = None) -> None:
        self.settings = IdmSettings() if settings is None else settings

    # ------------------------------------------------------------------ may_matter
    def may_matter(self, request: PlanRequest) -> np.ndarray:
        """``(K,)`` bool: False for agents the simulation provably never reads.

        The argument. The planner reads an agent at step ``k`` only through ``gap`` (NaN
        means no constraint, and its acceleration term is then +inf, which leaves the
        minimum over agents unchanged):

        - as a leader: its box is in the corridor at step ``k`` (``lateral_m < lane_width
          / 2 + half_across_m``), it moves along the path, and its arc exceeds the ego's
          arc ``s_k``;
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
        c = path_coords(request.reference, a)
        inside = _in_corridor(c, request.lane_width_m)
        s0 = float(project(request.reference, request.ego.xy[None])[1][0])
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
        ref = request.reference
        ego = request.ego
        half_ego = ego.length_m / 2.0
        v0 = max(request.target_speed_mps, 0.1)
        sqrt_ab = 2.0 * math.sqrt(p.a0_mps2 * p.b_mps2)

        agents = request.agents.on_times(times)  # the plan's steps
        ids = agents.ids
        if agents.n:
            coords = path_coords(ref, agents)
            inside = _in_corridor(coords, request.lane_width_m)
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
        s[0] = float(project(ref, ego.xy[None])[1][0])
        v[0] = max(ego.speed_mps, 0.0)
        blocking_id = -1
        for k in range(n_steps - 1):
            a_free = p.a0_mps2 * (1.0 - (v[k] / v0) ** p.delta)
            accel = a_free
            if ids.size:
                gap, v_lead = self._constraints(
                    coords, inside, crossing if any_crossing else None, t_out, k, times,
                    s[k], v[k], half_ego,
                )  # fmt: skip
                s_star = p.s0_m + np.maximum(
                    0.0, v[k] * p.headway_s + v[k] * (v[k] - v_lead) / sqrt_ab
                )
                with np.errstate(divide="ignore", invalid="ignore"):
                    a_agent = a_free - p.a0_mps2 * (s_star / gap) ** 2
                a_agent = np.where(gap > 0.0, a_agent, -np.inf)  # overlap: full braking
                a_agent = np.where(np.isnan(gap), np.inf, a_agent)  # no constraint
                worst = int(np.argmin(a_agent))
                accel = min(a_free, float(a_agent[worst]))
                if blocking_id < 0 and accel < a_free - p.blocking_margin_mps2:
                    blocking_id = int(ids[worst])
            accel = min(max(accel, -p.max_decel_mps2), p.a0_mps2)
            v_next = v[k] + accel * dt
            if v_next >= 0.0:
                s[k + 1] = s[k] + v[k] * dt + 0.5 * accel * dt * dt
                v[k + 1] = v_next
            else:  # stops within the step
                s[k + 1] = s[k] + v[k] ** 2 / (2.0 * -accel)
                v[k + 1] = 0.0
        xy, heading = _along(ref, s)
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
            speed = max(v_ego, 1e-3)
            t_arrive = times[k] + (s_c - half - s_ego - half_ego) / speed
            t_clear = times[k] + (s_c + half - s_ego + half_ego) / speed
            m = self.settings.time_margin_s
            conflict = has & (t_arrive <= t_out + m) & (t_clear >= t_in - m)
            gap_c = s_c - half - s_ego - half_ego
            use = conflict & ~(gap_c >= gap)  # the nearer constraint of the two
            gap = np.where(use, gap_c, gap)
            v_lead = np.where(use, 0.0, v_lead)
        return gap, v_lead


def _in_corridor(c: PathCoords, lane_width_m: float) -> np.ndarray:
    """``(K, T)``: the box overlaps the ego's lane corridor around the reference."""
    return np.asarray(c.lateral_m < lane_width_m / 2.0 + c.half_across_m)


def _along(reference: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(T, 2)`` and headings ``(T,)`` at arc lengths ``s`` along the reference."""
    path = reference[None]
    cum = geometry.cumulative_lengths(path)
    xy, seg = geometry.interpolate(path, cum, s[None])
    d = np.diff(reference, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])[np.minimum(seg[0], len(d) - 1)]
    return xy[0], heading
