"""Reactive agents for the closed loop: vehicles follow their logged path with IDM speed.

Each reactive agent moves along its *rail*, its own recorded positions over the scene (as
Waymax's ``IDMRoutePolicy`` does), with one state: its progress along the rail (m) and its
speed (m/s). Its acceleration is the IDM's (Treiber, Hennecke, Helbing 2000;
:mod:`replay.planning.idm_law`, shared with the IDM planner)::

    a = a0 * (1 - (v / v0)^delta - (s* / s)^2),   s* = s0 + max(0, v T + v (v - v_l) / (2 sqrt(a0 b)))

clipped to ``[-b, a0]``; speed stays >= 0. ``s`` is the bumper-to-bumper gap to the
leader, ``v_l`` the leader's speed projected on the follower's heading (nuPlan's rule).

**Leader search** (:func:`find_leaders`), one broadcast over (agent, obstacle, probe): the
agent's own box is probed at ``L`` points along its rail ahead (0 m, then evenly up to
its look-ahead ``10 m + v T + v^2 / b``), and every probe is tested against every
obstacle's current box (the ego, the other reactive agents, the agents that replay their
log). The first probe that touches an obstacle whose centre lies ahead of the agent's
centre gives the leader; the gap is refined within that probe step by projecting the
obstacle's corners on the follower's heading. Pairs whose centres are farther apart than
the look-ahead plus both half-diagonals cannot touch and are never probed.

**Update**: every agent's acceleration comes from the same current state and all move at
once (vectorised, simultaneous). nuPlan moves its IDM agents one after the other, each
seeing the ones already moved, so the two do not match step for step.

Pure numpy; no scene I/O (the closed loop builds the rails from a scene's tracks).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from replay.planning import idm_law
from risk import geometry
from risk.hindsight import box_corners, boxes_overlap


@dataclass(frozen=True, kw_only=True)
class ReactiveSettings:
    """IDM of the reactive agents; units in the names.

    Chosen between nuPlan's agents (a0 1.0, b 2.0 m/s², exponent 4, T 1.5 s, s0 1 m) and
    Waymax's (2.0, 4.0, 4, 2.0 s, 2 m): ``b`` 4 m/s² because the recorded drivers brake
    that hard when a car cuts in, and a follower clipped at 2 m/s² rear-ends any ego that
    brakes harder than a comfortable stop; ``a0`` 2 m/s² as recorded urban starts;
    ``T`` 1.5 s as nuPlan (closer to the recorded motorway headways than 2 s); ``s0`` 2 m
    as Waymax (a queued car's bumper gap in the drone recordings); exponent 4 as both.
    """

    accel_mps2: float = 2.0
    decel_mps2: float = 4.0
    exponent: float = 4.0
    headway_s: float = 1.5
    min_gap_m: float = 2.0
    min_lookahead_m: float = 10.0
    probes: int = 48
    #: A gap below this (m) counts as this (the IDM's s is a divisor).
    least_gap_m: float = 0.1

    @property
    def law(self) -> idm_law.IdmLaw:
        """The IDM's parameters for :mod:`replay.planning.idm_law`."""
        return idm_law.IdmLaw(
            accel_mps2=self.accel_mps2, decel_mps2=self.decel_mps2, headway_s=self.headway_s,
            min_gap_m=self.min_gap_m, exponent=self.exponent,
        )  # fmt: skip


@dataclass(frozen=True, eq=False)  # not slotted: the search index is cached on it
class Rails:
    """The logged paths of ``K`` agents: ``xy`` (K, P, 2) m, ``heading_rad`` (K, P)
    (unwrapped along each rail), ``arc_m`` (K, P) arc length from the rail's start. Each
    rail ends with a straight extension along its last heading, so that probes ahead of
    an agent near the end of its log stay defined."""

    xy: np.ndarray
    heading_rad: np.ndarray
    arc_m: np.ndarray

    @classmethod
    def from_positions(
        cls, xy: np.ndarray, heading_rad: np.ndarray, *, extend_m: float = 500.0
    ) -> Rails:
        """Rails through ``xy`` (K, P, 2) with headings ``heading_rad`` (K, P), extended
        straight by ``extend_m`` past the last point (repeated points are allowed)."""
        heading = np.unwrap(np.asarray(heading_rad, dtype=np.float64), axis=1)
        xy = np.asarray(xy, dtype=np.float64)
        last = heading[:, -1]
        end = xy[:, -1] + extend_m * np.stack([np.cos(last), np.sin(last)], axis=1)
        xy_ext = np.concatenate([xy, end[:, None]], axis=1)
        heading_ext = np.concatenate([heading, last[:, None]], axis=1)
        return cls(xy_ext, heading_ext, geometry.cumulative_lengths(xy_ext))

    @property
    def n(self) -> int:
        return int(self.xy.shape[0])

    def rows(self, which: np.ndarray) -> Rails:
        """The rails of the agents ``which`` (an index array)."""
        return Rails(self.xy[which], self.heading_rad[which], self.arc_m[which])

    @functools.cached_property
    def _columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x, y and heading ``(K, P)`` flattened, contiguous: read at every step."""
        return (
            np.ascontiguousarray(self.xy[..., 0]).ravel(),
            np.ascontiguousarray(self.xy[..., 1]).ravel(),
            np.ascontiguousarray(self.heading_rad).ravel(),
        )

    @functools.cached_property
    def _search(self) -> tuple[np.ndarray, np.ndarray]:
        """Every rail's arc lengths shifted by a per-rail offset and flattened (sorted
        as a whole), and the offsets ``(K,)``: one ``searchsorted`` finds the segments of
        any rails' queries (as :func:`risk.geometry.locate` does, which builds these
        ``(K, P)`` keys anew at each call; rails are read at every step of a run)."""
        span = 2.0 * float(self.arc_m.max(initial=0.0)) + 1.0
        offset = np.arange(self.n, dtype=np.float64) * span
        return (self.arc_m + offset[:, None]).ravel(), offset

    def poses(
        self, arc_m: np.ndarray, rows: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Points ``(R, L, 2)`` and headings ``(R, L)`` at arc lengths ``arc_m`` (R, L) of
        the rails ``rows`` (an index array; all ``K`` rails when None), linearly
        interpolated as :func:`risk.geometry.interpolate_components` (the same values)."""
        cum = self.arc_m
        p = cum.shape[1]
        which = np.arange(self.n) if rows is None else np.asarray(rows, dtype=np.int64)
        s = np.clip(arc_m, 0.0, cum[which, -1:])
        keys, offset = self._search
        base = (which * p)[:, None]
        found = np.searchsorted(keys, s + offset[which, None], side="right")
        idx = np.clip(found - 1 - base, 0, p - 1)
        # The offset's rounding can put a query within ~1e-10 m of a breakpoint on the
        # wrong side: then the exact per-row search (rare; the same answer either way).
        flat_cum = cum.ravel()
        too_high = (idx > 0) & (np.take(flat_cum, idx + base) > s)
        too_low = (idx < p - 1) & (np.take(flat_cum, np.minimum(idx + 1, p - 1) + base) <= s)
        if too_high.any() or too_low.any():
            idx = geometry.locate(cum[which], s)
        g = np.minimum(idx, p - 2) + base
        c0 = np.take(flat_cum, g)
        seg_len = np.take(flat_cum, g + 1) - c0
        ok = seg_len > 0
        frac = np.where(ok, (s - c0) / np.where(ok, seg_len, 1.0), 0.0)
        np.clip(frac, 0.0, 1.0, out=frac)
        x, y, heading = (
            (np.take(comp, g + 1) - a) * frac + a
            for comp in self._columns
            for a in (np.take(comp, g),)
        )
        return np.stack([x, y], axis=-1), heading


@dataclass(frozen=True, eq=False)
class Boxes:
    """``J`` obstacles now: centre ``xy`` (J, 2) m, ``heading_rad``, ``length_m``,
    ``width_m``, ``speed_mps`` (J,) along their heading."""

    xy: np.ndarray
    heading_rad: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    speed_mps: np.ndarray

    @property
    def n(self) -> int:
        return int(self.xy.shape[0])


def lookahead_m(speed_mps: np.ndarray, settings: ReactiveSettings) -> np.ndarray:
    """How far ahead (m) each agent looks for a leader: past its stopping distance at
    ``b`` twice over, so that a standing obstacle is seen before IDM must brake harder
    than ``b``."""
    v = np.asarray(speed_mps, dtype=np.float64)
    return settings.min_lookahead_m + v * settings.headway_s + v * v / settings.decel_mps2


def find_leaders(
    rails: Rails,
    arc_m: np.ndarray,
    speed_mps: np.ndarray,
    length_m: np.ndarray,
    width_m: np.ndarray,
    obstacles: Boxes,
    self_index: np.ndarray,
    settings: ReactiveSettings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each agent's leader among ``obstacles``.

    ``arc_m``, ``speed_mps``, ``length_m``, ``width_m`` (K,): the agents' progress along
    their rails and their sizes; ``self_index`` (K,): each agent's own row among the
    obstacles (-1 when it is not one). Returns the bumper-to-bumper gap (K,) in m (inf
    without a leader), the leader's speed projected on the follower's heading (K,) m/s
    (0 without one) and the leader's row among the obstacles (K,) (-1 without one).
    """
    k = rails.n
    gap = np.full(k, np.inf)
    lead_speed = np.zeros(k)
    leader = np.full(k, -1, dtype=np.int64)
    if k == 0 or obstacles.n == 0:
        return gap, lead_speed, leader
    reach = lookahead_m(speed_mps, settings)  # (K,)
    probes = settings.probes
    step = reach / (probes - 1)  # (K,)
    offsets = np.arange(probes)[None, :] * step[:, None]  # (K, L)
    xy_now, heading_now = rails.poses(arc_m[:, None])
    xy_now, heading_now = xy_now[:, 0], heading_now[:, 0]  # (K, 2), (K,)
    # Candidate pairs: ahead of the agent's centre and within reach of its probes.
    rel = obstacles.xy[None, :, :] - xy_now[:, None, :]  # (K, J, 2)
    ahead = rel[..., 0] * np.cos(heading_now)[:, None] + rel[..., 1] * np.sin(heading_now)[:, None]
    half_diag_k = 0.5 * np.hypot(length_m, width_m)
    half_diag_j = 0.5 * np.hypot(obstacles.length_m, obstacles.width_m)
    near = np.hypot(rel[..., 0], rel[..., 1]) <= (
        reach[:, None] + half_diag_k[:, None] + half_diag_j[None, :]
    )
    candidate = near & (ahead > 0.0)
    candidate[np.arange(k)[self_index >= 0], self_index[self_index >= 0]] = False
    ki, ji = np.nonzero(candidate)  # (C,)
    if ki.size == 0:
        return gap, lead_speed, leader
    # Probe poses only for the agents with a candidate (rows of ``probing``).
    probing, ki = np.unique(ki, return_inverse=True)
    probe_xy, probe_heading = rails.poses(arc_m[probing, None] + offsets[probing], probing)
    agent = probing[ki]  # (C,) the agent of each pair
    hit = boxes_overlap(
        probe_xy[ki, :, 0], probe_xy[ki, :, 1], probe_heading[ki],
        length_m[agent, None], width_m[agent, None],
        obstacles.xy[ji, 0, None], obstacles.xy[ji, 1, None], obstacles.heading_rad[ji, None],
        obstacles.length_m[ji, None], obstacles.width_m[ji, None],
    )  # (C, L)  # fmt: skip
    any_hit = hit.any(axis=1)
    first = np.where(any_hit, np.argmax(hit, axis=1), probes)  # (C,)
    # The agent's first touching probe over all its obstacles; only obstacles touched there.
    first_of_agent = np.full(k, probes)
    np.minimum.at(first_of_agent, agent, first)
    at_first = any_hit & (first == first_of_agent[agent])
    ki, agent, ji, first = ki[at_first], agent[at_first], ji[at_first], first[at_first]
    if ki.size == 0:
        return gap, lead_speed, leader
    # Refine within the probe step: the obstacle's nearest corner along the heading of
    # the last free probe, minus the follower's half length (exact on a straight rail).
    before = np.maximum(first - 1, 0)
    base_xy = probe_xy[ki, before]  # (C', 2)
    base_heading = probe_heading[ki, before]
    corners = box_corners(
        obstacles.xy[ji, 0], obstacles.xy[ji, 1], obstacles.heading_rad[ji],
        obstacles.length_m[ji], obstacles.width_m[ji],
    )  # (C', 4, 2)  # fmt: skip
    along = (corners[..., 0] - base_xy[:, None, 0]) * np.cos(base_heading)[:, None] + (
        corners[..., 1] - base_xy[:, None, 1]
    ) * np.sin(base_heading)[:, None]
    low = offsets[agent, before]
    high = offsets[agent, first]
    pair_gap = np.where(
        first == 0, 0.0, np.clip(low + along.min(axis=1) - 0.5 * length_m[agent], low, high)
    )
    # The nearest obstacle per agent (ties: the lower row).
    order = np.lexsort((ji, pair_gap, agent))
    ki, agent, ji, pair_gap = ki[order], agent[order], ji[order], pair_gap[order]
    keep = np.r_[True, agent[1:] != agent[:-1]]
    ki, agent, ji, pair_gap = ki[keep], agent[keep], ji[keep], pair_gap[keep]
    gap[agent] = pair_gap
    leader[agent] = ji
    follower_heading = probe_heading[ki, first_of_agent[agent]]
    lead_speed[agent] = obstacles.speed_mps[ji] * np.cos(
        obstacles.heading_rad[ji] - follower_heading
    )
    return gap, lead_speed, leader


def idm_acceleration(
    speed_mps: np.ndarray,
    desired_mps: np.ndarray,
    gap_m: np.ndarray,
    lead_speed_mps: np.ndarray,
    settings: ReactiveSettings,
) -> np.ndarray:
    """The IDM acceleration (K,) m/s² (:func:`replay.planning.idm_law.idm_acceleration`),
    clipped to ``[-decel, accel]``; an infinite gap is the free road, a gap below
    ``least_gap_m`` counts as that (the gap is a divisor)."""
    v0 = np.maximum(np.asarray(desired_mps, dtype=np.float64), 0.1)
    gap = np.maximum(np.asarray(gap_m, dtype=np.float64), settings.least_gap_m)
    accel = idm_law.idm_acceleration(
        np.asarray(speed_mps, dtype=np.float64), v0, gap, lead_speed_mps, settings.law
    )
    return np.clip(accel, -settings.decel_mps2, settings.accel_mps2)


def advance(
    arc_m: np.ndarray, speed_mps: np.ndarray, accel_mps2: np.ndarray, dt_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Progress and speed after ``dt_s`` at constant acceleration, never reversing (an
    agent that would stop within the step stops where it reaches 0)."""
    v1 = speed_mps + accel_mps2 * dt_s
    stops = v1 < 0.0
    braking = np.where(stops, np.minimum(accel_mps2, -1e-9), 1.0)
    travel = np.where(
        stops, speed_mps**2 / (-2.0 * braking), 0.5 * (speed_mps + np.maximum(v1, 0.0)) * dt_s
    )
    return arc_m + travel, np.maximum(v1, 0.0)


def step(
    rails: Rails,
    arc_m: np.ndarray,
    speed_mps: np.ndarray,
    desired_mps: np.ndarray,
    length_m: np.ndarray,
    width_m: np.ndarray,
    obstacles: Boxes,
    self_index: np.ndarray,
    dt_s: float,
    settings: ReactiveSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """One simultaneous IDM step of every agent: (progress, speed) after ``dt_s``."""
    gap, lead_speed, _ = find_leaders(
        rails, arc_m, speed_mps, length_m, width_m, obstacles, self_index, settings
    )
    accel = idm_acceleration(speed_mps, desired_mps, gap, lead_speed, settings)
    return advance(arc_m, speed_mps, accel, dt_s)
