"""Closed loop: the planner drives the ego, the other agents replay their log.

Non-reactive, like nuPlan's CLS-NR. From the ego's first recorded frame, the planner
re-plans at 10 Hz (at the log's own rate where that is slower: the others' states exist
only at logged frames) and the ego follows each plan **perfectly** until the next
re-plan: its next state is the plan's state at that time (no tracking controller, no
vehicle dynamics beyond what the planner itself respects). When the planner finds no plan
the ego keeps following its previous plan while it lasts, else brakes at 6 m/s² along its
heading; such steps are counted.

The run repeats once with all agents and once per filter, from the same start, so the
difference between the runs is what the filter costs in safety and saves in compute. At
every step the ego's box is checked against every logged agent's box at that time:

- ``collisions``: distinct agents whose box overlapped the ego's; ``rear_end_collisions``:
  those among them that were behind the ego (a non-reactive follower cannot brake for a
  planner that stops where the recorded driver did not);
- ``min_gap_m``: the least box-to-box distance to any agent over the run;
- ``time_headway_below_1s_s``: time spent less than 1 s behind the nearest agent ahead in
  the ego's lane (along its reference path, within half a lane width of it);
- ``progress_m``: distance travelled along the reference path.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from typing import Any

import numpy as np

from replay.analysis.planner_eval.open_loop import ALL_AGENTS, PlanSettings, _egos, scene_key
from replay.core.egos import load_scene
from replay.errors import ReplayError
from replay.planning.errors import NoReferencePath
from replay.planning.inputs import plan_request
from replay.planning.registry import make_planner
from replay.planning.truth import target_speed
from replay.planning.types import Plan, Planner
from risk.filtering import Filter, KeepAll
from risk.frame import Frame
from risk.geometry import cumulative_lengths, extend_paths, project_points
from risk.hindsight import box_gap, boxes_overlap

#: Re-planning rate (Hz) when the log is at least this fast.
REPLAN_HZ = 10.0
#: Deceleration (m/s²) when the planner has no plan and the previous one has run out.
FALLBACK_DECEL_MPS2 = 6.0
#: Lane width (m) for "in the ego's lane" (the leader of the time-headway check).
LANE_WIDTH_M = 3.5

CLOSED_LOOP_COLUMNS = (
    "scene", "dataset", "planner", "ego_id", "filter", "steps", "duration_s",
    "collisions", "rear_end_collisions", "min_gap_m", "time_headway_below_1s_s",
    "progress_m", "plan_ms_median", "plan_ms_p95", "filter_ms_median", "plan_failures",
    "mean_agents",
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class _State:
    xy: np.ndarray
    heading: float
    speed: float


def _frame_with_ego(
    log: Frame, ego_id: int, kind: int, state: _State, length: float, width: float,
    path: np.ndarray,
) -> Frame:  # fmt: skip
    """The logged frame with the recorded ego replaced by the simulated one (its path:
    ``path``), the ego last."""
    keep = log.ids != ego_id
    idx = np.flatnonzero(keep)
    new_index = np.full(log.n_agents, -1, dtype=np.int64)
    new_index[idx] = np.arange(idx.size)
    rows = np.flatnonzero(keep[log.path_agent])
    width_p = max(log.paths.shape[1], path.shape[0])
    paths = np.empty((rows.size + 1, width_p, 2))
    paths[:-1, : log.paths.shape[1]] = log.paths[rows]
    paths[:-1, log.paths.shape[1] :] = log.paths[rows, -1:]
    paths[-1, : path.shape[0]] = path
    paths[-1, path.shape[0] :] = path[-1]
    n = idx.size
    return Frame.from_padded(
        ids=np.append(log.ids[idx], ego_id),
        kinds=np.append(log.kinds[idx], kind),
        xy=np.vstack([log.xy[idx], state.xy[None]]),
        heading=np.append(log.heading[idx], state.heading),
        speed=np.append(log.speed[idx], max(state.speed, 0.0)),
        length=np.append(log.length[idx], length),
        width=np.append(log.width[idx], width),
        valid=np.append(log.valid[idx], True),
        paths=paths,
        path_points=np.append(log.path_points[rows], path.shape[0]),
        path_agent=np.append(new_index[log.path_agent[rows]], n),
        ego=n,
        t=log.t,
    )


def _advance(plan: Plan, dt: float) -> _State:
    """The plan's state ``dt`` seconds after its start (linear in between samples)."""
    t = plan.times_s
    x = float(np.interp(dt, t, plan.xy[:, 0]))
    y = float(np.interp(dt, t, plan.xy[:, 1]))
    heading = float(np.interp(dt, t, np.unwrap(plan.heading_rad)))
    speed = float(np.interp(dt, t, plan.speed_mps))
    return _State(np.array([x, y]), heading, speed)


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


def _brake(state: _State, dt: float) -> _State:
    v1 = max(0.0, state.speed - FALLBACK_DECEL_MPS2 * dt)
    travel = 0.5 * (state.speed + v1) * dt
    direction = np.array([math.cos(state.heading), math.sin(state.heading)])
    return _State(state.xy + travel * direction, state.heading, v1)


def drive(
    scene: Any,
    ego_id: int,
    planner: Planner,
    flt: Filter,
    settings: PlanSettings,
) -> dict[str, Any]:
    """One closed-loop run of ``ego_id`` with the agents ``flt`` keeps; one result row."""
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
    kind, length, width = int(start.kinds[e]), float(start.length[e]), float(start.width[e])
    duration = (schedule[-1][0] - first_index) * period
    tracks = scene.tracks()
    column = int(np.flatnonzero(tracks.ids == ego_id)[0])
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
    reference = ext[0, : points[0]]
    reference = reference[np.r_[True, np.any(np.diff(reference, axis=0) != 0, axis=1)]]
    cum = cumulative_lengths(reference[None])[0]
    state = _State(start.xy[e].copy(), float(start.heading[e]), float(start.speed[e]))
    step_dt = stride * period
    plan_ms: list[float] = []
    filter_ms: list[float] = []
    kept: list[int] = []
    failures = 0
    previous: Plan | None = None
    collided: set[int] = set()
    rear: set[int] = set()
    min_gap = math.inf
    close_s = 0.0
    _, arc0 = project_points(state.xy[None], reference, cum)
    for k, (_index, log) in enumerate(schedule):
        row = round((log.t - tracks.t0_s) / tracks.dt_s)
        _, arc = project_points(state.xy[None], reference, cum)
        ahead = reference[np.searchsorted(cum, arc[0], side="right") :]
        path = np.vstack([state.xy[None], ahead]) if ahead.shape[0] else state.xy[None]
        if path.shape[0] < 2:
            path = np.vstack(
                [state.xy, state.xy + np.array([math.cos(state.heading), math.sin(state.heading)])]
            )
        frame = _frame_with_ego(log, ego_id, kind, state, length, width, path)
        gap, hit, behind, thw_short = _safety(frame, tracks, row, column, state, reference, cum)
        min_gap = min(min_gap, gap)
        collided |= hit
        rear |= behind
        if k == len(schedule) - 1:
            break
        if thw_short:
            close_s += step_dt
        target = max(top_speed, state.speed)
        try:
            request = plan_request(
                frame, scene.map, target_speed_mps=target, horizon_s=settings.horizon_s,
                dt_s=settings.dt_s,
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
        if plan is not None and plan.ok and plan.times_s.size >= 2:
            state, previous = _advance(plan, step_dt), _shifted(plan, step_dt)
        else:
            failures += 1
            if previous is not None and previous.times_s[-1] >= step_dt:
                state, previous = _advance(previous, step_dt), _shifted(previous, step_dt)
            else:
                state, previous = _brake(state, step_dt), None
    _, arc_end = project_points(state.xy[None], reference, cum)
    times = np.asarray(plan_ms) if plan_ms else np.array([math.nan])
    return {
        "scene": scene_key(pathlib.Path(str(scene.path))),
        "dataset": scene.metadata.get("dataset", ""),
        "planner": planner.name,
        "ego_id": ego_id,
        "filter": flt.name,
        "steps": len(schedule),
        "duration_s": duration,
        "collisions": len(collided),
        "rear_end_collisions": len(rear),
        "min_gap_m": float(min_gap),
        "time_headway_below_1s_s": close_s,
        "progress_m": float(arc_end[0] - arc0[0]),
        "plan_ms_median": float(np.nanmedian(times)) if plan_ms else math.nan,
        "plan_ms_p95": float(np.nanquantile(times, 0.95)) if plan_ms else math.nan,
        "filter_ms_median": float(np.median(filter_ms)) if filter_ms else math.nan,
        "plan_failures": failures,
        "mean_agents": float(np.mean(kept)) if kept else math.nan,
    }


def _safety(
    frame: Frame,
    tracks: Any,
    row: int,
    ego_column: int,
    state: _State,
    reference: np.ndarray,
    cum: np.ndarray,
) -> tuple[float, set[int], set[int], bool]:
    """Gap, collided ids, rear-end ids and "less than 1 s behind the leader" at one step,
    against every logged agent (vectorised over agents)."""
    if not 0 <= row < tracks.valid.shape[0]:
        return math.inf, set(), set(), False
    others = tracks.valid[row].copy()
    others[ego_column] = False
    cols = np.flatnonzero(others)
    if cols.size == 0:
        return math.inf, set(), set(), False
    e = frame.ego
    xa, ya = tracks.xy[row, cols, 0], tracks.xy[row, cols, 1]
    ha, la, wa = tracks.heading[row, cols], tracks.length[row, cols], tracks.width[row, cols]
    ex, ey = np.full(cols.size, state.xy[0]), np.full(cols.size, state.xy[1])
    eh = np.full(cols.size, state.heading)
    el, ew = np.full(cols.size, frame.length[e]), np.full(cols.size, frame.width[e])
    gaps = box_gap(ex, ey, eh, el, ew, xa, ya, ha, la, wa)
    overlap = boxes_overlap(ex, ey, eh, el, ew, xa, ya, ha, la, wa)
    c, s = math.cos(state.heading), math.sin(state.heading)
    along = (xa - state.xy[0]) * c + (ya - state.xy[1]) * s
    hit_ids = {int(i) for i in tracks.ids[cols[overlap]]}
    rear_ids = {int(i) for i in tracks.ids[cols[overlap & (along < 0)]]}
    # The leader: the nearest agent ahead along the reference within half a lane of it.
    lateral, arc = project_points(np.stack([xa, ya], axis=1), reference, cum)
    _, ego_arc = project_points(state.xy[None], reference, cum)
    ahead = (lateral < 0.5 * LANE_WIDTH_M) & (arc > ego_arc[0])
    short = False
    if ahead.any() and state.speed > 0.5:
        bumper = arc[ahead] - ego_arc[0] - 0.5 * (la[ahead] + frame.length[e])
        short = bool(bumper.min() / state.speed < 1.0)
    return float(gaps.min()), hit_ids, rear_ids, short


def closed_loop_scene(
    source: str | os.PathLike[str],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    planner: Planner | None = None,
    filters: list[Filter] | None = None,
    egos_per_scene: int | None = None,
) -> list[dict[str, Any]]:
    """Closed-loop runs of one scene: per ego, once with all agents and once per filter.

    ``egos_per_scene``: at most this many of the egos, the ones present longest (ties:
    lower id), so that a sample covers each scene's best-observed agents."""
    path = pathlib.Path(source)
    scene = load_scene(path)
    if not scene.indexed:
        raise ReplayError(f"{path}: the scene has no frames")
    planner = make_planner(settings.planner) if planner is None else planner
    filters = settings.make_filters() if filters is None else filters
    egos = _egos(scene, ego)
    if egos_per_scene is not None and len(egos) > egos_per_scene:
        seen = np.concatenate([f.ids[f.valid] for _, f in scene.indexed])
        ids, counts = np.unique(seen, return_counts=True)
        frames_of = dict(zip(ids.tolist(), counts.tolist(), strict=True))
        egos = tuple(sorted(egos, key=lambda e: (-frames_of.get(e, 0), e))[:egos_per_scene])
    rows = []
    for ego_id in egos:
        for flt in [KeepAll(name=ALL_AGENTS), *filters]:
            rows.append(drive(scene, ego_id, planner, flt, settings))
    return rows
