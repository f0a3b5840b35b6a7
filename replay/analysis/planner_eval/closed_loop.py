"""Closed loop: the planner drives the ego; the others replay their log or react.

From the ego's first recorded frame the planner re-plans at 10 Hz (at the log's own rate
where that is slower: the logged states exist only at logged frames), and the ego follows
each plan through a tracker (:func:`replay.planning.tracking.make_tracker`: ``perfect``
puts it on the plan's own state, ``lqr`` drives a kinematic bicycle) until the next
re-plan. When the planner finds no plan the ego keeps following its previous plan while
it lasts, else brakes at 6 m/s² along its heading; such steps are counted.

The others (``agents``):

- ``log``: everyone replays the log (nuPlan's CLS-NR);
- ``reactive`` (default): vehicles follow their logged path with IDM speed control,
  reacting to the ego and to each other (:mod:`replay.planning.reactive`), and never run
  ahead of their own log (so that they keep the logged stops at lights and give-ways our
  maps do not describe); pedestrians, cyclists and other objects replay their log. An
  agent enters at its logged state when it first appears and leaves when its log ends.

Each ego runs once with all agents and once per filter, from the same start. The run's
history is scored by :mod:`replay.analysis.planner_eval.metrics` (collisions classified
and at fault, drivable area, driving direction, progress against the recorded route,
least time-to-collision, comfort, a score; docs/planners.md).

:func:`run_ego` is the unit of work: a pure function of (scene file, ego id, settings)
to result rows, so that any engine can run it. What does not change while runs go (a
scene's tracks, logged speeds, lanes, its vehicles' rails) is computed once per scene and
process (:func:`_scene` keeps the last two); an ego's filters run stepped together
(:func:`drive_all`) and share all the work but the filter and the planner while their
plans agree. Each row is what the run alone gives (tests/test_closed_loop_identity.py).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
import os
import pathlib
from typing import Any

import numpy as np

from replay.analysis.planner_eval import metrics
from replay.analysis.planner_eval.open_loop import ALL_AGENTS, PlanSettings, _egos, scene_key
from replay.core.egos import load_scene
from replay.errors import ReplayError
from replay.planning import reactive
from replay.planning.errors import NoReferencePath
from replay.planning.inputs import plan_request
from replay.planning.registry import make_planner
from replay.planning.tracking import PerfectTracker, Tracker, VehicleState, make_tracker
from replay.planning.truth import target_speed
from replay.planning.types import Plan, Planner, PlanRequest
from risk.filtering import Filter, KeepAll
from risk.frame import KIND_NAMES, Frame, Kind
from risk.geometry import cumulative_lengths, extend_paths, project_points
from risk.hindsight import box_gap

#: Re-planning rate (Hz) when the log is at least this fast.
REPLAN_HZ = 10.0
#: Deceleration (m/s²) when the planner has no plan and the previous one has run out.
FALLBACK_DECEL_MPS2 = 6.0
#: Lane width (m): the leader of the time-headway check, "in its lane", the drivable corridor.
LANE_WIDTH_M = 3.5
#: How the others move; the default first.
AGENT_MODES: tuple[str, ...] = ("reactive", "log")
DEFAULT_AGENTS = "reactive"
#: The tracker the ego follows its plans with (one of replay.planning.tracking.TRACKERS).
DEFAULT_TRACKER = "lqr"
#: Drivable area is judged up to this far (m) beyond the recorded ego's last position
#: along its route: a drone recording's map covers the recorded area only, and the ego
#: that drives on (the reference runs straight on past the map) is off the map, not off
#: the road.
MAPPED_MARGIN_M = 5.0
#: Map lane kinds that are drivable for the ego.
DRIVABLE_LANE_KINDS = ("vehicle", "bus")
#: Points of the path piece that leads a reactive agent from where it is to its logged
#: position (prefixed to its logged path candidates for the planner's prediction).
LAG_POINTS = 12

CLOSED_LOOP_COLUMNS = (
    "scene", "dataset", "planner", "ego_id", "ego_kind", "agents", "tracker", "filter",
    "steps", "duration_s", "collisions", "stopped_ego_collisions", "stopped_track_collisions",
    "front_collisions", "rear_end_collisions", "lateral_collisions", "at_fault_collisions",
    "drivable_area_ok", "driving_direction_score", "progress_m", "expert_progress_m",
    "progress_ratio", "min_ttc_s", "comfortable", "score", "min_gap_m",
    "time_headway_below_1s_s", "plan_ms_median", "plan_ms_p95", "filter_ms_median",
    "plan_failures", "mean_agents",
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ClosedLoopSettings:
    """What a closed-loop run needs besides the scene and the ego: the planner and
    filters (``plan``), how the others move (``agents``: ``reactive`` or ``log``), the
    tracker's name and the reactive agents' IDM."""

    plan: PlanSettings = dataclasses.field(default_factory=PlanSettings)
    agents: str = DEFAULT_AGENTS
    tracker: str = DEFAULT_TRACKER
    reactive: reactive.ReactiveSettings = dataclasses.field(
        default_factory=reactive.ReactiveSettings
    )

    def __post_init__(self) -> None:
        if self.agents not in AGENT_MODES:
            raise ReplayError(
                f"unknown agents mode {self.agents!r}; expected one of {', '.join(AGENT_MODES)}"
            )


# ---------------------------------------------------------------------- the others
def _filled(valid: np.ndarray) -> np.ndarray:
    """(T, N) row to read for each entry: the last valid row at or before it, else the
    first valid row (an agent's rail holds still outside its log)."""
    t = valid.shape[0]
    rows = np.where(valid, np.arange(t)[:, None], -1)
    np.maximum.accumulate(rows, axis=0, out=rows)
    first = np.argmax(valid, axis=0)
    return np.where(rows < 0, first[None, :], rows)


def logged_speeds(scene: Any, tracks: Any) -> np.ndarray:
    """Every agent's logged speed (T, N) m/s (0 where not recorded), from the frames."""
    speeds = np.zeros(tracks.valid.shape)
    for _, frame in scene.indexed:  # over frames, not agents
        row = round((frame.t - tracks.t0_s) / tracks.dt_s)
        cols = tracks.index_of(frame.ids)
        ok = frame.valid & (cols >= 0)
        speeds[row, cols[ok]] = frame.speed[ok]
    return speeds


@dataclasses.dataclass(frozen=True, eq=False)
class _Traffic:
    """What the reactive agents of a run need that does not change while it runs, over
    the tracks' columns ``cols``: their rails, logged progress and speed (K, T), desired
    speed, length and width (K,). Each column's values depend on that column alone, so a
    scene's vehicles are prepared once and each ego's runs take the rows without it."""

    cols: np.ndarray
    rails: reactive.Rails
    log_arc: np.ndarray
    log_speed: np.ndarray
    desired: np.ndarray
    length: np.ndarray
    width: np.ndarray

    @classmethod
    def of(cls, tracks: Any, speeds: np.ndarray, cols: np.ndarray) -> _Traffic:
        rows = _filled(tracks.valid[:, cols])  # (T, K)
        at = cols[None, :]
        xy = tracks.xy[rows, at].transpose(1, 0, 2)  # (K, T, 2)
        heading = tracks.heading[rows, at].T
        rails = reactive.Rails.from_positions(xy, heading)
        t = tracks.valid.shape[0]
        log_speed = np.where(tracks.valid[:, cols], speeds[:, cols], 0.0).T
        first = np.argmax(tracks.valid[:, cols], axis=0)  # the size at a recorded row
        return cls(
            cols=cols,
            rails=rails,
            log_arc=rails.arc_m[:, :t],  # (K, T): the logged progress at each row
            log_speed=log_speed,
            desired=log_speed.max(axis=1, initial=0.0),
            length=tracks.length[first, cols],
            width=tracks.width[first, cols],
        )

    def rows(self, which: np.ndarray) -> _Traffic:
        """The agents ``which`` (an index array or a boolean mask over ``cols``)."""
        return _Traffic(
            cols=self.cols[which], rails=self.rails.rows(which), log_arc=self.log_arc[which],
            log_speed=self.log_speed[which], desired=self.desired[which],
            length=self.length[which], width=self.width[which],
        )  # fmt: skip


class _Others:
    """The other agents of one run, over the tracks' columns: logged, or reactive
    vehicles on their rails (state: progress along the rail and speed)."""

    def __init__(
        self, tracks: Any, speeds: np.ndarray, ego_column: int, traffic: _Traffic,
        settings: reactive.ReactiveSettings,
    ) -> None:  # fmt: skip
        """``traffic``: the reactive agents (none for ``log``; never the ego)."""
        self.tracks = tracks
        self.speeds = speeds
        self.settings = settings
        n = tracks.valid.shape[1]
        self.others = np.ones(n, dtype=bool)
        self.others[ego_column] = False
        self.cols = traffic.cols
        self.rails = traffic.rails
        self.log_arc = traffic.log_arc
        self.log_speed = traffic.log_speed
        self.desired = traffic.desired
        self.length = traffic.length
        self.width = traffic.width
        self.arc = np.zeros(self.cols.size)
        self.speed = np.zeros(self.cols.size)
        self.entered = np.zeros(self.cols.size, dtype=bool)

    def fork(self) -> _Others:
        """An independent copy (its own state; the static arrays shared)."""
        twin = copy.copy(self)
        twin.arc, twin.speed, twin.entered = self.arc.copy(), self.speed.copy(), self.entered.copy()
        return twin

    def at(self, row: int) -> dict[str, np.ndarray]:
        """Everyone's state at ``row`` over the tracks' columns (the ego's column is
        not present); reactive agents entering now take their logged state."""
        tr = self.tracks
        present = tr.valid[row] & self.others
        world = {
            "xy": tr.xy[row].copy(),
            "heading": tr.heading[row].copy(),
            "speed": self.speeds[row].copy(),
            "length": tr.length[row].copy(),
            "width": tr.width[row].copy(),
            "valid": present,
        }
        if self.cols.size:
            here = tr.valid[row, self.cols]
            new = here & ~self.entered
            self.arc[new] = self.log_arc[new, row]
            self.speed[new] = self.log_speed[new, row]
            self.entered |= here
            # Where each agent is, then the path from there to where its log has it
            # (for prediction): one lookup on the rails.
            share = np.linspace(0.0, 1.0, LAG_POINTS)[None, :]
            lag_arc = self.arc[:, None] + (self.log_arc[:, row] - self.arc)[:, None] * share
            poses_xy, poses_heading = self.rails.poses(np.hstack([self.arc[:, None], lag_arc]))
            world["xy"][self.cols[here]] = poses_xy[here, 0]
            world["heading"][self.cols[here]] = poses_heading[here, 0]
            world["speed"][self.cols[here]] = self.speed[here]
            lag = np.repeat(tr.xy[row][:, None, :], LAG_POINTS, axis=1)
            lag[self.cols[here]] = poses_xy[here, 1:]
            world["lag"] = lag
        return world

    def advance(
        self, row: int, next_row: int, world: dict[str, np.ndarray], ego: VehicleState,
        dt_s: float,
    ) -> None:  # fmt: skip
        """Move the reactive agents from ``row`` to ``next_row``, all at once, against
        everyone's boxes at ``row`` (the ego's included)."""
        if self.cols.size == 0:
            return
        present = np.flatnonzero(world["valid"])
        obstacles = reactive.Boxes(
            xy=np.vstack([world["xy"][present], ego.xy[None]]),
            heading_rad=np.append(world["heading"][present], ego.heading_rad),
            length_m=np.append(world["length"][present], ego.length_m),
            width_m=np.append(world["width"][present], ego.width_m),
            speed_mps=np.append(world["speed"][present], max(ego.speed_mps, 0.0)),
        )
        row_of = np.full(self.tracks.valid.shape[1], -1)
        row_of[present] = np.arange(present.size)
        active = self.tracks.valid[row, self.cols]
        arc1, speed1 = reactive.step(
            self.rails, self.arc, self.speed, self.desired, self.length, self.width,
            obstacles, row_of[self.cols], dt_s, self.settings,
        )  # fmt: skip
        # Never ahead of the log: the logged stops (lights, give-ways) stay.
        limit = self.log_arc[:, min(next_row, self.log_arc.shape[1] - 1)]
        capped = arc1 > limit
        arc1 = np.where(capped, limit, arc1)
        log_v = self.log_speed[:, min(next_row, self.log_speed.shape[1] - 1)]
        speed1 = np.where(capped, np.minimum(speed1, log_v), speed1)
        self.arc = np.where(active, arc1, self.arc)
        self.speed = np.where(active, speed1, self.speed)


# ---------------------------------------------------------------------- the planner's frame
def _planner_frame(
    log: Frame, columns: np.ndarray, world: dict[str, np.ndarray], ego_id: int, kind: int,
    ego: VehicleState, path: np.ndarray,
) -> Frame:  # fmt: skip
    """The logged frame with everyone at their simulated state (``world``, over the
    tracks' ``columns`` of the frame's agents), reactive agents' paths led from where
    they are to their logged paths, and the recorded ego replaced by the simulated one
    (its path: ``path``), the ego last."""
    keep = log.ids != ego_id
    idx = np.flatnonzero(keep)
    cols = columns[idx]
    new_index = np.full(log.n_agents, -1, dtype=np.int64)
    new_index[idx] = np.arange(idx.size)
    rows = np.flatnonzero(keep[log.path_agent])
    lag = world.get("lag")
    own = log.paths[rows]
    if lag is not None:  # each candidate led in from where the agent is now
        own = np.concatenate([lag[columns[log.path_agent[rows]]], own], axis=1)
    prefix = 0 if lag is None else LAG_POINTS
    width_p = max(own.shape[1], path.shape[0])
    paths = np.empty((rows.size + 1, width_p, 2))
    paths[:-1, : own.shape[1]] = own
    paths[:-1, own.shape[1] :] = own[:, -1:]
    paths[-1, : path.shape[0]] = path
    paths[-1, path.shape[0] :] = path[-1]
    valid = log.valid[idx] & (cols >= 0) & world["valid"][cols]
    n = idx.size
    return Frame.from_padded(
        ids=np.append(log.ids[idx], ego_id),
        kinds=np.append(log.kinds[idx], kind),
        xy=np.vstack([np.where(valid[:, None], world["xy"][cols], log.xy[idx]), ego.xy[None]]),
        heading=np.append(np.where(valid, world["heading"][cols], log.heading[idx]), ego.heading_rad),
        speed=np.append(np.where(valid, np.maximum(world["speed"][cols], 0.0), log.speed[idx]),
                        max(ego.speed_mps, 0.0)),
        length=np.append(log.length[idx], ego.length_m),
        width=np.append(log.width[idx], ego.width_m),
        valid=np.append(valid, True),
        paths=paths,
        path_points=np.append(log.path_points[rows] + prefix, path.shape[0]),
        path_agent=np.append(new_index[log.path_agent[rows]], n),
        ego=n,
        t=log.t,
    )  # fmt: skip


def _with_actuators(request: PlanRequest, state: VehicleState, tracker: Tracker) -> PlanRequest:
    """``request`` with the simulated ego's actuator state: its acceleration and, from a
    tracker that steers (not ``perfect``), its steering angle. The request is built from a
    frame, which carries neither (acceleration 0, steering unknown): a planner that
    simulates its proposals from the ego's state (``pdm``) would otherwise start them from
    actuators the vehicle does not have, and judge proposals the vehicle cannot drive
    (under ``lqr`` the acceleration lags its command by 0.2 s)."""
    steer = None if isinstance(tracker, PerfectTracker) else state.steer_rad
    ego = dataclasses.replace(request.ego, accel_mps2=state.accel_mps2, steer_rad=steer)
    return dataclasses.replace(request, ego=ego)


def _shifted(plan: Plan, dt: float) -> Plan | None:
    """The rest of ``plan`` after ``dt`` seconds, or None when too little is left."""
    later = plan.times_s >= dt - 1e-9
    if later.sum() < 2:
        return None
    return dataclasses.replace(
        plan,
        times_s=plan.times_s[later] - plan.times_s[later][0],
        xy=plan.xy[later],
        heading_rad=plan.heading_rad[later],
        speed_mps=plan.speed_mps[later],
    )


def _brake(state: VehicleState, dt: float) -> VehicleState:
    v1 = max(0.0, state.speed_mps - FALLBACK_DECEL_MPS2 * dt)
    travel = 0.5 * (state.speed_mps + v1) * dt
    direction = np.array([math.cos(state.heading_rad), math.sin(state.heading_rad)])
    return dataclasses.replace(
        state, xy=state.xy + travel * direction, speed_mps=v1, accel_mps2=-FALLBACK_DECEL_MPS2
    )


# ---------------------------------------------------------------------- one run
@dataclasses.dataclass(frozen=True)
class _Run:
    """A scene and an ego, prepared once for all of its runs (all agents, each filter)."""

    scene: Any
    tracks: Any
    speeds: np.ndarray
    shared: _SceneRuns
    ego_id: int
    column: int
    schedule: list[tuple[int, Frame]]
    columns: list[np.ndarray]  # per scheduled frame: the tracks' column of each agent
    first_index: int
    stride: int
    start: VehicleState
    kind: int
    reference: np.ndarray
    top_speed: float
    route: np.ndarray  # the logged ego's path, extended: progress is measured along it
    expert_progress_m: float
    lanes: list[np.ndarray]
    expert_excursion_m: float  # the logged ego's worst corner outside the drivable corridor


@dataclasses.dataclass(frozen=True, eq=False)  # not slotted: caches on the instance
class _SceneRuns:
    """What every ego's runs in one scene share, computed once per scene: the tracks,
    everyone's logged speeds, each frame's track columns, the drivable lanes and the
    reactive agents' static data for all of the scene's vehicles."""

    scene: Any

    @functools.cached_property
    def tracks(self) -> Any:
        return self.scene.tracks()

    @functools.cached_property
    def speeds(self) -> np.ndarray:
        return logged_speeds(self.scene, self.tracks)

    @functools.cached_property
    def columns(self) -> dict[int, np.ndarray]:
        """Per frame index: the tracks' column of each of its agents."""
        return {i: self.tracks.index_of(f.ids) for i, f in self.scene.indexed}

    @functools.cached_property
    def lanes(self) -> list[np.ndarray]:
        return [
            np.asarray(lane.centerline, dtype=np.float64)
            for lane in self.scene.map.lanes
            if lane.kind in DRIVABLE_LANE_KINDS and len(lane.centerline) >= 2
        ]

    @functools.cached_property
    def vehicles(self) -> _Traffic:
        tracks = self.tracks
        return _Traffic.of(tracks, self.speeds, np.flatnonzero(tracks.kinds == Kind.VEHICLE))

    def traffic(self, mode: str, ego_column: int) -> _Traffic:
        """The reactive agents of an ego's run: every vehicle but the ego (``reactive``),
        none (``log``)."""
        vehicles = self.vehicles
        if mode != "reactive":
            return vehicles.rows(np.zeros(0, np.int64))
        return vehicles.rows(np.flatnonzero(vehicles.cols != ego_column))


def _prepare(scene: Any, ego_id: int, settings: PlanSettings) -> _Run:
    """The ego's runs prepared; ``scene``: a loaded scene or its :class:`_SceneRuns`."""
    shared = scene if isinstance(scene, _SceneRuns) else _SceneRuns(scene)
    scene = shared.scene
    indexed = scene.indexed
    period = float(scene.frame_period_s)
    stride = max(1, round(1.0 / (REPLAN_HZ * period)))
    steps = [(i, f) for i, f in indexed if np.any((f.ids == ego_id) & f.valid)]
    if not steps:
        raise ReplayError(f"{scene.path}: agent {ego_id} is never valid in this scene")
    first_index, first = steps[0]
    schedule = [(i, f) for i, f in indexed if i >= first_index and (i - first_index) % stride == 0]
    start = first.with_ego(int(np.flatnonzero(first.ids == ego_id)[0]))
    e = start.ego
    tracks = shared.tracks
    column = int(np.flatnonzero(tracks.ids == ego_id)[0])
    duration = (schedule[-1][0] - first_index) * period
    whole_s = tracks.valid.shape[0] * tracks.dt_s
    top_speed = target_speed(tracks, 0, column, whole_s, float(start.speed[e]))
    # The reference: the ego's first path candidate, extended straight beyond any
    # distance the run can cover.
    rows = np.flatnonzero(start.path_agent == e)
    reach = top_speed * (duration + settings.horizon_s) + 50.0
    ext, points = extend_paths(
        start.paths[rows[:1]], start.path_points[rows[:1]], start.heading[e : e + 1],
        np.array([reach]),
    )  # fmt: skip
    reference = _distinct(ext[0, : points[0]])
    # The recorded route: the logged ego's own positions over the run, extended straight.
    last_row = round((schedule[-1][1].t - tracks.t0_s) / tracks.dt_s)
    first_row = round((first.t - tracks.t0_s) / tracks.dt_s)
    logged = tracks.valid[first_row : last_row + 1, column]
    logged_xy = tracks.xy[first_row : last_row + 1, column][logged]
    expert = metrics.EgoHistory(
        times_s=np.zeros(logged_xy.shape[0]), xy=logged_xy,
        heading_rad=tracks.heading[first_row : last_row + 1, column][logged],
        speed_mps=np.zeros(logged_xy.shape[0]), length_m=float(start.length[e]),
        width_m=float(start.width[e]),
    )  # fmt: skip
    logged_xy = _distinct(logged_xy) if logged_xy.shape[0] else start.xy[e : e + 1]
    route_ext, route_points = extend_paths(
        logged_xy[None], np.array([logged_xy.shape[0]]), start.heading[e : e + 1],
        np.array([float(cumulative_lengths(logged_xy[None])[0, -1]) + reach]),
    )  # fmt: skip
    route = _distinct(route_ext[0, : route_points[0]])
    route_cum = cumulative_lengths(route[None])[0]
    _, expert_arc = project_points(logged_xy[[0, -1]], route, route_cum)
    lanes = shared.lanes
    excursion = metrics.corridor_excursion_m(expert, lanes, LANE_WIDTH_M) if lanes else np.zeros(1)
    return _Run(
        scene=scene,
        tracks=tracks,
        speeds=shared.speeds,
        shared=shared,
        ego_id=ego_id,
        column=column,
        schedule=schedule,
        columns=[shared.columns[i] for i, _ in schedule],
        first_index=first_index,
        stride=stride,
        start=VehicleState(
            xy=start.xy[e].copy(),
            heading_rad=float(start.heading[e]),
            speed_mps=float(start.speed[e]),
            length_m=float(start.length[e]),
            width_m=float(start.width[e]),
        ),
        kind=int(start.kinds[e]),
        reference=reference,
        top_speed=top_speed,
        route=route,
        expert_progress_m=float(expert_arc[1] - expert_arc[0]),
        lanes=lanes,
        expert_excursion_m=float(np.max(excursion, initial=0.0)),
    )


def _distinct(points: np.ndarray) -> np.ndarray:
    """``points`` without consecutive repeats."""
    return points[np.r_[True, np.any(np.diff(points, axis=0) != 0, axis=1)]]


def _ego_path(state: VehicleState, reference: np.ndarray, cum: np.ndarray) -> np.ndarray:
    """The ego's path for the planner's frame: from where it is along the reference."""
    _, arc = project_points(state.xy[None], reference, cum)
    ahead = reference[np.searchsorted(cum, arc[0], side="right") :]
    path = np.vstack([state.xy[None], ahead]) if ahead.shape[0] else state.xy[None]
    if path.shape[0] < 2:
        direction = np.array([math.cos(state.heading_rad), math.sin(state.heading_rad)])
        path = np.vstack([state.xy, state.xy + direction])
    return path


def drive(
    run: _Run,
    planner: Planner,
    flt: Filter,
    tracker: Tracker,
    settings: ClosedLoopSettings,
) -> dict[str, Any]:
    """One closed-loop run of the prepared ego with the agents ``flt`` keeps; one row."""
    return drive_all(run, planner, [flt], tracker, settings)[0]


@dataclasses.dataclass
class _Timeline:
    """What one or more runs that have not parted yet share: the others, the ego's
    state and its plan to fall back on, and their history so far."""

    others: _Others
    state: VehicleState
    previous: Plan | None
    ego_xy: np.ndarray
    ego_heading: np.ndarray
    ego_speed: np.ndarray
    hist: dict[str, np.ndarray]
    failures: int = 0

    def fork(self) -> _Timeline:
        return dataclasses.replace(
            self, others=self.others.fork(), ego_xy=self.ego_xy.copy(),
            ego_heading=self.ego_heading.copy(), ego_speed=self.ego_speed.copy(),
            hist={name: values.copy() for name, values in self.hist.items()},
        )  # fmt: skip


@dataclasses.dataclass
class _Lane:
    """One filter's run: its timeline (shared with the runs it has not parted from) and
    its own timings."""

    flt: Filter
    timeline: _Timeline
    plan_ms: list[float] = dataclasses.field(default_factory=list)
    filter_ms: list[float] = dataclasses.field(default_factory=list)
    kept: list[int] = dataclasses.field(default_factory=list)


def _same_course(a: Plan | None, b: Plan | None) -> bool:
    """Whether the ego moves alike under plans ``a`` and ``b``: both unusable, or both
    usable with the same trajectory (all the tracker and the fallback read)."""
    usable_a = a is not None and a.ok and a.times_s.size >= 2
    usable_b = b is not None and b.ok and b.times_s.size >= 2
    if not (usable_a and usable_b):
        return usable_a == usable_b
    assert a is not None and b is not None
    return all(
        np.array_equal(x, y)
        for x, y in (
            (a.times_s, b.times_s), (a.xy, b.xy), (a.heading_rad, b.heading_rad),
            (a.speed_mps, b.speed_mps),
        )
    )  # fmt: skip


def drive_all(
    run: _Run,
    planner: Planner,
    filters: list[Filter],
    tracker: Tracker,
    settings: ClosedLoopSettings,
) -> list[dict[str, Any]]:
    """The closed-loop runs of the prepared ego, one per filter, one row each, stepped
    together: while runs have moved alike (their plans gave the same trajectories) they
    share one timeline (the others, the ego, the planner's frame and request), and only
    the filter and the planner run per filter; a run whose plan differs parts with a
    copy. Each row is what a run on its own gives."""
    scene, tracks = run.scene, run.tracks
    period = float(scene.frame_period_s)
    step_dt = run.stride * period
    cum = cumulative_lengths(run.reference[None])[0]
    traffic = run.shared.traffic(settings.agents, run.column)
    n_steps = len(run.schedule)
    shape = (n_steps, tracks.valid.shape[1])
    start = _Timeline(
        others=_Others(tracks, run.speeds, run.column, traffic, settings.reactive),
        state=run.start, previous=None, ego_xy=np.zeros((n_steps, 2)),
        ego_heading=np.zeros(n_steps), ego_speed=np.zeros(n_steps),
        hist={
            "xy": np.zeros((*shape, 2)), "heading": np.zeros(shape), "speed": np.zeros(shape),
            "length": np.zeros(shape), "width": np.zeros(shape),
            "valid": np.zeros(shape, bool),
        },
    )  # fmt: skip
    lanes = [_Lane(flt, start) for flt in filters]
    times = np.zeros(n_steps)
    for k, (_index, log) in enumerate(run.schedule):
        row = round((log.t - tracks.t0_s) / tracks.dt_s)
        times[k] = log.t
        for line in list({id(lane.timeline): lane.timeline for lane in lanes}.values()):
            sharing = [lane for lane in lanes if lane.timeline is line]
            state = line.state
            world = line.others.at(row)
            for name in line.hist:
                line.hist[name][k] = world[name]
            line.ego_xy[k], line.ego_heading[k] = state.xy, state.heading_rad
            line.ego_speed[k] = state.speed_mps
            if k == n_steps - 1:
                continue
            path = _ego_path(state, run.reference, cum)
            frame = _planner_frame(log, run.columns[k], world, run.ego_id, run.kind, state, path)
            target = max(run.top_speed, state.speed_mps)
            try:
                request = plan_request(
                    frame, scene.map, target_speed_mps=target,
                    horizon_s=settings.plan.horizon_s, dt_s=settings.plan.dt_s,
                )  # fmt: skip
                request = _with_actuators(request, state, tracker)
            except NoReferencePath:
                request = None
            plans: list[Plan | None] = []
            for lane in sharing:
                plan: Plan | None = None
                if request is not None:
                    answer = lane.flt.apply(frame)
                    lane.filter_ms.append(answer.time_ms)
                    keep = np.isin(request.agents.ids, answer.kept_ids)
                    lane.kept.append(int(keep.sum()))
                    plan = planner.plan(request.with_agents(request.agents.subset(keep)))
                    lane.plan_ms.append(plan.plan_ms)
                plans.append(plan)
            next_row = round((run.schedule[k + 1][1].t - tracks.t0_s) / tracks.dt_s)
            line.others.advance(row, next_row, world, state, step_dt)  # the ego's state now
            # The runs that planned alike move on together; the others part.
            courses: list[tuple[Plan | None, list[_Lane]]] = []
            for lane, plan in zip(sharing, plans, strict=True):
                for course, members in courses:
                    if _same_course(course, plan):
                        members.append(lane)
                        break
                else:
                    courses.append((plan, [lane]))
            for i, (plan, members) in enumerate(courses):
                own = line if i == 0 else line.fork()
                _move(own, plan, state, tracker, step_dt)
                for lane in members:
                    lane.timeline = own
    rows: list[dict[str, Any]] = []
    scored: dict[int, tuple[dict[str, Any], float]] = {}
    for lane in lanes:
        line = lane.timeline
        if id(line) not in scored:  # runs that never parted share their scores
            ego = metrics.EgoHistory(
                times_s=times, xy=line.ego_xy, heading_rad=line.ego_heading,
                speed_mps=line.ego_speed, length_m=run.start.length_m,
                width_m=run.start.width_m,
            )  # fmt: skip
            hist = line.hist
            seen = metrics.OthersHistory(
                ids=tracks.ids, kinds=tracks.kinds, xy=hist["xy"], heading_rad=hist["heading"],
                speed_mps=hist["speed"], length_m=hist["length"], width_m=hist["width"],
                valid=hist["valid"],
            )  # fmt: skip
            scored[id(line)] = (
                _scores(ego, seen, run),
                _close_following_s(ego, seen, run.reference, cum, step_dt),
            )
        row, headway = scored[id(line)]
        rows.append(_row(run, planner, lane, tracker, settings, row, headway, line.failures))
    return rows


def _move(
    line: _Timeline, plan: Plan | None, state: VehicleState, tracker: Tracker, step_dt: float
) -> None:
    """The ego of ``line`` from ``state`` over one step: along ``plan`` when usable, else
    along its previous plan while it lasts, else braking (a failure)."""
    if plan is not None and plan.ok and plan.times_s.size >= 2:
        line.state, line.previous = tracker.follow(state, plan, step_dt), _shifted(plan, step_dt)
        return
    line.failures += 1
    previous = line.previous
    if previous is not None and previous.times_s[-1] >= step_dt:
        line.state, line.previous = (
            tracker.follow(state, previous, step_dt),
            _shifted(previous, step_dt),
        )
    else:
        line.state, line.previous = _brake(state, step_dt), None


def _row(
    run: _Run, planner: Planner, lane: _Lane, tracker: Tracker, settings: ClosedLoopSettings,
    scores: dict[str, Any], headway_s: float, failures: int,
) -> dict[str, Any]:  # fmt: skip
    """One run's row (:data:`CLOSED_LOOP_COLUMNS`)."""
    scene = run.scene
    plan_ms = lane.plan_ms
    durations = np.asarray(plan_ms) if plan_ms else np.array([math.nan])
    return {
        "scene": scene_key(pathlib.Path(str(scene.path))),
        "dataset": scene.metadata.get("dataset", ""),
        "planner": planner.name,
        "ego_id": run.ego_id,
        "ego_kind": KIND_NAMES[run.kind],
        "agents": settings.agents,
        "tracker": tracker.name,
        "filter": lane.flt.name,
        "steps": len(run.schedule),
        "duration_s": (run.schedule[-1][0] - run.first_index) * float(scene.frame_period_s),
        **scores,
        "time_headway_below_1s_s": headway_s,
        "plan_ms_median": float(np.nanmedian(durations)) if plan_ms else math.nan,
        "plan_ms_p95": float(np.nanquantile(durations, 0.95)) if plan_ms else math.nan,
        "filter_ms_median": float(np.median(lane.filter_ms)) if lane.filter_ms else math.nan,
        "plan_failures": failures,
        "mean_agents": float(np.mean(lane.kept)) if lane.kept else math.nan,
    }


def _scores(ego: metrics.EgoHistory, seen: metrics.OthersHistory, run: _Run) -> dict[str, Any]:
    """The run's metrics (:mod:`replay.analysis.planner_eval.metrics`) as row values."""
    in_lane = metrics.in_lane(ego, run.reference, LANE_WIDTH_M)
    hits = metrics.classify_collisions(ego, seen, in_lane)
    route_cum = cumulative_lengths(run.route[None])[0]
    _, arc = project_points(ego.xy, run.route, route_cum)
    progress_m = float(arc[-1] - arc[0])
    # Judged where the recording's map reaches: up to where the recorded ego went.
    mapped = arc - arc[0] <= run.expert_progress_m + MAPPED_MARGIN_M
    drivable, _ = metrics.drivable_area_ok(
        ego.rows(mapped), run.lanes, LANE_WIDTH_M, allowance_m=run.expert_excursion_m
    )
    direction, _ = metrics.driving_direction(ego, run.lanes, LANE_WIDTH_M)
    ratio = metrics.progress_ratio(progress_m, run.expert_progress_m)
    ttc = metrics.time_to_collision(ego, seen, hits, in_lane)
    min_ttc = float(ttc.min(initial=math.inf))
    comfort = metrics.comfort(ego)
    gaps = box_gap(
        ego.xy[:, None, 0], ego.xy[:, None, 1], ego.heading_rad[:, None], *ego.size(),
        seen.xy[..., 0], seen.xy[..., 1], seen.heading_rad, seen.length_m,
        seen.width_m,
    )  # fmt: skip
    min_gap = float(np.where(seen.valid, gaps, np.inf).min(initial=math.inf))
    return {
        "collisions": hits.n,
        "stopped_ego_collisions": hits.count(metrics.CollisionType.STOPPED_EGO),
        "stopped_track_collisions": hits.count(metrics.CollisionType.STOPPED_TRACK),
        "front_collisions": hits.count(metrics.CollisionType.ACTIVE_FRONT),
        "rear_end_collisions": hits.count(metrics.CollisionType.ACTIVE_REAR),
        "lateral_collisions": hits.count(metrics.CollisionType.ACTIVE_LATERAL),
        "at_fault_collisions": int(hits.at_fault.sum()),
        "drivable_area_ok": drivable,
        "driving_direction_score": direction,
        "progress_m": progress_m,
        "expert_progress_m": run.expert_progress_m,
        "progress_ratio": ratio,
        "min_ttc_s": min_ttc,
        "comfortable": comfort.comfortable,
        "score": metrics.run_score(
            fault_factor=metrics.at_fault_factor(hits, seen.kinds),
            drivable_ok=drivable,
            direction_score=direction,
            progress=ratio,
            min_ttc_s=min_ttc,
            comfortable=comfort.comfortable,
        ),
        "min_gap_m": min_gap,
    }


def _close_following_s(
    ego: metrics.EgoHistory, seen: metrics.OthersHistory, reference: np.ndarray,
    cum: np.ndarray, step_dt: float,
) -> float:  # fmt: skip
    """Time spent less than 1 s behind the nearest agent ahead in the ego's lane (along
    the reference, within half a lane width of it), over the run but its last step."""
    n_t, k = seen.valid.shape
    lateral, arc = project_points(seen.xy.reshape(-1, 2), reference, cum)
    lateral, arc = lateral.reshape(n_t, k), arc.reshape(n_t, k)
    _, ego_arc = project_points(ego.xy, reference, cum)
    ahead = seen.valid & (lateral < 0.5 * LANE_WIDTH_M) & (arc > ego_arc[:, None])
    bumper = arc - ego_arc[:, None] - 0.5 * (seen.length_m + ego.length_m)
    nearest = np.where(ahead, bumper, np.inf).min(axis=1)
    short = (ego.speed_mps > 0.5) & (nearest / np.maximum(ego.speed_mps, 0.5) < 1.0)
    return float(short[:-1].sum() * step_dt)


# ---------------------------------------------------------------------- the unit of work
def load_tracker(name: str) -> Tracker:
    """The tracker ``name`` (an unknown name is a user error)."""
    return make_tracker(name)


@functools.lru_cache(maxsize=2)
def _scene(path: str) -> _SceneRuns:
    """A scene read once per process for the runs of its egos, with what they share."""
    return _SceneRuns(load_scene(path))


def run_ego(
    source: str | os.PathLike[str], ego_id: int, settings: ClosedLoopSettings
) -> list[dict[str, Any]]:
    """Every closed-loop run of one ego: once with all agents and once per filter; one
    row each (:data:`CLOSED_LOOP_COLUMNS`). Depends on nothing but its arguments."""
    shared = _scene(str(pathlib.Path(source)))
    if not shared.scene.indexed:
        raise ReplayError(f"{source}: the scene has no frames")
    planner = make_planner(settings.plan.planner)
    tracker = load_tracker(settings.tracker)
    run = _prepare(shared, int(ego_id), settings.plan)
    filters = [KeepAll(name=ALL_AGENTS), *settings.plan.make_filters()]
    return drive_all(run, planner, filters, tracker, settings)


def vehicle_egos(scene: Any, ego: int | str | None) -> tuple[int, ...]:
    """The egos of ``--ego`` that a car planner may drive (vehicles; pedestrians and
    cyclists are no car-planner egos), those present longest first (ties: lower id)."""
    egos = _egos(scene, ego)
    tracks = scene.tracks()
    cols = tracks.index_of(np.asarray(egos, dtype=np.int64))
    ok = (cols >= 0) & (tracks.kinds[np.maximum(cols, 0)] == Kind.VEHICLE)
    frames = tracks.valid.sum(axis=0)
    chosen = [(int(e), int(frames[c])) for e, c, good in zip(egos, cols, ok, strict=True) if good]
    return tuple(e for e, _ in sorted(chosen, key=lambda item: (-item[1], item[0])))
