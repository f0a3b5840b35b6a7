"""Open loop: at every replayed frame, plan once with all agents and once per filter.

For each (scene, ego, frame) the planner gets the ego's state, its reference path, its
lanes and every other agent with the toolkit's own prediction (constant speed along the
agent's path; :func:`replay.planning.inputs.plan_request`). It plans once with all of
them (the reference plan) and once with the agents each filter keeps; each filtered plan
is compared with the reference (:func:`replay.planning.compare.compare_plans`): did the
plan change, by how much, and did the filter drop the agent that constrained the
reference plan?

The ego's *target speed* is the speed the driver was willing to drive
(:func:`replay.planning.truth.target_speed`): the larger of its speed now and the fastest
it drove over the planning horizon in the recorded future.

With ``truth`` set, every agent is also removed on its own ("all agents but this one"),
which labels it *planner-important* when the plan changes (Waymo's CausalAgents idea).
Agents the planner provably cannot react to (``Planner.may_matter`` False) are labelled
unimportant without that plan.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import numpy as np

from replay.core.egos import load_scene
from replay.core.engine import Stride, seen_from
from replay.errors import ReplayError
from replay.planning.compare import (
    EXECUTED_S,
    changed_within,
    compare_plans,
    conflicts,
    max_shift_m,
    safety_verdict,
)
from replay.planning.errors import NoReferencePath
from replay.planning.inputs import ego_kind, plan_request, plans_for
from replay.planning.registry import make_planner
from replay.planning.truth import planner_truth, target_speed
from replay.planning.types import Plan, Planner, PlanRequest, cold
from risk.cascade import CascadeConfig
from risk.filtering import CascadeFilter, Filter, parse_filter
from risk.frame import Frame
from risk.motion import moving_agent_ids

#: The reference filter's name: every valid other agent.
ALL_AGENTS = "none"


@dataclasses.dataclass(frozen=True)
class PlanSettings:
    """What ``replay plan`` runs: the planner, the filters and the comparison.

    ``tolerance_m``: a filtered plan *changed* when it moves more than this from the
    all-agents plan at any equal time within the horizon (or its stop/go, lane or success
    differs); see :func:`replay.planning.compare.compare_plans`.
    """

    planner: str = "idm"
    filters: tuple[str, ...] = ("cascade",)
    cascade: CascadeConfig = dataclasses.field(default_factory=CascadeConfig.default)
    tolerance_m: float = 0.5
    horizon_s: float = 5.0
    dt_s: float = 0.1
    truth: bool = False
    #: ``vehicles``: plan for vehicle egos only (ego-frames of pedestrians, cyclists and
    #: other agents are skipped and counted); ``all``: every ego.
    ego_kinds: str = "vehicles"

    def make_filters(self) -> list[Filter]:
        """The filters, parsed once (an unknown spec raises FilterSpecError)."""
        specs = [s for s in self.filters if s.strip() != ALL_AGENTS]
        # The planners read the kept agents only: cascades run without their tiers.
        filters = [parse_filter(spec, self.cascade, tiers=False) for spec in specs]
        names = [f.name for f in filters]
        if len(set(names)) != len(names):
            raise ReplayError(f"--filter: a filter is given twice ({', '.join(names)})")
        return filters


class _Columns:
    """Rows collected as columns (one list per column)."""

    def __init__(self, names: Sequence[str]) -> None:
        self.data: dict[str, list[Any]] = {name: [] for name in names}

    def add(self, **values: Any) -> None:
        for name, column in self.data.items():
            column.append(values[name])

    def __len__(self) -> int:
        return len(next(iter(self.data.values()), []))


PLAN_COLUMNS = (
    "scene", "dataset", "planner", "ego_id", "frame", "t_s", "filter", "n_others",
    "n_agents", "filter_ms", "plan_ms", "plan_ok", "changed", "max_shift_m", "why",
    "stops", "lane", "blocking_id", "blocking_dropped", "reason", "target_speed_mps",
    "ego_kind",
    "ego_speed_mps", "changed_1s", "max_shift_1s_m", "unsafe", "unsafe_agent_id",
)  # fmt: skip

#: Column types of the tables (columns that may be all null need theirs stated).
SCHEMA: dict[str, str] = {
    "scene": "str", "dataset": "str", "planner": "str", "filter": "str", "why": "str",
    "reason": "str", "ego_kind": "str", "ego_id": "int", "frame": "int", "n_others": "int", "n_agents": "int",
    "lane": "int", "blocking_id": "int", "agent_id": "int", "kind": "int", "t_s": "float",
    "filter_ms": "float", "plan_ms": "float", "max_shift_m": "float",
    "target_speed_mps": "float", "distance_m": "float", "planner_shift_m": "float",
    "plan_ok": "bool", "changed": "bool", "stops": "bool", "blocking_dropped": "bool",
    "planner_label": "bool", "planner_skipped": "bool", "kept_by_cascade": "bool",
    "ego_speed_mps": "float", "changed_1s": "bool", "max_shift_1s_m": "float",
    "unsafe": "bool", "unsafe_agent_id": "int",
}  # fmt: skip

TRUTH_COLUMNS = (
    "scene", "dataset", "planner", "ego_id", "frame", "t_s", "agent_id", "kind",
    "distance_m", "planner_label", "planner_shift_m", "planner_skipped", "kept_by_cascade",
)  # fmt: skip


@dataclasses.dataclass
class ScenePlans:
    """One scene's rows: plans (one per ego-frame and filter) and, with ``truth``, one
    per (ego-frame, agent)."""

    plans: dict[str, list[Any]]
    truth: dict[str, list[Any]] | None
    egos: tuple[int, ...]
    ego_frames: int
    no_path: int
    #: Ego-frames and distinct egos not planned for their kind (PlanSettings.ego_kinds),
    #: by kind name.
    skipped_ego_frames: dict[str, int] = dataclasses.field(default_factory=dict)
    skipped_egos: dict[str, int] = dataclasses.field(default_factory=dict)


def scene_key(path: pathlib.Path) -> str:
    """A scene's name in the tables: its folder (the dataset) and file name, so that
    equal file names of two datasets stay apart."""
    return f"{path.parent.name}/{path.name}" if path.parent.name else path.name


def _egos(scene: Any, ego: int | str | None) -> tuple[int, ...]:
    if ego == "all":
        return tuple(int(i) for i in moving_agent_ids(scene.frames()))
    if ego is not None:
        return (int(ego),)
    value = scene.metadata.get("ego_id")
    if value is None:
        first = scene.indexed[0][1] if scene.indexed else None
        if first is None:
            raise ReplayError(f"{scene.path}: the scene has no frames")
        return (first.ego_id,)
    return (int(value),)


def ego_frames(scene: Any, egos: Sequence[int], every: Stride) -> Iterator[tuple[int, int, Frame]]:
    """(ego id, frame index, frame seen from that ego) at the stride, where it is valid."""
    step = every.frames_at(float(scene.frame_period_s))
    for ego_id in egos:
        for index, frame in scene.indexed:
            if index % step:
                continue
            seen = seen_from(frame, ego_id)
            if seen is not None:
                yield ego_id, index, seen


def plan_scene(
    source: str | os.PathLike[str],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    every: Stride | int = 1,
    planner: Planner | None = None,
    filters: Sequence[Filter] | None = None,
    on_frame: Any = None,
) -> ScenePlans:
    """Every (ego, frame) of one scene file in open loop; see the module's docstring."""
    path = pathlib.Path(source)
    scene = load_scene(path)
    if not scene.indexed:
        raise ReplayError(f"{path}: the scene has no frames")
    planner = make_planner(settings.planner) if planner is None else planner
    filters = settings.make_filters() if filters is None else list(filters)
    egos = _egos(scene, ego)
    known = set(np.concatenate([f.ids[f.valid] for _, f in scene.indexed]).tolist())
    missing = [e for e in egos if e not in known]
    if missing:
        raise ReplayError(
            f"{path}: no agent with id {missing[0]} in the scene; see 'replay inspect {path}'"
        )
    tracks = scene.tracks()
    column_of = {int(i): c for c, i in enumerate(tracks.ids)}
    dataset = scene.metadata.get("dataset", "")
    plans = _Columns(PLAN_COLUMNS)
    truth = _Columns(TRUTH_COLUMNS) if settings.truth else None
    cascade = next((f for f in filters if isinstance(f, CascadeFilter)), None)
    if truth is not None and cascade is None:
        cascade = CascadeFilter(settings.cascade, tiers=False)
    n_frames = no_path = 0
    skipped: dict[str, int] = {}
    skipped_ids: dict[str, set[int]] = {}
    for ego_id, index, frame in ego_frames(scene, egos, Stride.of(every)):
        kind = ego_kind(frame)
        if not plans_for(frame, settings.ego_kinds):
            skipped[kind] = skipped.get(kind, 0) + 1
            skipped_ids.setdefault(kind, set()).add(ego_id)
            continue
        n_frames += 1
        row = round((frame.t - tracks.t0_s) / tracks.dt_s)
        speed_now = float(frame.speed[frame.ego])
        target = target_speed(tracks, row, column_of[ego_id], settings.horizon_s, speed_now)
        common = {
            "scene": scene_key(path), "dataset": dataset, "planner": planner.name,
            "ego_id": ego_id, "frame": index, "t_s": float(frame.t),
            "n_others": int(frame.others.sum()), "target_speed_mps": target,
            "ego_kind": kind,
            "ego_speed_mps": speed_now,
        }  # fmt: skip
        try:
            request = plan_request(
                frame, scene.map, target_speed_mps=target, horizon_s=settings.horizon_s,
                dt_s=settings.dt_s,
            )  # fmt: skip
        except NoReferencePath as exc:
            no_path += 1
            for name in (ALL_AGENTS, *(f.name for f in filters)):
                plans.add(
                    **common, filter=name, n_agents=0, filter_ms=0.0, plan_ms=0.0,
                    plan_ok=False, changed=None, max_shift_m=math.nan, why="",
                    stops=False, lane=0, blocking_id=-1, blocking_dropped=None,
                    reason=str(exc), changed_1s=None, max_shift_1s_m=math.nan, unsafe=None,
                    unsafe_agent_id=-1,
                )  # fmt: skip
            continue
        reference = cold(planner).plan(request)
        _add_plan(plans, common, ALL_AGENTS, request.agents.n, 0.0, reference, reference, None)
        # the all-agents plan's own conflicts, once for every filter's safety verdict
        reference_conflicts = conflicts(reference, request.agents, request.ego)
        kept_by: dict[str, np.ndarray] = {}
        for flt in filters:
            answer = flt.apply(frame)
            kept_by[flt.name] = answer.kept_ids
            keep = np.isin(request.agents.ids, answer.kept_ids)
            plan = cold(planner).plan(request.with_agents(request.agents.subset(keep)))
            change = compare_plans(reference, plan, tolerance_m=settings.tolerance_m)
            verdict = safety_verdict(
                plan, request.agents, keep, request.ego, reference_conflicts=reference_conflicts
            )
            _add_plan(
                plans, common, flt.name, int(keep.sum()), answer.time_ms, plan, reference,
                change, kept_ids=answer.kept_ids, tolerance=settings.tolerance_m,
                verdict=verdict,
            )  # fmt: skip
        if truth is not None:
            assert cascade is not None
            kept = kept_by.get(cascade.name)
            if kept is None:
                kept = cascade.apply(frame).kept_ids
            _add_truth(truth, common, frame, request, reference, planner, kept, settings)
        if on_frame is not None:
            on_frame()
    return ScenePlans(
        plans=plans.data,
        truth=None if truth is None else truth.data,
        egos=egos,
        ego_frames=n_frames,
        no_path=no_path,
        skipped_ego_frames=skipped,
        skipped_egos={k: len(v) for k, v in skipped_ids.items()},
    )


def _add_plan(
    plans: _Columns,
    common: dict[str, Any],
    name: str,
    n_agents: int,
    filter_ms: float,
    plan: Plan,
    reference: Plan,
    change: Any,
    *,
    kept_ids: np.ndarray | None = None,
    tolerance: float = 0.0,
    verdict: Any = None,
) -> None:
    if change is None:  # the reference itself: unchanged when it exists, else unknown
        changed, shift, why = (False if plan.ok else None), (0.0 if plan.ok else math.nan), ""
        changed_1s, shift_1s = changed, shift
        unsafe, unsafe_agent = (False if plan.ok else None), -1
    else:
        changed, shift, why = change.changed, change.max_shift_m, change.why
        changed_1s = changed_within(reference, plan, until_s=EXECUTED_S, tolerance_m=tolerance)
        shift_1s = max_shift_m(reference, plan, until_s=EXECUTED_S) if plan.ok else math.nan
        unsafe, unsafe_agent = (None, -1) if verdict is None else (verdict.unsafe, verdict.agent_id)
    blocking_dropped = None
    if kept_ids is not None and reference.ok and reference.blocking_id >= 0:
        blocking_dropped = bool(not np.isin(reference.blocking_id, kept_ids))
    plans.add(
        **common, filter=name, n_agents=n_agents, filter_ms=filter_ms, plan_ms=plan.plan_ms,
        plan_ok=plan.ok, changed=changed, max_shift_m=float(shift), why=why,
        stops=plan.stops, lane=plan.lane, blocking_id=plan.blocking_id,
        blocking_dropped=blocking_dropped, reason=plan.reason, changed_1s=changed_1s,
        max_shift_1s_m=float(shift_1s), unsafe=unsafe, unsafe_agent_id=unsafe_agent,
    )  # fmt: skip


def _add_truth(
    truth: _Columns,
    common: dict[str, Any],
    frame: Frame,
    request: PlanRequest,
    reference: Plan,
    planner: Planner,
    cascade_kept: np.ndarray,
    settings: PlanSettings,
) -> None:
    """One row per agent: does removing it alone change the all-agents plan?"""
    agents = request.agents
    if agents.n == 0:
        return
    labels = planner_truth(planner, request, reference, tolerance_m=settings.tolerance_m)
    index = {int(i): n for n, i in enumerate(frame.ids)}
    rows = np.array([index[int(i)] for i in agents.ids], dtype=np.int64)
    d = frame.xy[rows] - frame.xy[frame.ego]
    distance = np.hypot(d[:, 0], d[:, 1])
    kept = np.isin(agents.ids, cascade_kept)
    keys = ("scene", "dataset", "planner", "ego_id", "frame", "t_s")
    for k in range(agents.n):
        label = labels.label[k]
        truth.add(
            **{key: common[key] for key in keys},
            agent_id=int(agents.ids[k]), kind=int(agents.kinds[k]),
            distance_m=float(distance[k]),
            planner_label=None if np.isnan(label) else bool(label),
            planner_shift_m=float(labels.shift_m[k]), planner_skipped=bool(labels.skipped[k]),
            kept_by_cascade=bool(kept[k]),
        )  # fmt: skip


def plan_scenes(
    sources: Iterable[str | os.PathLike[str]],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    every: Stride | int = 1,
    on_frame: Any = None,
) -> Iterator[tuple[pathlib.Path, ScenePlans]]:
    """:func:`plan_scene` over many scene files, one after the other (one planner and
    one set of filters for all)."""
    planner = make_planner(settings.planner)
    filters = settings.make_filters()
    for source in sources:
        result = plan_scene(
            source, settings, ego=ego, every=every, planner=planner, filters=filters,
            on_frame=on_frame,
        )  # fmt: skip
        yield pathlib.Path(source), result
