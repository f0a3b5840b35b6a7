"""``pdm``: a PDM-Closed-style planner in numpy (after Dauner et al., CoRL 2023).

One call (:meth:`PdmPlanner.plan`), every stage vectorised over proposals ``P``, agents
``K`` and time ``T`` (the only Python loops run over time steps; those loops, the
projections onto the centreline and the scorer's box tests run compiled,
:mod:`replay.planning.pdm_kernel`, unless ``PdmPlanner(compiled=False)``: the numpy forms,
kept as the oracles):

1. **Centreline**: the request's reference (the ego's route), extended straight at both
   ends so that no projection is clamped at its ends (the phantom of issue 35).
2. **Proposals**: IDM along the centreline shifted by each lateral offset (0, +1, -1 m;
   merged in from the ego's own offset, :func:`merge`), at each target speed (0.2 ... 1.0
   of the request's target speed): 15, and braking proposals to a stop along the
   centreline (4.05 and 8 m/s^2), counted only when every IDM proposal collides at
   fault: ``P = 17``. One
   state array ``(P, T, N_PROPOSAL)`` with the columns of :class:`ProposalColumn`. Every
   2 steps (held in between, as PDM) each proposal's leader is the nearest forecast agent
   ahead whose box reaches into the proposal's corridor (the shifted path widened by the
   ego's half width, as PDM's), up to the corridor's end (``max(target, ego speed) *
   horizon`` ahead).
3. **Simulation**: each proposal tracked by the kinematic bicycle under the batch LQR
   tracker (:mod:`replay.planning.lqr`), from the ego's actual pose, over the whole
   request horizon.
4. **Scoring** as PDM (:class:`MultiMetric`, :class:`WeightedMetric` rows ``(M, P)``):
   multiplicative at-fault collision (0, or 0.5 for objects of kind OTHER), drivable area,
   driving direction; weighted progress (5), time to collision (5), comfort (2);
   ``score = product * weighted mean``. Every agent is scored under two forecasts, its
   map-path one (the request's) and constant velocity along its current heading
   (PDM-Closed's; :class:`_Hypotheses`, extra rows of the scored agents): a proposal
   collides at fault when it does under either.
5. **Decision**: the best proposal (its IDM trajectory, as PDM: the simulation is for the
   scores; among proposals that all score 0, the one that collides at fault latest), or
   an emergency brake when it collides at fault within 2 s while the ego drives at 5 m/s
   or less.

Where it departs from the paper and why: ``docs/planners.md``, section "pdm".

``may_matter`` is exact in the sense of the planner's own arithmetic: an agent is read
only by the leader search (stage 2) and by the box tests of the scorer, whose candidate
pairs come from a bounding-circle test against the simulated ego boxes (stage 4). The
planner itself keeps only the agents that pass either test (:meth:`PdmPlanner._relevant`)
before any number depends on them, so an agent that passes neither leaves every array
bit for bit the same.
"""

from __future__ import annotations

import functools
import math
import time
import types
from dataclasses import dataclass, replace
from enum import IntEnum

import numpy as np
from scipy.signal import savgol_filter

from replay.planning import lqr
from replay.planning.types import (
    STOP_SPEED_MPS,
    AgentForecasts,
    EgoState,
    Plan,
    PlanRequest,
    plan_times,
)
from risk import geometry
from risk.frame import Kind
from risk.hindsight import TOUCH_M, boxes_overlap

#: The reference is extended straight by this much at both ends (m): agents beyond its
#: ends project onto the extension instead of onto its end points.
REFERENCE_EXTENSION_M = 1000.0


class ProposalColumn(IntEnum):
    """Columns of the proposal array ``(P, T, N_PROPOSAL)``: box centre (m), heading
    (rad), speed (m/s), progress along the reference (m)."""

    X = 0
    Y = 1
    HEADING = 2
    SPEED = 3
    PROGRESS = 4


N_PROPOSAL = len(ProposalColumn)


class MultiMetric(IntEnum):
    """Rows of the multiplicative metrics ``(3, P)``."""

    NO_AT_FAULT_COLLISION = 0
    DRIVABLE_AREA = 1
    DRIVING_DIRECTION = 2


class WeightedMetric(IntEnum):
    """Rows of the weighted metrics ``(3, P)``."""

    PROGRESS = 0
    TTC = 1
    COMFORT = 2


@dataclass(frozen=True, kw_only=True)
class PdmSettings:
    """PDM-Closed's constants (tuplan_garage ``pdm_closed_planner.yaml``, the scorer and the
    emergency brake) unless said otherwise.

    ``drivable_margin_m``: how far a corner may lie outside the usable lanes (nuPlan's
    drivable-area metric tolerates 0.3 m; our lanes, unlike nuPlan's drivable layer, have
    no shoulders). ``blocking_margin_mps2``: how far below the free-road acceleration a
    leader must push the chosen proposal to be reported as blocking (as ``idm``).
    ``leader_update_steps``: the leader search runs every this many steps and its answer
    is held in between (PDM: 2). ``merge_time_s``, ``merge_min_m``: a proposal's path
    starts at the ego's lateral offset from the reference and merges into its own offset
    over this much travel at the ego's speed (at least ``merge_min_m``), a smoothstep
    (PDM's paths start at their offset: nuPlan's tracker closes the gap).
    ``brake_proposals_mps2``: braking proposals (our addition): along the centreline at
    each of these decelerations to a stop (nuPlan's comfort bound 4.05 m/s^2; 8 m/s^2, a
    car's hard braking and the tracker's limit), scored like the others and eligible only
    when every IDM proposal collides at fault; among proposals that all score 0 the one
    whose first at-fault collision comes latest (none: never) wins. PDM's IDM brakes at
    most at 3 m/s^2 and its emergency brake acts only up to 5 m/s, so above that, with
    every proposal colliding, it kept the slowest IDM proposal and drove into a car
    turning across its lane at 3 m/s^2 (issue 35's closed loop).
    ``score_tie``: proposals scoring within this of the best tie; among them the one
    nearest the centreline wins, then the higher score. PDM takes the exact argmax, and a
    sideways proposal then wins by trifles: 1e-6 more progress on a straight road, or, in
    closed loop creeping up to a standing car, 0.03 m of 4.7 m (0.0025 of the score), so
    that the ego weaved from one side to the other.
    ``constant_velocity_s``: besides its map-path forecast, every agent is scored under a
    second hypothesis, straight on at its current speed and heading (PDM-Closed's only
    forecast), up to this many seconds ahead (0: none); a proposal collides at fault when
    it does so under either. ``constant_velocity_tolerance_m``: an agent whose
    constant-velocity forecast stays this close to its map-path forecast over that window
    (centres, plus half its length times the heading difference) gets no second
    hypothesis: it would find the same contacts. ``drop_unavoidable_twins``: a
    constant-velocity row that every proposal, the braking ones included, hits at fault
    is left out of the collision and TTC metrics (it cannot tell the proposals apart: it
    would zero them all, and the choice among zeros would ignore what the map-path
    forecasts say).
    """

    target_fractions: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8, 1.0)
    lateral_offsets_m: tuple[float, ...] = (0.0, 1.0, -1.0)
    idm_accel_mps2: float = 1.5
    idm_decel_mps2: float = 3.0
    idm_headway_s: float = 1.5
    idm_min_gap_m: float = 1.0
    idm_exponent: float = 10.0
    weight_progress: float = 5.0
    weight_ttc: float = 5.0
    weight_comfort: float = 2.0
    static_collision_score: float = 0.5
    stopped_speed_mps: float = 0.05
    ttc_stopped_speed_mps: float = 5e-3
    ttc_lookahead_s: tuple[float, ...] = (0.0, 0.3, 0.6, 0.9)
    ahead_angle_rad: float = math.radians(30.0)
    behind_angle_rad: float = math.radians(150.0)
    progress_min_m: float = 0.1
    direction_ok_m: float = 2.0
    direction_violation_m: float = 6.0
    drivable_margin_m: float = 0.3
    brake_within_s: float = 2.0
    brake_max_speed_mps: float = 5.0
    brake_decel_mps2: float = 4.05
    brake_proposals_mps2: tuple[float, ...] = (4.05, 8.0)
    blocking_margin_mps2: float = 0.1
    leader_update_steps: int = 2
    merge_time_s: float = 2.0
    merge_min_m: float = 5.0
    score_tie: float = 0.01
    constant_velocity_s: float = 5.0
    constant_velocity_tolerance_m: float = 0.1
    drop_unavoidable_twins: bool = True
    # nuPlan's comfort bounds
    max_lon_accel_mps2: float = 2.40
    min_lon_accel_mps2: float = -4.05
    max_abs_lat_accel_mps2: float = 4.89
    max_abs_yaw_rate: float = 0.95
    max_abs_yaw_accel: float = 1.93
    max_abs_lon_jerk: float = 4.13
    max_abs_jerk: float = 8.37


# ---------------------------------------------------------------------- the centreline
@dataclass(frozen=True, eq=False)
class _Centreline:
    """The extended reference: vertices ``(V, 2)``, arc length at them ``(V,)`` (0 at the
    original start), the tangent heading at them ``(V,)`` (unwrapped; the mean of the
    adjacent segments) and each segment's heading ``(V - 1,)``."""

    xy: np.ndarray
    arc_m: np.ndarray
    vertex_heading: np.ndarray
    segment_heading: np.ndarray
    compiled: bool = False  # project with pdm_kernel.project (else numpy, the oracle)

    @classmethod
    def of(cls, reference: np.ndarray, compiled: bool = False) -> _Centreline:
        keep = np.r_[True, np.any(np.diff(reference, axis=0) != 0.0, axis=1)]
        ref = reference[keep]
        d = np.diff(ref, axis=0)
        first = d[0] / np.hypot(*d[0])
        last = d[-1] / np.hypot(*d[-1])
        xy = np.vstack(
            [ref[0] - REFERENCE_EXTENSION_M * first, ref, ref[-1] + REFERENCE_EXTENSION_M * last]
        )
        seg = np.diff(xy, axis=0)
        seg_heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
        # a vertex's tangent: the mean of its two segments' directions (unwrapped)
        vertex = np.r_[seg_heading[0], 0.5 * (seg_heading[:-1] + seg_heading[1:]), seg_heading[-1]]
        arc = geometry.cumulative_lengths(xy[None])[0] - REFERENCE_EXTENSION_M
        return cls(
            xy=xy, arc_m=arc, vertex_heading=vertex, segment_heading=seg_heading, compiled=compiled
        )

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arc length, signed lateral offset (+ left) and the path's heading there, each
        ``points.shape[:-1]``, of points ``(..., 2)``."""
        shape = points.shape[:-1]
        flat = points.reshape(-1, 2)
        if self.compiled:
            arc, lateral, h = _kernel().project(flat, self.xy, self.arc_m, self.segment_heading)
            return arc.reshape(shape), lateral.reshape(shape), h.reshape(shape)
        dist, arc = geometry.project_points(flat, self.xy, self.arc_m)
        seg = np.clip(
            np.searchsorted(self.arc_m, arc, side="right") - 1, 0, len(self.segment_heading) - 1
        )
        h = self.segment_heading[seg]
        rel = flat - self.xy[seg]
        side = np.where(np.cos(h) * rel[:, 1] - np.sin(h) * rel[:, 0] >= 0.0, 1.0, -1.0)
        return arc.reshape(shape), (side * dist).reshape(shape), h.reshape(shape)

    def pose(self, arc_m: np.ndarray, offset_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points ``(..., 2)`` and headings at arc lengths ``arc_m`` on the centreline
        shifted ``offset_m`` to the left (broadcast together); the heading is interpolated
        between the vertices' tangents (continuous along the path)."""
        arc_m, offset_m = np.broadcast_arrays(arc_m, offset_m)
        seg = np.clip(
            np.searchsorted(self.arc_m, arc_m, side="right") - 1, 0, len(self.segment_heading) - 1
        )
        a0 = self.arc_m[seg]
        span = self.arc_m[seg + 1] - a0
        w = (arc_m - a0) / span
        xy = self.xy[seg] + w[..., None] * (self.xy[seg + 1] - self.xy[seg])
        heading = self.vertex_heading[seg] + w * (
            self.vertex_heading[seg + 1] - self.vertex_heading[seg]
        )
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
        return xy + offset_m[..., None] * normal, heading


# ---------------------------------------------------------------------- agents
@dataclass(frozen=True, eq=False)
class _AgentsAlong:
    """Agents on the plan's times in the centreline's coordinates, shapes ``(K, T)``:
    arc, signed lateral offset, the box's half extents along / across the path, speed
    along the path (finite differences of the forecast, projected on the path)."""

    arc_m: np.ndarray
    lateral_m: np.ndarray
    half_along_m: np.ndarray
    half_across_m: np.ndarray
    speed_along_mps: np.ndarray

    def rows(self, which: np.ndarray) -> _AgentsAlong:
        """The agents selected by a mask or index array ``(K,)``."""
        return _AgentsAlong(
            arc_m=self.arc_m[which],
            lateral_m=self.lateral_m[which],
            half_along_m=self.half_along_m[which],
            half_across_m=self.half_across_m[which],
            speed_along_mps=self.speed_along_mps[which],
        )

    @classmethod
    def of(cls, line: _Centreline, agents: AgentForecasts) -> _AgentsAlong:
        arc, lateral, path_h = line.project(agents.xy)
        rel = agents.heading_rad - path_h
        c, s = np.abs(np.cos(rel)), np.abs(np.sin(rel))
        half_l, half_w = agents.length_m[:, None] / 2.0, agents.width_m[:, None] / 2.0
        velocity = _velocities(agents)
        speed_along = velocity[..., 0] * np.cos(path_h) + velocity[..., 1] * np.sin(path_h)
        return cls(
            arc_m=arc,
            lateral_m=lateral,
            half_along_m=c * half_l + s * half_w,
            half_across_m=s * half_l + c * half_w,
            speed_along_mps=speed_along,
        )


def merge(
    arc_m: np.ndarray, offset_m: np.ndarray, s0: float, d0: float, length_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """A proposal path's lateral offset (m, + left) and its slope d offset / d arc at arc
    lengths ``arc_m``: ``d0`` (the ego's) at ``s0``, ``offset_m`` from ``s0 + length_m``
    on, a smoothstep between (broadcasting)."""
    u = np.clip((arc_m - s0) / length_m, 0.0, 1.0)
    left = 1.0 - u * u * (3.0 - 2.0 * u)  # share of d0 still in the offset
    offset = offset_m + (d0 - offset_m) * left
    slope = (d0 - offset_m) * (-6.0 * u * (1.0 - u)) / length_m
    return offset, slope


def _at_steps(agents: AgentForecasts, steps: np.ndarray) -> AgentForecasts:
    """The forecasts at some of their time indices ``steps`` (S,)."""
    return AgentForecasts(
        ids=agents.ids,
        kinds=agents.kinds,
        length_m=agents.length_m,
        width_m=agents.width_m,
        times_s=agents.times_s[steps],
        xy=agents.xy[:, steps],
        heading_rad=agents.heading_rad[:, steps],
    )


def _velocities(agents: AgentForecasts) -> np.ndarray:
    """Velocity ``(K, T, 2)`` (m/s) of the forecasts: forward differences, the last step
    repeated (zeros with a single time)."""
    if agents.times_s.size < 2:
        return np.zeros(agents.xy.shape)
    v = np.diff(agents.xy, axis=1) / np.diff(agents.times_s)[None, :, None]
    return np.concatenate([v, v[:, -1:]], axis=1)


def _current_speed(agents: AgentForecasts) -> np.ndarray:
    """``(K,)`` each agent's speed now: the request's when it carries it, else the
    forecast's mean speed (its polyline's length over the forecast's duration)."""
    if agents.speed_mps is not None:
        return np.maximum(agents.speed_mps, 0.0)
    duration = float(agents.times_s[-1] - agents.times_s[0]) if agents.times_s.size > 1 else 0.0
    if duration <= 0.0:
        return np.zeros(agents.n)
    step = np.hypot(*np.moveaxis(np.diff(agents.xy, axis=1), -1, 0))
    return np.asarray(step.sum(axis=1) / duration)


@dataclass(frozen=True, eq=False)
class _ConstantVelocity:
    """Every agent's constant-velocity forecast: straight on along its heading now at its
    speed now, boxes ``xy`` ``(K, T, 2)`` and ``heading_rad`` ``(K, T)``; ``twins``
    ``(J,)`` the agents whose forecast departs from their map-path one by more than
    ``constant_velocity_tolerance_m`` within the window (they get a second row);
    ``last_step``: the window's last time index (0: no second hypothesis)."""

    xy: np.ndarray
    heading_rad: np.ndarray
    twins: np.ndarray
    last_step: int

    @staticmethod
    def window(agents: AgentForecasts, settings: PdmSettings) -> int:
        """The last time index of the constant-velocity hypothesis (0: none)."""
        last = int(np.searchsorted(agents.times_s, settings.constant_velocity_s + 1e-9)) - 1
        return max(min(last, agents.times_s.size - 1), 0)

    @classmethod
    def of(
        cls, agents: AgentForecasts, settings: PdmSettings, among: np.ndarray | None = None
    ) -> _ConstantVelocity:
        """The forecasts of the agents ``among`` (an index array; default all); the rows
        of the others are left unset and none of them is a twin."""
        window = cls.window(agents, settings)
        if window < 1 or agents.n == 0:
            return cls(xy=agents.xy, heading_rad=agents.heading_rad, twins=np.zeros(0, np.int64),
                       last_step=0)  # fmt: skip
        rows = np.arange(agents.n) if among is None else np.asarray(among, dtype=np.int64)
        xy = np.zeros(agents.xy.shape)
        heading = np.zeros(agents.heading_rad.shape)
        if rows.size == 0:
            return cls(xy=xy, heading_rad=heading, twins=rows, last_step=window)
        chosen = agents.subset(rows) if among is not None else agents
        heading0 = chosen.heading_rad[:, 0]
        travel = _current_speed(chosen)[:, None] * (chosen.times_s - chosen.times_s[0])[None, :]
        direction = np.stack([np.cos(heading0), np.sin(heading0)], axis=-1)  # (K', 2)
        xy[rows] = chosen.xy[:, :1] + travel[..., None] * direction[:, None, :]  # (K', T, 2)
        heading[rows] = heading0[:, None]
        ahead = slice(0, window + 1)
        turned = np.abs(lqr.wrap_angle(heading[rows, ahead] - chosen.heading_rad[:, ahead]))
        apart = np.hypot(*np.moveaxis(xy[rows, ahead] - chosen.xy[:, ahead], -1, 0))
        apart = apart + chosen.length_m[:, None] / 2.0 * turned
        twins = rows[(apart > settings.constant_velocity_tolerance_m).any(axis=1)]
        return cls(xy=xy, heading_rad=heading, twins=twins, last_step=window)


@dataclass(frozen=True, eq=False)
class _Hypotheses:
    """The agents as the scorer sees them: rows ``(R,)``, first every agent's map-path
    forecast, then a constant-velocity twin of the agents whose straight-on forecast
    departs from it (:meth:`of`). ``owner`` ``(R,)``: the agent (row of the forecasts)
    of each row; ``last_step`` ``(R,)``: the last time index a row is checked at."""

    agents: AgentForecasts
    owner: np.ndarray
    last_step: np.ndarray
    twin: np.ndarray  # (R,) bool: a constant-velocity row

    @classmethod
    def of(cls, agents: AgentForecasts, settings: PdmSettings) -> _Hypotheses:
        """Every agent's map-path row, then the twins of all agents that have one."""
        cv = _ConstantVelocity.of(agents, settings)
        return cls.join(agents, np.arange(agents.n), cv, cv.twins)

    @classmethod
    def join(
        cls,
        agents: AgentForecasts,
        originals: np.ndarray,
        cv: _ConstantVelocity,
        twins: np.ndarray,
    ) -> _Hypotheses:
        """The map-path rows of the agents ``originals`` then the constant-velocity rows
        of the agents ``twins`` (index arrays into ``agents``), as one set of rows."""
        n_t = agents.times_s.size
        rows = np.r_[originals, twins].astype(np.int64)
        if twins.size == 0:
            forecasts = agents.subset(rows)
        else:
            forecasts = AgentForecasts(
                ids=agents.ids[rows],
                kinds=agents.kinds[rows],
                length_m=agents.length_m[rows],
                width_m=agents.width_m[rows],
                times_s=agents.times_s,
                xy=np.concatenate([agents.xy[originals], cv.xy[twins]]),
                heading_rad=np.concatenate([agents.heading_rad[originals], cv.heading_rad[twins]]),
                speed_mps=None if agents.speed_mps is None else agents.speed_mps[rows],
            )
        last = np.r_[np.full(originals.size, n_t - 1), np.full(twins.size, cv.last_step)]
        twin = np.r_[np.zeros(originals.size, dtype=bool), np.ones(twins.size, dtype=bool)]
        return cls(agents=forecasts, owner=rows, last_step=last.astype(np.int64), twin=twin)


# ---------------------------------------------------------------------- scores
@dataclass(frozen=True, eq=False)
class ProposalScores:
    """The scorer's answer for ``P`` proposals.

    ``multi`` ``(3, P)``: rows of :class:`MultiMetric`; ``weighted`` ``(3, P)``: rows of
    :class:`WeightedMetric`, progress normalised (by the best progress among proposals
    whose multiplicative product is not 0); ``progress_m`` ``(P,)``: raw progress along the
    reference; ``total`` ``(P,)``: ``product(multi) * weighted mean``; ``collision_step``
    ``(P,)``: time index of the first at-fault collision (inf: none); ``collision_row``
    ``(P,)``: the agent (row of the scored agents) hit then, -1 none.
    """

    multi: np.ndarray
    weighted: np.ndarray
    progress_m: np.ndarray
    total: np.ndarray
    collision_step: np.ndarray
    collision_row: np.ndarray

    @classmethod
    def of(
        cls,
        multi: np.ndarray,
        weighted_raw: np.ndarray,
        collision_step: np.ndarray,
        collision_row: np.ndarray,
        settings: PdmSettings,
    ) -> ProposalScores:
        """Aggregates as PDM: progress is normalised by the best progress among the
        proposals not zeroed by a multiplicative metric (all 1 where that best is below
        ``progress_min_m``, 0 where zeroed)."""
        p = settings
        product = multi.prod(axis=0)
        raw = weighted_raw[WeightedMetric.PROGRESS] * product
        best = raw.max()
        weighted = weighted_raw.copy()
        if best > p.progress_min_m:
            weighted[WeightedMetric.PROGRESS] = raw / best
        else:
            weighted[WeightedMetric.PROGRESS] = np.where(product == 0.0, 0.0, 1.0)
        weights = np.array([p.weight_progress, p.weight_ttc, p.weight_comfort])
        return cls(
            multi=multi,
            weighted=weighted,
            progress_m=weighted_raw[WeightedMetric.PROGRESS].copy(),
            total=product * (weights @ weighted) / weights.sum(),
            collision_step=collision_step,
            collision_row=np.asarray(collision_row, dtype=np.int64),
        )


# ---------------------------------------------------------------------- the planner
@dataclass(frozen=True, eq=False)
class _Proposals:
    states: np.ndarray  # (P, T, N_PROPOSAL)
    offset_m: np.ndarray  # (P,)
    fraction: np.ndarray  # (P,)
    leader: np.ndarray  # (P, T) int: index into leader_ids of the limiting leader, -1 none
    leader_ids: np.ndarray  # (L,) int64: ids of the agents the leader search reads
    simulated: np.ndarray  # (P, T, N_STATE) rear-axle bicycle states
    wheelbase_m: float


class PdmPlanner:
    """PDM-Closed-style planner (see the module's docstring)."""

    name = "pdm"

    def __init__(
        self,
        settings: PdmSettings | None = None,
        tracker: lqr.TrackerSettings | None = None,
        *,
        compiled: bool = True,
    ) -> None:
        self.settings = PdmSettings() if settings is None else settings
        self.tracker = lqr.TrackerSettings() if tracker is None else tracker
        #: The per-step loops compiled with numba (:mod:`replay.planning.pdm_kernel`);
        #: False: their numpy forms, the oracles the tests compare them with.
        self.compiled = compiled

    def warm_up(self) -> None:
        """Compile the per-step loops (or load them from numba's cache) now, by planning
        a small made-up request: call it once in a parent process before starting
        workers, so that on a cold cache they load what it compiled (about 5 s of CPU)
        instead of each compiling it."""
        if not self.compiled:
            return
        times = plan_times(5.0, 0.1)
        ahead = np.stack([30.0 + 0.0 * times, np.zeros_like(times)], axis=-1)
        crossing = np.stack([20.0 + 0.0 * times, -10.0 + 4.0 * times], axis=-1)
        agents = AgentForecasts(
            ids=np.array([1, 2]), kinds=np.array([Kind.VEHICLE, Kind.PEDESTRIAN]),
            length_m=np.array([4.5, 0.6]), width_m=np.array([1.8, 0.6]), times_s=times,
            xy=np.stack([ahead, crossing]),
            heading_rad=np.stack([0.0 * times, np.full(times.size, math.pi / 2)]),
        )  # fmt: skip
        self.plan(
            PlanRequest(
                ego=EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=8.0),
                reference=np.array([[0.0, 0.0], [50.0, 0.0], [100.0, 5.0]]),
                target_speed_mps=10.0,
                agents=agents,
            )
        )

    # ------------------------------------------------------------------ may_matter
    def may_matter(self, request: PlanRequest) -> np.ndarray:
        """``(K,)`` bool: False for agents the planner provably never reads (see the
        module's docstring); costs about one plan."""
        if request.agents.n == 0:
            return np.zeros(0, dtype=bool)
        if not _usable(request.reference):
            return np.ones(request.agents.n, dtype=bool)  # plan fails whatever the agents
        return self._relevant(request)[3]

    # ------------------------------------------------------------------ plan
    def plan(self, request: PlanRequest) -> Plan:
        start = time.perf_counter()
        if not _usable(request.reference):
            return Plan.failed("the reference path has fewer than two distinct points")
        line, scored, proposals, _, candidates = self._relevant(request)
        agents = scored.agents  # the scorer's rows: ids repeat for the second hypotheses
        p = self.settings
        sim = proposals.simulated
        sim_xy = _centres(sim, proposals.wheelbase_m)
        scores = self._score(request, line, scored, sim, sim_xy, candidates)
        total = scores.total
        best = _choose(scores, proposals.fraction > 0.0, proposals.offset_m, p.score_tie)
        ego = request.ego
        brake = bool(
            scores.collision_step[best] * request.dt_s <= p.brake_within_s
            and ego.speed_mps <= p.brake_max_speed_mps
        )
        if brake:
            xy, heading, speed = _brake(request, p.brake_decel_mps2)
            row = int(scores.collision_row[best])
            blocking = int(agents.ids[row]) if row >= 0 else -1
        else:  # the proposal itself, as PDM (its simulation was for the scores)
            chosen = proposals.states[best]
            xy = chosen[:, [ProposalColumn.X, ProposalColumn.Y]]
            heading = np.unwrap(chosen[:, ProposalColumn.HEADING])
            speed = chosen[:, ProposalColumn.SPEED]
            limited = proposals.leader[best][proposals.leader[best] >= 0]
            blocking = int(proposals.leader_ids[limited[0]]) if limited.size else -1
        _, lateral_end, _ = line.project(xy[-1:])
        return Plan(
            ok=True,
            times_s=request.times_s,
            xy=xy,
            heading_rad=heading,
            speed_mps=speed,
            plan_ms=(time.perf_counter() - start) * 1e3,
            lane=int(np.rint(lateral_end[0] / request.lane_width_m)),
            stops=bool((speed < STOP_SPEED_MPS).any()),
            blocking_id=blocking,
            extras={
                "score": float(total[best]),
                "offset_m": float(proposals.offset_m[best]),
                "target_fraction": float(proposals.fraction[best]),
                "emergency_brake": float(brake),
                "brake_proposal": float(proposals.fraction[best] == 0.0),
                "proposals": float(total.size),
            },
        )

    # ------------------------------------------------------------------ stages
    def _leader_reach(
        self, request: PlanRequest, along: _AgentsAlong, s0: float, d0: float
    ) -> np.ndarray:
        """``(K, T)``: where an agent's box reaches some proposal's corridor ahead of the
        ego's arc ``s0`` (the ego ``d0`` to the left of the reference), before the
        corridor's end."""
        ego = request.ego
        # the proposals' paths run between the ego's offset d0 and their own
        widest = max(max(abs(o) for o in self.settings.lateral_offsets_m), abs(d0))
        corridor = np.abs(along.lateral_m) < widest + ego.width_m / 2.0 + along.half_across_m
        end = s0 + self._corridor_length(request)
        return corridor & (along.arc_m > s0) & (along.arc_m - along.half_along_m < end)

    @staticmethod
    def _corridor_length(request: PlanRequest) -> float:
        """How far ahead of the ego the leader search looks (m): PDM's corridor is the
        distance driven at the highest target speed over the horizon."""
        fastest = max(request.target_speed_mps, request.ego.speed_mps, 0.0)
        return fastest * request.horizon_s + request.ego.length_m / 2.0

    def _relevant(
        self, request: PlanRequest
    ) -> tuple[_Centreline, _Hypotheses, _Proposals, np.ndarray, np.ndarray | None]:
        """The centreline, the scorer's rows of the agents read anywhere (their map-path
        forecasts on the plan's times and constant-velocity twins, :class:`_Hypotheses`),
        the simulated proposals (built on the agents the leader search can read), the
        mask ``(K,)`` of agents read anywhere (the leader search, or a bounding-circle
        candidate of the scorer under either hypothesis) and the scorer's candidates
        ``(P, T, D, R')`` of those rows (None without agents).

        Two distance bounds from the ego's position keep the work in proportion to the
        agents near the ego, never dropping one that either test would read: a leader's
        centre lies within ``corridor + |d0| + max(widest offset, |d0|) + half width + 2 r``
        of the ego (``d0`` the ego's offset from the reference, ``r`` the agent's half diagonal;
        a path is never shorter than its chord), and a scorer candidate's within the
        farthest simulated box centre (moved ahead by the largest look-ahead) plus both
        half diagonals.
        """
        line = _Centreline.of(request.reference, self.compiled)
        agents = request.agents.on_times(request.times_s)
        ego = request.ego
        s0_arr, d0_arr, _ = line.project(ego.xy[None])
        s0, d0 = float(s0_arr[0]), float(d0_arr[0])
        leaders = np.zeros(agents.n, dtype=bool)
        leaders_along = None
        if agents.n:
            distance = np.hypot(agents.xy[..., 0] - ego.xy[0], agents.xy[..., 1] - ego.xy[1])
            half_diagonal = np.hypot(agents.length_m, agents.width_m) / 2.0
            widest = max(max(abs(o) for o in self.settings.lateral_offsets_m), abs(d0))
            bound = self._corridor_length(request) + abs(d0) + widest + ego.width_m / 2.0
            maybe = np.flatnonzero(
                (distance <= (bound + 2.0 * half_diagonal + 1e-6)[:, None]).any(axis=1)
            )
            if maybe.size:
                searched = _at_steps(agents.subset(maybe), self._search_steps(request))
                along = _AgentsAlong.of(line, searched)
                reach = np.asarray(self._leader_reach(request, along, s0, d0).any(axis=1))
                leaders[maybe[reach]] = True
                leaders_along = along.rows(reach) if reach.any() else None
        proposals = self._proposals(request, line, leaders_along, agents.ids[leaders], s0, d0)
        if agents.n == 0:
            return line, _Hypotheses.of(agents, self.settings), proposals, leaders, None
        sim = proposals.simulated
        sim_xy = _centres(sim, proposals.wheelbase_m)
        look = self._lookahead_steps(request.dt_s)
        farthest = float(np.hypot(sim_xy[..., 0] - ego.xy[0], sim_xy[..., 1] - ego.xy[1]).max())
        farthest += float(sim[..., lqr.StateIndex.SPEED].max()) * float(look.max()) * request.dt_s
        ego_half_diagonal = math.hypot(ego.length_m, ego.width_m) / 2.0
        near_bound = farthest + ego_half_diagonal + half_diagonal + 1e-6
        maybe_near = np.flatnonzero((distance <= near_bound[:, None]).any(axis=1))
        # the constant-velocity rows (within their window) that come as near
        # only an agent whose straight-on travel within the window can bring it that near
        window_s = float(agents.times_s[_ConstantVelocity.window(agents, self.settings)])
        reach_cv = distance[:, 0] - _current_speed(agents) * window_s
        cv = _ConstantVelocity.of(
            agents, self.settings, among=np.flatnonzero(reach_cv <= near_bound + 1e-6)
        )
        cv_xy = cv.xy[cv.twins, : cv.last_step + 1]
        cv_distance = np.hypot(cv_xy[..., 0] - ego.xy[0], cv_xy[..., 1] - ego.xy[1])
        maybe_twins = cv.twins[(cv_distance <= near_bound[cv.twins, None]).any(axis=1)]
        tested = _Hypotheses.join(agents, maybe_near, cv, maybe_twins)
        near_row = np.zeros(tested.owner.size, dtype=bool)
        cand = np.zeros((*sim.shape[:2], look.size, 0), dtype=bool)
        if tested.owner.size:
            cand = _candidates(
                request, tested.agents, sim, sim_xy, look, last_step=tested.last_step,
                compiled=self.compiled,
            )  # fmt: skip
            near_row = np.asarray(cand.any(axis=(0, 1, 2)))
        near = np.zeros(agents.n, dtype=bool)
        near[tested.owner[near_row]] = True
        relevant = leaders | near
        # The scorer's rows: the relevant agents' map-path rows (in their order; leaders
        # far from every simulated box have no candidates), then the twins that have some
        # (a twin without candidates has no contact: leaving it out changes nothing).
        kept_twins = near_row[maybe_near.size :]
        scored = _Hypotheses.join(agents, np.flatnonzero(relevant), cv, maybe_twins[kept_twins])
        column = np.full(agents.n, -1)
        column[maybe_near] = np.arange(maybe_near.size)
        columns = np.r_[column[relevant], maybe_near.size + np.flatnonzero(kept_twins)].astype(
            np.int64
        )
        relevant_cand = np.zeros((*cand.shape[:3], columns.size), dtype=bool)
        relevant_cand[..., columns >= 0] = cand[..., columns[columns >= 0]]
        return line, scored, proposals, relevant, relevant_cand

    def _search_steps(self, request: PlanRequest) -> np.ndarray:
        """The steps at which the IDM searches for leaders (the last step plans nothing)."""
        return np.arange(0, max(request.times_s.size - 1, 1), self.settings.leader_update_steps)

    def _lookahead_steps(self, dt_s: float) -> np.ndarray:
        return np.array([round(t / dt_s) for t in self.settings.ttc_lookahead_s], dtype=np.int64)

    def _proposals(
        self,
        request: PlanRequest,
        line: _Centreline,
        leaders: _AgentsAlong | None,
        leader_ids: np.ndarray,
        s0: float,
        d0: float,
    ) -> _Proposals:
        """IDM along every (offset, target) pair, then each tracked by the bicycle."""
        p = self.settings
        ego = request.ego
        times = request.times_s
        dt = request.dt_s
        n_t = times.size
        offsets = np.repeat(
            np.asarray(p.lateral_offsets_m, dtype=np.float64), len(p.target_fractions)
        )
        fractions = np.tile(
            np.asarray(p.target_fractions, dtype=np.float64), len(p.lateral_offsets_m)
        )
        target = np.maximum(fractions * max(request.target_speed_mps, 0.0), 0.1)
        half_len, half_wid = ego.length_m / 2.0, ego.width_m / 2.0
        merge_m = max(p.merge_time_s * max(ego.speed_mps, 0.0), p.merge_min_m)

        corridor = None
        if leaders is not None:  # (L, S): the leaders at the search steps
            arc_t = np.ascontiguousarray(leaders.arc_m.T)  # (S, L)
            # the gap to the ego is back - s (bumper to bumper along the path)
            back_t = np.ascontiguousarray((leaders.arc_m - leaders.half_along_m).T) - half_len
            path_offset, _ = merge(arc_t[:, None, :], offsets[None, :, None], s0, d0, merge_m)
            corridor = np.abs(leaders.lateral_m.T[:, None, :] - path_offset) < (
                half_wid + leaders.half_across_m.T[:, None, :]
            )  # (S, P, L)
            end = s0 + self._corridor_length(request)
            corridor &= (arc_t - leaders.half_along_m.T < end)[:, None, :]
            speed_t = np.ascontiguousarray(leaders.speed_along_mps.T)
        # IDM over the time steps: compiled, or the numpy loop (the oracle)
        rollout = _kernel().idm_rollout if self.compiled else _idm_rollout
        s, v, a_free_t, a_lead_t, lead_t = rollout(
            n_t, s0, max(ego.speed_mps, 0.0), target,
            None if corridor is None else (corridor, arc_t, back_t, speed_t), p, dt,
        )  # fmt: skip
        s, v = s.T, v.T
        # a leader limits a step where it lowers the acceleration by the margin (a step
        # without a leader has a_lead = a_free = 0 here)
        limited = a_lead_t < a_free_t - p.blocking_margin_mps2
        leader = np.where(limited, lead_t, -1).T  # (P, T)
        if p.brake_proposals_mps2:  # braking to a stop on the centreline (fraction 0)
            brake_s, brake_v = _braking(
                np.asarray(p.brake_proposals_mps2, dtype=np.float64), times - times[0],
                s0, max(ego.speed_mps, 0.0),
            )  # fmt: skip
            n_b = brake_s.shape[0]
            s, v = np.vstack([s, brake_s]), np.vstack([v, brake_v])
            offsets = np.r_[offsets, np.zeros(n_b)]
            fractions = np.r_[fractions, np.zeros(n_b)]
            leader = np.vstack([leader, np.full((n_b, n_t), -1, dtype=leader.dtype)])

        offset_pt, slope = merge(s, offsets[:, None], s0, d0, merge_m)
        xy, heading = line.pose(s, offset_pt)
        heading = heading + np.arctan(slope)
        states = np.empty((offsets.size, n_t, N_PROPOSAL))
        states[..., ProposalColumn.X] = xy[..., 0]
        states[..., ProposalColumn.Y] = xy[..., 1]
        states[..., ProposalColumn.HEADING] = heading
        states[..., ProposalColumn.SPEED] = v
        states[..., ProposalColumn.PROGRESS] = s
        simulated, wb = self._simulate(request, states, dt)
        return _Proposals(
            states=states,
            offset_m=offsets,
            fraction=fractions,
            leader=leader,
            leader_ids=leader_ids,
            simulated=simulated,
            wheelbase_m=wb,
        )

    def _simulate(
        self, request: PlanRequest, states: np.ndarray, dt: float
    ) -> tuple[np.ndarray, float]:
        """Each proposal tracked from the ego's pose by the bicycle under the LQR tracker
        over the whole horizon: states ``(P, T, N_STATE)`` (rear axle) and the wheelbase."""
        ego = request.ego
        n_p, n_t = states.shape[:2]
        wb = float(lqr.wheelbase_m(ego.length_m))
        wheelbase = np.full(n_p, wb)
        xy = states[..., [ProposalColumn.X, ProposalColumn.Y]]
        heading = states[..., ProposalColumn.HEADING]
        reference = lqr.reference_from_centres(
            xy, heading, states[..., ProposalColumn.SPEED], wheelbase
        )
        initial = np.zeros((n_p, lqr.N_STATE))
        initial[:, [lqr.StateIndex.REAR_X, lqr.StateIndex.REAR_Y]] = lqr.rear_axle_xy(
            ego.xy, ego.heading_rad, wb
        )
        initial[:, lqr.StateIndex.HEADING] = ego.heading_rad
        initial[:, lqr.StateIndex.SPEED] = max(ego.speed_mps, 0.0)
        initial[:, lqr.StateIndex.ACCEL] = ego.accel_mps2
        # The vehicle's own steering angle when the request carries it (a closed loop's);
        # else the ego is taken to follow its route's curvature now (a logged ego does),
        # which avoids a steering step on curves.
        initial[:, lqr.StateIndex.STEER] = (
            np.arctan(wb * reference.curvature_per_m[0, 0])
            if ego.steer_rad is None
            else ego.steer_rad
        )
        settings = self.tracker if self.tracker.dt_s == dt else replace(self.tracker, dt_s=dt)
        simulate = _kernel().simulate if self.compiled else lqr.simulate
        return simulate(initial, reference, n_t - 1, wheelbase, settings), wb

    # ------------------------------------------------------------------ scoring
    def score(self, request: PlanRequest, simulated: np.ndarray) -> ProposalScores:
        """The scores of simulated proposals ``(P, T, N_STATE)`` (bicycle states, rear
        axle, on the request's times) against the request's agents and lanes."""
        line = _Centreline.of(request.reference, self.compiled)
        scored = _Hypotheses.of(request.agents.on_times(request.times_s), self.settings)
        wheelbase = float(lqr.wheelbase_m(request.ego.length_m))
        return self._score(request, line, scored, simulated, _centres(simulated, wheelbase))

    def _score(
        self,
        request: PlanRequest,
        line: _Centreline,
        scored: _Hypotheses,
        sim: np.ndarray,
        sim_xy: np.ndarray,
        candidates: np.ndarray | None = None,
    ) -> ProposalScores:
        """Metric rows and scores of the simulated proposals (see :class:`ProposalScores`)
        against the scorer's rows ``scored`` (each agent under either hypothesis: a row's
        at-fault collision is its agent's); ``candidates``: the bounding-circle candidates
        of these rows when known. ``collision_row`` is a row of ``scored``."""
        agents = scored.agents
        p = self.settings
        ego = request.ego
        dt = request.dt_s
        n_p = sim.shape[0]
        heading = sim[..., lqr.StateIndex.HEADING]
        speed = sim[..., lqr.StateIndex.SPEED]
        rear = sim[..., [lqr.StateIndex.REAR_X, lqr.StateIndex.REAR_Y]]
        arc, lateral, path_h = line.project(sim_xy)  # (P, T)

        # Where the ego's corners are: lanes around the reference (corners' lateral
        # offsets from the centre's, the path taken as straight over the box).
        rel = heading - path_h
        corner_l = np.array([1.0, 1.0, -1.0, -1.0]) * ego.length_m / 2.0
        corner_w = np.array([1.0, -1.0, -1.0, 1.0]) * ego.width_m / 2.0
        corner_lat = (
            lateral[..., None]
            + corner_l * np.sin(rel)[..., None]
            + corner_w * np.cos(rel)[..., None]
        )
        w = request.lane_width_m
        left_edge = (request.lanes_left + 0.5) * w + p.drivable_margin_m
        right_edge = -(request.lanes_right + 0.5) * w - p.drivable_margin_m
        off_road = ((corner_lat > left_edge) | (corner_lat < right_edge)).any(axis=-1)  # (P, T)
        lane_of = np.rint(corner_lat / w)
        multiple_lanes = lane_of.max(axis=-1) != lane_of.min(axis=-1)
        straddles = off_road | multiple_lanes

        multi = np.ones((len(MultiMetric), n_p))
        weighted = np.ones((len(WeightedMetric), n_p))
        multi[MultiMetric.DRIVABLE_AREA] = np.where(off_road.any(axis=1), 0.0, 1.0)
        multi[MultiMetric.DRIVING_DIRECTION] = self._direction(sim_xy, rel)
        weighted[WeightedMetric.PROGRESS] = np.maximum(arc[:, -1] - arc[:, 0], 0.0)
        weighted[WeightedMetric.COMFORT] = self._comfortable(
            sim, dt, float(lqr.wheelbase_m(ego.length_m))
        )
        if agents.n == 0:
            return ProposalScores.of(multi, weighted, np.full(n_p, np.inf), np.full(n_p, -1), p)

        look = self._lookahead_steps(dt)
        # Agents touching the ego now are ignored (PDM: already collided).
        now = boxes_overlap(
            ego.xy[0], ego.xy[1], np.asarray(ego.heading_rad), np.asarray(ego.length_m), np.asarray(ego.width_m),
            agents.xy[:, 0, 0], agents.xy[:, 0, 1], agents.heading_rad[:, 0], agents.length_m, agents.width_m,
        )  # fmt: skip
        c = contacts(
            request, agents, sim, sim_xy, look, ignore=now, candidates=candidates,
            last_step=scored.last_step, compiled=self.compiled,
        )  # fmt: skip
        ip, it, idd, ik, ta, cx, cy = (
            c.proposal,
            c.step,
            c.lookahead,
            c.agent,
            c.agent_step,
            c.x,
            c.y,
        )

        # Classes at a contact: the ego stands, the agent stands, the agent is behind the
        # ego, the agent touches the ego's front edge, otherwise lateral (nuPlan's order).
        velocity = _velocities(agents)
        agent_speed = np.hypot(velocity[ik, ta, 0], velocity[ik, ta, 1])
        to_agent = agents.xy[ik, ta] - rear[ip, it]
        bearing = np.abs(
            lqr.wrap_angle(np.arctan2(to_agent[:, 1], to_agent[:, 0]) - heading[ip, it])
        )
        behind = bearing > p.behind_angle_rad
        ahead = bearing < p.ahead_angle_rad
        front_x = cx + ego.length_m / 2.0 * np.cos(heading[ip, it])
        front_y = cy + ego.length_m / 2.0 * np.sin(heading[ip, it])
        front = boxes_overlap(
            front_x, front_y, heading[ip, it], np.zeros(1), np.asarray(ego.width_m),
            agents.xy[ik, ta, 0], agents.xy[ik, ta, 1], agents.heading_rad[ik, ta],
            agents.length_m[ik], agents.width_m[ik],
        )  # fmt: skip
        ego_stands = speed[ip, it] <= p.stopped_speed_mps
        agent_stands = (agent_speed <= p.stopped_speed_mps) | (agents.kinds[ik] == Kind.OTHER)
        at_fault = ~ego_stands & (agent_stands | (~behind & (front | straddles[ip, it])))

        # Each (proposal, agent) counts at its first contact (later ones are ignored, as
        # PDM's collided-track lists do); contacts in order of time, then look-ahead.
        order = it * look.size + idd
        collision = idd == 0
        collision_score, collision_step, collision_agent = _first_contact(
            n_p,
            agents.n,
            ip[collision],
            ik[collision],
            order[collision],
            it[collision],
            at_fault[collision],
        )
        # A constant-velocity row that every proposal (the braking ones included) hits
        # at fault says nothing about which to choose: it would zero them all, and the
        # choice among zeros would then ignore the map-path forecasts' differences.
        unavoidable = scored.twin & collision_score.all(axis=0)
        if p.drop_unavoidable_twins and unavoidable.any():
            collision_score = collision_score & ~unavoidable
        factor = np.where(agents.kinds == Kind.OTHER, p.static_collision_score, 0.0)
        multi[MultiMetric.NO_AT_FAULT_COLLISION] = np.where(
            collision_score, factor[np.maximum(collision_agent, 0)], 1.0
        ).min(axis=1)
        first_fault = np.where(collision_score, collision_step, np.inf)
        worst = np.argmin(first_fault, axis=1)
        step = first_fault[np.arange(n_p), worst]
        collision_row = np.where(np.isfinite(step), worst, -1)

        # TTC: contacts while the ego stands are skipped (not ignored for later, as PDM).
        moving = speed[ip, it] >= p.ttc_stopped_speed_mps
        ttc_fault = ahead | (straddles[ip, it] & ~behind)
        ttc_counts, _, _ = _first_contact(
            n_p, agents.n, ip[moving], ik[moving], order[moving], it[moving], ttc_fault[moving]
        )
        if p.drop_unavoidable_twins and unavoidable.any():
            ttc_counts = ttc_counts & ~unavoidable
        weighted[WeightedMetric.TTC] = np.where(ttc_counts.any(axis=1), 0.0, 1.0)
        return ProposalScores.of(multi, weighted, step, collision_row, p)

    def _direction(self, sim_xy: np.ndarray, rel_heading: np.ndarray) -> np.ndarray:
        """Driving direction ``(P,)``: the longest stretch (m) driven against the
        reference's direction: up to 2 m 1, up to 6 m 0.5, else 0."""
        p = self.settings
        step = np.zeros(sim_xy.shape[:2])
        step[:, 1:] = np.hypot(*np.moveaxis(np.diff(sim_xy, axis=1), -1, 0))
        against = np.abs(lqr.wrap_angle(rel_heading)) > math.pi / 2.0
        run = np.cumsum(np.where(against, step, 0.0), axis=1)
        # the run restarts where the ego drives with the reference again
        restart = np.maximum.accumulate(np.where(against, 0.0, run), axis=1)
        longest = (run - restart).max(axis=1)
        return np.where(
            longest <= p.direction_ok_m, 1.0, np.where(longest <= p.direction_violation_m, 0.5, 0.0)
        )

    def _comfortable(self, sim: np.ndarray, dt: float, wheelbase: float) -> np.ndarray:
        """``(P,)`` 1.0 where every comfort bound of nuPlan holds over the horizon (PDM's
        Savitzky-Golay smoothing, as linear operators built once per length)."""
        p = self.settings
        n_t = sim.shape[1]
        lon = sim[..., lqr.StateIndex.ACCEL]
        yaw_rate_model = (
            sim[..., lqr.StateIndex.SPEED] * np.tan(sim[..., lqr.StateIndex.STEER]) / wheelbase
        )
        lat = sim[..., lqr.StateIndex.SPEED] * yaw_rate_model
        heading = np.unwrap(sim[..., lqr.StateIndex.HEADING], axis=1)
        whole = _savgol(n_t, n_t, 2, 0, dt)
        lon_s, lat_s = lon @ whole.T, lat @ whole.T
        short = _savgol(n_t, 8, 2, 0, dt)
        jerk_op = _savgol(n_t, n_t, 2, 1, dt) @ short
        lon_jerk = lon @ jerk_op.T
        jerk = np.hypot(lon, lat) @ jerk_op.T
        yaw_rate = heading @ _savgol(n_t, 5, 2, 1, dt).T
        yaw_accel = heading @ _savgol(n_t, 5, 3, 2, dt).T
        ok = (
            ((lon_s > p.min_lon_accel_mps2) & (lon_s < p.max_lon_accel_mps2)).all(axis=1)
            & (np.abs(lat_s) < p.max_abs_lat_accel_mps2).all(axis=1)
            & (np.abs(jerk) < p.max_abs_jerk).all(axis=1)
            & (np.abs(lon_jerk) < p.max_abs_lon_jerk).all(axis=1)
            & (np.abs(yaw_rate) < p.max_abs_yaw_rate).all(axis=1)
            & (np.abs(yaw_accel) < p.max_abs_yaw_accel).all(axis=1)
        )
        return ok.astype(np.float64)


def _idm_rollout(
    n_t: int,
    s0: float,
    v0: float,
    target: np.ndarray,
    leaders: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
    settings: PdmSettings,
    dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IDM along every proposal ``(P,)`` (target speeds ``target``) from arc ``s0`` at speed
    ``v0`` over ``n_t`` times, in numpy (the oracle of :func:`pdm_kernel.idm_rollout`):
    arc and speed ``(n_t, P)``, and per step the free-road and with-leader accelerations
    and the held leader's row ``(n_t, P)`` (zeros at steps without a held leader).
    ``leaders``: ``corridor`` ``(S, P, L)``, the leaders' arcs, rears (less the ego's half
    length) and speeds along the path ``(S, L)`` at the search steps; None: none."""
    p = settings
    n_p = target.size
    sqrt_ab = 2.0 * math.sqrt(p.idm_accel_mps2 * p.idm_decel_mps2)
    # Time-major arrays (row k is contiguous): the loop runs over steps only.
    s = np.empty((n_t, n_p))
    v = np.empty((n_t, n_p))
    s[0] = s0
    v[0] = v0
    # Per step, for the leader bookkeeping after the loop: free-road and with-leader
    # accelerations, and the nearest agent's row in the corridor ahead.
    a_free_t = np.zeros((n_t, n_p))
    a_lead_t = np.zeros((n_t, n_p))
    lead_t = np.zeros((n_t, n_p), dtype=np.int64)
    corridor = None
    if leaders is not None:
        corridor, arc_t, back_t, speed_t = leaders
        any_t = np.asarray(corridor.any(axis=(1, 2)))
    proposal_rows = np.arange(n_p)
    inv_target = 1.0 / target
    a_max, b_max = p.idm_accel_mps2, p.idm_decel_mps2
    every = p.leader_update_steps
    # The leader found at the last search, held until the next (as PDM): where its
    # rear is along the path (inf: none), its speed along the path, its row.
    held_back = np.full(n_p, np.inf)
    held_speed = np.zeros(n_p)
    held_row = np.zeros(n_p, dtype=np.int64)
    for k in range(n_t - 1):  # time steps only: proposals and agents vectorised
        vk, sk = v[k], s[k]
        a_free = a_max - a_max * (vk * inv_target) ** p.idm_exponent
        accel = a_free
        if corridor is not None:
            i, search = divmod(k, every)
            if search == 0:
                if any_t[i]:
                    masked = np.where(corridor[i] & (arc_t[i] > sk[:, None]), back_t[i], np.inf)
                    held_row = np.argmin(masked, axis=1)
                    held_back = masked[proposal_rows, held_row]
                    held_speed = speed_t[i, held_row]
                else:
                    held_back = np.full(n_p, np.inf)
            if np.isfinite(held_back).any():
                # no leader: the gap is inf, its IDM term 0, accel the free-road one
                gap = held_back - sk
                s_star = p.idm_min_gap_m + vk * (p.idm_headway_s + (vk - held_speed) / sqrt_ab)
                accel = a_free - a_max * (s_star / np.maximum(gap, p.idm_min_gap_m)) ** 2
                a_free_t[k], a_lead_t[k], lead_t[k] = a_free, accel, held_row
        accel = np.minimum(np.maximum(accel, -b_max), a_max)
        v_next = vk + accel * dt
        s[k + 1] = sk + (vk + 0.5 * dt * accel) * dt
        v[k + 1] = v_next
        stops = v_next < 0.0
        if stops.any():  # stops within the step: no reversing
            s[k + 1, stops] = sk[stops] + vk[stops] ** 2 / (2.0 * -accel[stops])
            v[k + 1, stops] = 0.0
    return s, v, a_free_t, a_lead_t, lead_t


# ---------------------------------------------------------------------- helpers
def _kernel() -> types.ModuleType:
    """:mod:`replay.planning.pdm_kernel`, imported on first use: numba and the compiled
    code (about 0.3 s in a fresh process, loaded from numba's cache) only in processes
    that plan with ``pdm``, not in every one that imports the planners."""
    import replay.planning.pdm_kernel as pdm_kernel

    return pdm_kernel


def _usable(reference: np.ndarray) -> bool:
    """The reference has two distinct points (a direction to extend it along)."""
    return reference.shape[0] >= 2 and bool(np.any(np.diff(reference, axis=0)))


def _best(total: np.ndarray, offset_m: np.ndarray, tie: float) -> int:
    """The chosen proposal: among those within ``tie`` of the best score, the one nearest
    the centreline, then the highest score, then the first."""
    near = np.flatnonzero(total >= total.max() - tie)
    order = np.lexsort((-total[near], np.abs(offset_m[near])))
    return int(near[order[0]])


def _choose(scores: ProposalScores, idm: np.ndarray, offset_m: np.ndarray, tie: float) -> int:
    """The chosen proposal. Braking proposals (``idm`` False) are eligible only when every
    IDM proposal collides at fault. Among the eligible, the best score (:func:`_best`);
    when they all score 0, those whose first at-fault collision comes latest (inf: none)
    first, then :func:`_best` among them."""
    collides = scores.multi[MultiMetric.NO_AT_FAULT_COLLISION] < 1.0
    eligible = idm | bool(collides[idm].all())
    total = np.where(eligible, scores.total, -np.inf)
    if total.max() <= 0.0:
        latest = np.where(eligible, scores.collision_step, -np.inf)
        total = np.where(latest == latest.max(), total, -np.inf)
    return _best(total, offset_m, tie)


def _braking(
    decel_mps2: np.ndarray, t_s: np.ndarray, s0: float, v0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Arc length and speed ``(B, T)`` braking from ``v0`` at ``s0`` at each deceleration
    ``(B,)`` to a stop and holding it, at times ``t_s`` ``(T,)`` from now."""
    d = decel_mps2[:, None]
    moving = np.minimum(t_s[None, :], v0 / d)
    return s0 + v0 * moving - 0.5 * d * moving * moving, np.maximum(v0 - d * t_s[None, :], 0.0)


def _centres(sim: np.ndarray, wheelbase: float) -> np.ndarray:
    """Box centres ``(..., 2)`` of bicycle states ``(..., N_STATE)`` (rear axle)."""
    rear = sim[..., [lqr.StateIndex.REAR_X, lqr.StateIndex.REAR_Y]]
    return lqr.centre_xy(rear, sim[..., lqr.StateIndex.HEADING], wheelbase)


def _candidates(
    request: PlanRequest,
    agents: AgentForecasts,
    sim: np.ndarray,
    sim_xy: np.ndarray,
    look: np.ndarray,
    last_step: np.ndarray | None = None,
    *,
    compiled: bool = False,
) -> np.ndarray:
    """``(P, T, D, K)``: the ego's box at step ``t`` of proposal ``p``, moved ahead by its
    speed times look-ahead ``d``, and agent ``k``'s box at step ``t + d`` could touch (their
    bounding circles do). Pairs whose ``t + d`` lies beyond the forecast, or beyond the
    agent's ``last_step`` ``(K,)``, are not checked. ``compiled``: the same test by
    :func:`pdm_kernel.candidates` (else numpy, the oracle)."""
    ego = request.ego
    n_t = sim.shape[1]
    heading = sim[..., lqr.StateIndex.HEADING]
    reach = (
        math.hypot(ego.length_m, ego.width_m) / 2.0
        + np.hypot(agents.length_m, agents.width_m) / 2.0
    )
    last = np.full(agents.n, n_t - 1) if last_step is None else np.minimum(last_step, n_t - 1)
    if compiled:
        return np.asarray(
            _kernel().candidates(
                sim_xy, heading, sim[..., lqr.StateIndex.SPEED], look, request.dt_s,
                agents.xy, reach, last,
            )
        )  # fmt: skip
    shift = sim[..., lqr.StateIndex.SPEED][..., None] * (look * request.dt_s)  # (P, T, D)
    cx = sim_xy[..., 0, None] + shift * np.cos(heading)[..., None]
    cy = sim_xy[..., 1, None] + shift * np.sin(heading)[..., None]
    ta = np.minimum(np.arange(n_t)[:, None] + look[None, :], n_t - 1)  # (T, D)
    ax = agents.xy[:, ta, 0]  # (K, T, D)
    ay = agents.xy[:, ta, 1]
    # Coarse, (K, T, D): the agent against the circle around all P ego centres at (t, d)
    # (a centre within r of the agent puts the agent within radius + r of the circle's
    # centre); only what passes is tested per proposal.
    mx, my = cx.mean(axis=0), cy.mean(axis=0)  # (T, D)
    radius = np.sqrt(((cx - mx) ** 2 + (cy - my) ** 2).max(axis=0))
    agent_step = np.arange(n_t)[:, None] + look[None, :]  # (T, D)
    within = agent_step[None] <= last[:, None, None]  # (K, T, D)
    wide = radius[None] + reach[:, None, None] + 1e-6
    coarse = ((ax - mx) ** 2 + (ay - my) ** 2 <= wide * wide) & within
    ik, it, idd = np.nonzero(coarse)
    dx = cx[:, it, idd] - ax[ik, it, idd]  # (P, m)
    dy = cy[:, it, idd] - ay[ik, it, idd]
    out = np.zeros((*cx.shape, agents.n), dtype=bool)
    out[:, it, idd, ik] = dx * dx + dy * dy <= reach[ik] * reach[ik]
    return out


@dataclass(frozen=True, eq=False)
class Contacts:
    """Box contacts, one entry each ``(C,)``: proposal, time index, look-ahead index,
    agent row, the agent's time index (``step + look[lookahead]``) and the centre of the
    ego's box (moved ahead by its speed times the look-ahead)."""

    proposal: np.ndarray
    step: np.ndarray
    lookahead: np.ndarray
    agent: np.ndarray
    agent_step: np.ndarray
    x: np.ndarray
    y: np.ndarray


def contacts(
    request: PlanRequest,
    agents: AgentForecasts,
    sim: np.ndarray,
    sim_xy: np.ndarray,
    look: np.ndarray,
    ignore: np.ndarray | None = None,
    candidates: np.ndarray | None = None,
    last_step: np.ndarray | None = None,
    *,
    compiled: bool = False,
) -> Contacts:
    """Every ``(proposal, step, look-ahead, agent)`` whose boxes overlap (separating axes,
    :func:`risk.hindsight.boxes_overlap`), the ego's box at ``sim_xy`` with the simulated
    heading, moved ahead by speed times ``look * dt``, against the agent's box at
    ``step + look``; only the pairs whose bounding circles touch are tested
    (:func:`_candidates`, or ``candidates`` ``(P, T, D, K)`` when already computed).
    ``ignore`` ``(K,)``: agents left out; ``last_step`` ``(K,)``: each agent's last time
    index checked (default: the forecast's end). ``compiled``: the candidates and the box
    tests by :mod:`pdm_kernel` (the same tests term by term; else numpy, the oracle)."""
    ego = request.ego
    dt = request.dt_s
    heading = sim[..., lqr.StateIndex.HEADING]
    speed = sim[..., lqr.StateIndex.SPEED]
    if candidates is None:
        cand = _candidates(
            request, agents, sim, sim_xy, look, last_step=last_step, compiled=compiled
        )
    else:
        cand = candidates
    if ignore is not None:
        cand = cand & ~ignore[None, None, None, :]
    if compiled:
        found = _kernel().box_contacts(
            cand, sim_xy, heading, speed, look, dt, ego.length_m, ego.width_m,
            agents.xy, agents.heading_rad, agents.length_m, agents.width_m, TOUCH_M,
        )  # fmt: skip
        return Contacts(*found)
    ip, it, idd, ik = np.nonzero(cand)
    shift = look[idd] * dt * speed[ip, it]
    h = heading[ip, it]
    cx = sim_xy[ip, it, 0] + shift * np.cos(h)
    cy = sim_xy[ip, it, 1] + shift * np.sin(h)
    ta = it + look[idd]
    hit = boxes_overlap(
        cx, cy, h, np.asarray(ego.length_m), np.asarray(ego.width_m),
        agents.xy[ik, ta, 0], agents.xy[ik, ta, 1], agents.heading_rad[ik, ta],
        agents.length_m[ik], agents.width_m[ik],
    )  # fmt: skip
    return Contacts(
        proposal=ip[hit],
        step=it[hit],
        lookahead=idd[hit],
        agent=ik[hit],
        agent_step=ta[hit],
        x=cx[hit],
        y=cy[hit],
    )


def _first_contact(
    n_p: int,
    n_k: int,
    ip: np.ndarray,
    ik: np.ndarray,
    order: np.ndarray,
    step: np.ndarray,
    counts: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For contacts listed by proposal ``ip``, agent ``ik`` and rank ``order``: per
    ``(P, K)`` whether the first contact counts, its step (inf: none) and the agent row
    (-1: none) as ``(P, K)`` arrays."""
    key = ip * n_k + ik
    by = np.lexsort((order, key))  # by pair, then rank: the first of each pair leads
    first = by[np.r_[True, key[by][1:] != key[by][:-1]]] if by.size else by
    counted = np.zeros((n_p, n_k), dtype=bool)
    at = np.full((n_p, n_k), np.inf)
    counted[ip[first], ik[first]] = counts[first]
    at[ip[first], ik[first]] = step[first]
    agent = np.where(counted, np.arange(n_k)[None, :], -1)
    return counted, at, agent


@functools.lru_cache(maxsize=32)
def _savgol(n: int, window: int, poly: int, deriv: int, dt: float) -> np.ndarray:
    """The Savitzky-Golay filter on ``n`` samples as a matrix ``(n, n)`` (``y = M x``),
    with scipy's edge handling; the window is cut to ``n``."""
    window = min(window, n)
    poly = min(poly, window - 1)
    return np.asarray(savgol_filter(np.eye(n), window, poly, deriv=deriv, delta=dt, axis=0))


def _brake(request: PlanRequest, decel_mps2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The emergency brake: straight ahead along the ego's heading at ``decel_mps2`` to a
    stop (PDM brakes along the current heading too)."""
    ego = request.ego
    t = request.times_s
    v0 = max(ego.speed_mps, 0.0)
    stop_t = v0 / decel_mps2
    tt = np.minimum(t, stop_t)
    dist = v0 * tt - 0.5 * decel_mps2 * tt * tt
    speed = np.maximum(v0 - decel_mps2 * t, 0.0)
    direction = np.array([math.cos(ego.heading_rad), math.sin(ego.heading_rad)])
    xy = ego.xy[None, :] + dist[:, None] * direction[None, :]
    return xy, np.full(t.size, ego.heading_rad), speed
