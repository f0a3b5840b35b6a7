"""The inputs of ``replay stats`` and ``replay evaluate``, one scene at a time: a scene
replayed, or a table read, into its agents and frames tables (:func:`scene_tables`, the
job both commands run on :mod:`replay.jobs`), and the parts of a run read back.

Scenes are keyed as :mod:`replay.jobs.scenes` says: the ``scene`` column of a replayed
scene's tables is its key (its path relative to the common folder of the inputs)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import polars as pl

from replay.analysis.stats.files import concat_agents, frames_from_agents, read_agents_table
from replay.core.engine import EVERY_FRAME, Stride
from replay.core.pool import parallel_map
from replay.core.stats_sink import stage_names_of, tier_names_of
from replay.core.worker import replay_scene
from replay.errors import ReplayError
from replay.jobs import Inputs, Job, JobReport, SceneOutput, SceneRef, fingerprint, scene_refs
from replay.planning.annotator import PlannerAnnotator
from replay.planning.registry import make_planner
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings
from risk.prediction import PredictionSettings

#: The name of the per-scene job in the markers of ``OUT/parts/.done``.
JOB_NAME = "scene_tables"


@dataclass(frozen=True)
class TablesSettings:
    """What decides a scene's tables (the tables given as inputs are read as written)."""

    cascade: CascadeConfig
    models: tuple[str, ...] | None = None  # risk columns to compute (None: all)
    ego: int | str | None = None
    every: Stride = EVERY_FRAME
    params: Mapping[str, Any] | None = None  # model name -> parameters
    prediction: PredictionSettings | None = None
    hindsight: HindsightSettings | None = None  # settings of the truth columns
    planner: str | None = None  # a planner whose truth the tables carry

    def digest(self) -> str:
        data = {
            "cascade": self.cascade.to_dict(),
            "models": self.models,
            "ego": self.ego,
            "every": [self.every.frames, self.every.seconds],
            "params": None if self.params is None else {k: repr(v) for k, v in self.params.items()},
            "prediction": None if self.prediction is None else repr(self.prediction),
            "hindsight": None if self.hindsight is None else dataclasses.asdict(self.hindsight),
            "planner": self.planner,
        }
        return fingerprint(JOB_NAME, data)


def tables_job(settings: TablesSettings) -> Job:
    """The per-scene job of ``replay stats`` and ``replay evaluate``."""
    if settings.planner is not None:
        make_planner(settings.planner)  # an unknown name or a missing extra: before any work
    return Job(JOB_NAME, scene_tables, settings, settings.digest())


def planner_annotators(name: str) -> list[PlannerAnnotator]:
    """A planner annotator with planner truth (``planner_label`` columns), made in the
    worker process that replays the scene."""
    return [PlannerAnnotator(make_planner(name), truth=True, filtered=False)]


def scene_tables(ref: SceneRef, settings: TablesSettings) -> SceneOutput:
    """One input's ``agents`` and ``frames`` tables; the partial holds its stage and tier
    names, the scenes its rows name and its dataset (the folder its file is in)."""
    if ref.kind == "scene":
        s = settings
        annotators = () if s.planner is None else planner_annotators(s.planner)
        tables = replay_scene(
            ref.path, name=ref.key, cascade=s.cascade, models=s.models, ego=s.ego,
            every=s.every, params=s.params, prediction=s.prediction, hindsight=s.hindsight,
            annotators=annotators,
        )  # fmt: skip
        agents, frames = tables.agents, tables.frames
        stages = list(s.cascade.stage_names)
        tiers = [t.name for t in s.cascade.tiers]
    else:
        agents = read_agents_table(ref.path, scene=ref.key)
        stages = stage_names_of(agents)
        tiers = tier_names_of(agents, fallback=[t.name for t in settings.cascade.tiers])
        frames = frames_from_agents(agents, stages, tiers)
    scenes = [ref.key] if ref.kind == "scene" else sorted(agents["scene"].unique().to_list())
    partial = {
        "kind": ref.kind,
        "rows": agents.height,
        "stage_names": stages,
        "tier_names": tiers,
        "scenes": scenes,
        "dataset": ref.dataset,
    }
    return SceneOutput({"agents": agents, "frames": frames}, partial)


@dataclass(frozen=True)
class Collected:
    """The parts of a run, as lazy frames in key order, with their names."""

    agents: pl.LazyFrame
    frames: pl.LazyFrame
    stage_names: list[str]
    tier_names: list[str]
    datasets: dict[str, str]  # scene -> dataset


def collected_parts(report: JobReport, cascade: CascadeConfig) -> Collected:
    """The agents and frames of every complete scene of ``report``, read lazily; checks
    that tables given as inputs have the scenes' cascade stages."""
    if not report.done:
        first = report.failures[0] if report.failures else None
        why = f": {first.reason}" if first is not None else ""
        raise ReplayError(f"every input failed ({len(report.failures)}){why}")
    stages, tiers = _names([d.partial for d in report.done], cascade)
    datasets = {s: str(d.partial["dataset"]) for d in report.done for s in d.partial["scenes"]}
    return Collected(report.scan("agents"), report.scan("frames"), stages, tiers, datasets)


def _names(
    partials: Sequence[Mapping[str, Any]], cascade: CascadeConfig
) -> tuple[list[str], list[str]]:
    stage_names = list(cascade.stage_names)
    tier_names = [t.name for t in cascade.tiers]
    replayed = any(p["kind"] == "scene" for p in partials)
    for p in partials:
        if p["kind"] != "table":
            continue
        stages = list(p["stage_names"])
        if replayed and stages != stage_names:
            raise ReplayError(
                f"a table's cascade stages ({', '.join(stages)}) differ from the cascade "
                f"the scenes run with ({', '.join(stage_names)}); give --cascade"
            )
        stage_names, tier_names = stages, list(p["tier_names"])
    return stage_names, tier_names


def collect(
    inputs: Inputs,
    cascade: CascadeConfig,
    *,
    models: Sequence[str] | None,
    workers: int,
    progress: bool,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    ego: int | str | None = None,
    every: Stride = EVERY_FRAME,
    planner: str | None = None,
) -> tuple[pl.DataFrame, pl.DataFrame, list[str], list[str]]:
    """Agents and frames tables of every input in memory, with the stage and tier names
    (the library's way, without part files: the sensitivity sweep, notebooks). The
    first failure is raised."""
    settings = TablesSettings(
        cascade, None if models is None else tuple(models), ego, every, params, prediction,
        hindsight, planner,
    )  # fmt: skip
    job = tables_job(settings)
    refs = scene_refs(inputs)
    if not refs:
        raise ReplayError("no input")
    outputs = parallel_map(
        functools.partial(scene_tables, settings=job.settings), refs,
        workers=min(workers, len(refs)), progress=progress, desc="replaying scenes", unit="scene",
    )  # fmt: skip
    stages, tiers = _names([o.partial for o in outputs], cascade)
    agents = concat_agents([o.tables["agents"] for o in outputs])
    frames = pl.concat([o.tables["frames"] for o in outputs], how="diagonal_relaxed")
    return agents, frames, stages, tiers


def datasets_of(refs: Sequence[SceneRef]) -> dict[str, str]:
    """Scene key -> dataset (the folder its file is in)."""
    return {r.key: r.dataset for r in refs}


__all__ = [
    "JOB_NAME",
    "Collected",
    "TablesSettings",
    "collect",
    "collected_parts",
    "datasets_of",
    "planner_annotators",
    "scene_tables",
    "tables_job",
]
