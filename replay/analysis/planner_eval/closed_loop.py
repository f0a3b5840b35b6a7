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
to result rows, so that any engine can run it.
"""

from __future__ import annotations

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
from replay.planning.tracking import Tracker, VehicleState, make_tracker
from replay.planning.truth import target_speed
from replay.planning.types import Plan, Planner
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


class _Others:
    """The other agents of one run, over the tracks' columns: logged, or reactive
    vehicles on their rails (state: progress along the rail and speed)."""

    def __init__(
        self, tracks: Any, speeds: np.ndarray, ego_column: int, mode: str,
        settings: reactive.ReactiveSettings,
    ) -> None:  # fmt: skip
        self.tracks = tracks
        self.speeds = speeds
        self.settings = settings
        n = tracks.valid.shape[1]
        self.others = np.ones(n, dtype=bool)
        self.others[ego_column] = False
        is_vehicle = tracks.kinds == Kind.VEHICLE
        self.cols = (
            np.flatnonzero(is_vehicle & self.others)
            if mode == "reactive"
            else np.zeros(0, np.int64)
        )
        rows = _filled(tracks.valid[:, self.cols])  # (T, K)
        cols = self.cols[None, :]
        xy = tracks.xy[rows, cols].transpose(1, 0, 2)  # (K, T, 2)
        heading = tracks.heading[rows, cols].T
        self.rails = reactive.Rails.from_positions(xy, heading)
        t = tracks.valid.shape[0]
        self.log_arc = self.rails.arc_m[:, :t]  # (K, T): the logged progress at each row
        self.log_speed = np.where(tracks.valid[:, self.cols], speeds[:, self.cols], 0.0).T
        self.desired = self.log_speed.max(axis=1, initial=0.0)
        first = np.argmax(tracks.valid[:, self.cols], axis=0)  # the size at a recorded row
        self.length = tracks.length[first, self.cols]
        self.width = tracks.width[first, self.cols]
        self.arc = np.zeros(self.cols.size)
        self.speed = np.zeros(self.cols.size)
        self.entered = np.zeros(self.cols.size, dtype=bool)

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
            xy, heading = self.rails.poses(self.arc[:, None])
            world["xy"][self.cols[here]] = xy[here, 0]
            world["heading"][self.cols[here]] = heading[here, 0]
            world["speed"][self.cols[here]] = self.speed[here]
            # The path from where each agent is to where its log has it (for prediction).
            share = np.linspace(0.0, 1.0, LAG_POINTS)[None, :]
            lag_arc = self.arc[:, None] + (self.log_arc[:, row] - self.arc)[:, None] * share
            lag_xy, _ = self.rails.poses(lag_arc)
            lag = np.repeat(tr.xy[row][:, None, :], LAG_POINTS, axis=1)
            lag[self.cols[here]] = lag_xy[here]
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


def _prepare(scene: Any, ego_id: int, settings: PlanSettings) -> _Run:
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
    tracks = scene.tracks()
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
    lanes = [
        np.asarray(lane.centerline, dtype=np.float64)
        for lane in scene.map.lanes
        if lane.kind in DRIVABLE_LANE_KINDS and len(lane.centerline) >= 2
    ]
    excursion = metrics.corridor_excursion_m(expert, lanes, LANE_WIDTH_M) if lanes else np.zeros(1)
    return _Run(
        scene=scene,
        tracks=tracks,
        speeds=logged_speeds(scene, tracks),
        ego_id=ego_id,
        column=column,
        schedule=schedule,
        columns=[tracks.index_of(f.ids) for _, f in schedule],
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
    scene, tracks = run.scene, run.tracks
    period = float(scene.frame_period_s)
    step_dt = run.stride * period
    cum = cumulative_lengths(run.reference[None])[0]
    others = _Others(tracks, run.speeds, run.column, settings.agents, settings.reactive)
    state = run.start
    plan_ms: list[float] = []
    filter_ms: list[float] = []
    kept: list[int] = []
    failures = 0
    previous: Plan | None = None
    n_steps = len(run.schedule)
    ego_xy = np.zeros((n_steps, 2))
    ego_heading = np.zeros(n_steps)
    ego_speed = np.zeros(n_steps)
    shape = (n_steps, tracks.valid.shape[1])
    hist = {
        "xy": np.zeros((*shape, 2)), "heading": np.zeros(shape), "speed": np.zeros(shape),
        "length": np.zeros(shape), "width": np.zeros(shape), "valid": np.zeros(shape, bool),
    }  # fmt: skip
    times = np.zeros(n_steps)
    for k, (_index, log) in enumerate(run.schedule):
        row = round((log.t - tracks.t0_s) / tracks.dt_s)
        world = others.at(row)
        for name in hist:
            hist[name][k] = world[name]
        ego_xy[k], ego_heading[k], ego_speed[k] = state.xy, state.heading_rad, state.speed_mps
        times[k] = log.t
        if k == n_steps - 1:
            break
        path = _ego_path(state, run.reference, cum)
        frame = _planner_frame(log, run.columns[k], world, run.ego_id, run.kind, state, path)
        target = max(run.top_speed, state.speed_mps)
        try:
            request = plan_request(
                frame, scene.map, target_speed_mps=target, horizon_s=settings.plan.horizon_s,
                dt_s=settings.plan.dt_s,
            )  # fmt: skip
        except NoReferencePath:
            request = None
        plan: Plan | None = None
        if request is not None:
            answer = flt.apply(frame)
            filter_ms.append(answer.time_ms)
            keep = np.isin(request.agents.ids, answer.kept_ids)
            kept.append(int(keep.sum()))
            plan = planner.plan(request.with_agents(request.agents.subset(keep)))
            plan_ms.append(plan.plan_ms)
        next_row = round((run.schedule[k + 1][1].t - tracks.t0_s) / tracks.dt_s)
        others.advance(row, next_row, world, state, step_dt)  # against the ego's state now
        if plan is not None and plan.ok and plan.times_s.size >= 2:
            state, previous = tracker.follow(state, plan, step_dt), _shifted(plan, step_dt)
        else:
            failures += 1
            if previous is not None and previous.times_s[-1] >= step_dt:
                state, previous = (
                    tracker.follow(state, previous, step_dt),
                    _shifted(previous, step_dt),
                )
            else:
                state, previous = _brake(state, step_dt), None
    ego = metrics.EgoHistory(
        times_s=times, xy=ego_xy, heading_rad=ego_heading, speed_mps=ego_speed,
        length_m=run.start.length_m, width_m=run.start.width_m,
    )  # fmt: skip
    seen = metrics.OthersHistory(
        ids=tracks.ids, kinds=tracks.kinds, xy=hist["xy"], heading_rad=hist["heading"],
        speed_mps=hist["speed"], length_m=hist["length"], width_m=hist["width"],
        valid=hist["valid"],
    )  # fmt: skip
    row = _scores(ego, seen, run)
    durations = np.asarray(plan_ms) if plan_ms else np.array([math.nan])
    return {
        "scene": scene_key(pathlib.Path(str(scene.path))),
        "dataset": scene.metadata.get("dataset", ""),
        "planner": planner.name,
        "ego_id": run.ego_id,
        "ego_kind": KIND_NAMES[run.kind],
        "agents": settings.agents,
        "tracker": tracker.name,
        "filter": flt.name,
        "steps": n_steps,
        "duration_s": (run.schedule[-1][0] - run.first_index) * period,
        **row,
        "time_headway_below_1s_s": _close_following_s(ego, seen, run.reference, cum, step_dt),
        "plan_ms_median": float(np.nanmedian(durations)) if plan_ms else math.nan,
        "plan_ms_p95": float(np.nanquantile(durations, 0.95)) if plan_ms else math.nan,
        "filter_ms_median": float(np.median(filter_ms)) if filter_ms else math.nan,
        "plan_failures": failures,
        "mean_agents": float(np.mean(kept)) if kept else math.nan,
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
def _scene(path: str) -> Any:
    """A scene read once per process for the runs of its egos."""
    return load_scene(path)


def run_ego(
    source: str | os.PathLike[str], ego_id: int, settings: ClosedLoopSettings
) -> list[dict[str, Any]]:
    """Every closed-loop run of one ego: once with all agents and once per filter; one
    row each (:data:`CLOSED_LOOP_COLUMNS`). Depends on nothing but its arguments."""
    scene = _scene(str(pathlib.Path(source)))
    if not scene.indexed:
        raise ReplayError(f"{source}: the scene has no frames")
    planner = make_planner(settings.plan.planner)
    tracker = load_tracker(settings.tracker)
    run = _prepare(scene, int(ego_id), settings.plan)
    filters = [KeepAll(name=ALL_AGENTS), *settings.plan.make_filters()]
    return [drive(run, planner, flt, tracker, settings) for flt in filters]


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
