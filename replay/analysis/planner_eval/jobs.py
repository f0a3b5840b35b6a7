"""``replay plan``'s per-scene work as jobs on the job engine (:mod:`replay.jobs`).

Each job is a module-level pure function ``(ref, settings) -> SceneOutput`` with frozen,
picklable settings, so that local processes and Ray run the same code:

- :func:`match_scene`: the cascade's kept count per ego-frame (summed, in the partial)
  and every other agent's distance to the ego (table ``match_distances``): the matched
  nearest-K and radius cuts (:func:`replay.analysis.planner_eval.study.matched_cuts`);
- :func:`open_loop_scene`: one planner's open loop over one scene (table
  ``plans_<planner>``, with ``--truth`` also ``agents_<planner>``; the counts in the
  partial);
- :func:`vehicle_egos_scene`: the scene's vehicle egos of ``--ego`` (partial only): the
  driver draws the closed-loop sample from them;
- :func:`closed_loop_scene`: one task per scene runs that scene's sampled egos
  (:func:`replay.analysis.planner_eval.closed_loop.run_ego`, which reads the scene once
  per worker for all of them), table ``closed_loop_<planner>``.

The driver reads the tables back lazily and in key order (:meth:`JobReport.scan`), so
the tables and the bootstrap do not depend on the engine or on the finishing order.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Mapping
from typing import Any

import numpy as np
import polars as pl

from replay.analysis.planner_eval.closed_loop import ClosedLoopSettings, run_ego, vehicle_egos
from replay.analysis.planner_eval.open_loop import (
    SCHEMA,
    PlanSettings,
    _egos,
    ego_frames,
    plan_scene,
)
from replay.core.egos import load_scene
from replay.core.engine import Stride
from replay.jobs import Job, SceneOutput, SceneRef, fingerprint
from replay.planning.inputs import plans_for
from risk.filtering import CascadeFilter

_POLARS_TYPES = {"str": pl.String, "int": pl.Int64, "float": pl.Float64, "bool": pl.Boolean}


def dataset_of(path: pathlib.Path) -> str:
    """A scene's dataset: the name of its folder (as in ``replay evaluate``)."""
    return path.parent.name or "."


def _typed(columns: Mapping[str, list[Any]], ref: SceneRef) -> pl.DataFrame:
    """One scene's rows (columns of Python values) as a table with the stated types, its
    key in the ``scene`` column and its folder in ``dataset``."""
    n = len(columns["scene"])
    data = {**columns, "scene": [ref.key] * n, "dataset": [dataset_of(ref.path)] * n}
    return pl.DataFrame(data, schema={k: _POLARS_TYPES[SCHEMA[k]] for k in data})


def _key(name: str, settings: Any) -> str:
    return fingerprint(name, {"settings": repr(settings)})


# ---------------------------------------------------------------------- matched cuts
@dataclasses.dataclass(frozen=True)
class MatchSettings:
    """The matching pass: the cascade (``plan.cascade``), the egos and the stride."""

    plan: PlanSettings
    ego: int | str | None
    every: Stride


def kept_and_distances(
    source: str | pathlib.Path, settings: PlanSettings, ego: int | str | None, every: Stride
) -> tuple[list[int], np.ndarray]:
    """Per ego-frame of one scene that the open loop plans: the cascade's kept count, and
    every other agent's centre distance to the ego (``(n, 2)``: ego-frame number, metres)."""
    scene = load_scene(source)
    cascade = CascadeFilter(settings.cascade, tiers=False)  # the kept count only
    kept: list[int] = []
    distances: list[np.ndarray] = []
    seen = ego_frames(scene, _egos(scene, ego), every)
    planned = (f for _, _, f in seen if plans_for(f, settings.ego_kinds))  # as the open loop
    for n, frame in enumerate(planned):
        kept.append(cascade.apply(frame).n_kept)
        d = frame.xy[frame.others] - frame.xy[frame.ego]
        distances.append(np.stack([np.full(d.shape[0], n), np.hypot(d[:, 0], d[:, 1])], axis=1))
    return kept, (np.concatenate(distances) if distances else np.zeros((0, 2)))


def match_scene(ref: SceneRef, settings: MatchSettings) -> SceneOutput:
    kept, distances = kept_and_distances(ref.path, settings.plan, settings.ego, settings.every)
    table = pl.DataFrame({"distance_m": distances[:, 1].astype(np.float64)})
    return SceneOutput({"match_distances": table}, {"ego_frames": len(kept), "kept": sum(kept)})


def match_job(settings: MatchSettings) -> Job:
    # Only what decides the kept counts and distances (not the filters or the planner).
    essential = (settings.plan.cascade, settings.plan.ego_kinds, settings.ego, settings.every)
    return Job("plan-match", match_scene, settings, _key("plan-match", essential))


# ---------------------------------------------------------------------- open loop
@dataclasses.dataclass(frozen=True)
class OpenLoopSettings:
    """One planner's open loop: ``plan`` (its planner and resolved filters), egos, stride."""

    plan: PlanSettings
    ego: int | str | None
    every: Stride


def plans_table(planner: str) -> str:
    return f"plans_{planner}"


def truth_table(planner: str) -> str:
    return f"agents_{planner}"


def open_loop_scene(ref: SceneRef, settings: OpenLoopSettings) -> SceneOutput:
    result = plan_scene(ref.path, settings.plan, ego=settings.ego, every=settings.every)
    tables: dict[str, pl.DataFrame] = {}
    if result.plans.get("scene"):
        tables[plans_table(settings.plan.planner)] = _typed(result.plans, ref)
    if result.truth is not None and result.truth.get("scene"):
        tables[truth_table(settings.plan.planner)] = _typed(result.truth, ref)
    partial = {
        "ego_frames": result.ego_frames,
        "no_path": result.no_path,
        "skipped_ego_frames": result.skipped_ego_frames,
        "skipped_egos": result.skipped_egos,
    }
    return SceneOutput(tables, partial)


def open_loop_job(settings: OpenLoopSettings) -> Job:
    name = f"plan-open-{settings.plan.planner}"
    return Job(name, open_loop_scene, settings, _key(name, settings))


# ---------------------------------------------------------------------- closed loop
@dataclasses.dataclass(frozen=True)
class EgosSettings:
    ego: int | str | None


def vehicle_egos_scene(ref: SceneRef, settings: EgosSettings) -> SceneOutput:
    """A scene's vehicle egos of ``--ego`` (those present longest first) and how many
    egos ``--ego`` names in all."""
    scene = load_scene(ref.path)
    egos = vehicle_egos(scene, settings.ego)
    return SceneOutput({}, {"vehicle_egos": list(egos), "egos": len(_egos(scene, settings.ego))})


def egos_job(settings: EgosSettings) -> Job:
    return Job("plan-egos", vehicle_egos_scene, settings, _key("plan-egos", settings))


#: At most this many egos of one scene per closed-loop task: a scene with many sampled
#: egos (a dataset of one or two scenes takes a dataset's whole share) would otherwise
#: run them one after another on one worker while the others sit idle.
EGOS_PER_TASK = 4


@dataclasses.dataclass(frozen=True)
class ClosedLoopJobSettings:
    """The closed loop of one planner: ``closed`` (planner, filters, agents, tracker) and
    each task's egos (``egos``: task key -> (scene key, ego ids in the order to run))."""

    closed: ClosedLoopSettings
    egos: tuple[tuple[str, tuple[str, tuple[int, ...]]], ...]


def ego_tasks(
    chosen: dict[str, list[int]], per_task: int | None = None
) -> list[tuple[str, str, tuple[int, ...]]]:
    """(task key, scene key, egos): each scene's sampled egos cut into runs of at most
    ``per_task``; a scene's first task keeps the scene's key, the others add
    ``#egos-NNN`` (zero-padded, so keys sort in the egos' order)."""
    per_task = EGOS_PER_TASK if per_task is None else per_task
    tasks: list[tuple[str, str, tuple[int, ...]]] = []
    for key in sorted(chosen):
        egos = chosen[key]
        for i, start in enumerate(range(0, len(egos), per_task)):
            task_key = key if i == 0 else f"{key}#egos-{i:03d}"
            tasks.append((task_key, key, tuple(egos[start : start + per_task])))
    return tasks


def closed_loop_table(planner: str) -> str:
    return f"closed_loop_{planner}"


def closed_loop_scene(ref: SceneRef, settings: ClosedLoopJobSettings) -> SceneOutput:
    """A run of one scene's sampled egos in closed loop (:func:`ego_tasks`), one task:
    the scene is read once for them (:func:`run_ego` keeps it per worker)."""
    scene_key, egos = dict(settings.egos).get(ref.key, (ref.key, ()))
    rows = [row for ego_id in egos for row in run_ego(ref.path, ego_id, settings.closed)]
    if not rows:
        return SceneOutput({})
    df = pl.DataFrame(rows, infer_schema_length=None).with_columns(
        pl.lit(scene_key).alias("scene"), pl.lit(dataset_of(ref.path)).alias("dataset")
    )
    return SceneOutput({closed_loop_table(settings.closed.plan.planner): df})


def closed_loop_job(settings: ClosedLoopJobSettings) -> Job:
    """The fingerprint covers the whole sample: a rerun of the same command skips its
    complete scenes; another sample (other scenes, another ``--closed-loop-sample``)
    runs again."""
    name = f"plan-closed-{settings.closed.plan.planner}"
    return Job(name, closed_loop_scene, settings, _key(name, settings))
