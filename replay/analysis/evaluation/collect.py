"""The agents an evaluation reads: from a run's part files, lazily and only the columns it
uses (:func:`evaluation_agents`), or in memory for the library and the sensitivity sweep
(:func:`collect_agents`, :func:`evaluate_inputs`)."""

from __future__ import annotations

import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import polars as pl

from replay.analysis.evaluation.corpus import EvaluationError, EvaluationSettings
from replay.analysis.evaluation.streaming import evaluate_frame
from replay.analysis.stats.collect import collect, datasets_of
from replay.core.engine import Stride
from replay.jobs import resolve_inputs, scene_refs
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings
from risk.prediction import PredictionSettings

#: Tables that ``replay evaluate`` writes into its output folder (with the sweep's):
#: never read back as inputs from there.
EVALUATION_TABLES = (
    "roc", "miss_rates", "positives", "budgets", "sensitivity", "sensitivity_ranking",
    "sensitivity_findings",
)  # fmt: skip
#: The agents-table columns an evaluation reads (the others, such as positions and
#: per-model times, stay on disk), and the prefixes of the column families it reads.
EVALUATION_COLUMNS = (
    "scene", "frame", "ego_id", "agent_id", "kind", "t_s", "baseline", "dropped_by",
    "distance_m", "speed_mps", "track_ok", "planner_label", "dataset",
)  # fmt: skip
EVALUATION_PREFIXES = ("risk_", "kept_", "truth_", "label_")
#: The order every evaluation reads its rows in (evaluate_table's).
ROW_ORDER = ("scene", "frame", "ego_id")


def evaluation_agents(agents: pl.LazyFrame) -> pl.DataFrame:
    """The columns of ``agents`` that an evaluation uses, sorted by scene, frame and ego
    (stable), collected with polars' streaming engine: the driver never holds the
    columns it does not use, nor a second sorted copy."""
    names = agents.collect_schema().names()
    keep = [c for c in names if c in EVALUATION_COLUMNS or c.startswith(EVALUATION_PREFIXES)]
    lazy = agents.select(keep).sort(*ROW_ORDER, maintain_order=True)
    return lazy.collect(engine="streaming")


def check_tables_hindsight(has_tables: bool, hindsight: HindsightSettings | None) -> None:
    if has_tables and hindsight is not None and hindsight != HindsightSettings():
        raise EvaluationError(
            "tables carry the hindsight truth they were written with; to evaluate other "
            "--truth-* settings give the .mcap scenes"
        )


def evaluate_inputs(
    paths: Sequence[str | os.PathLike[str]],
    *,
    cascade: CascadeConfig | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    settings: EvaluationSettings | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: int | Stride = 1,
) -> dict[str, Any]:
    """Replay (scenes) or read (tables) the inputs and evaluate them; the summary dict.

    ``params`` (model name -> parameters) and ``prediction`` go to every model evaluation
    of the replayed scenes; tables are read as they were written. This is what
    ``replay evaluate`` computes, without writing files."""
    agents, datasets, hs = collect_agents(
        paths, cascade=cascade, params=params, prediction=prediction, hindsight=hindsight,
        workers=workers, progress=progress, ego=ego, every=every,
    )  # fmt: skip

    return evaluate_frame(
        agents, settings=settings, datasets=datasets, hindsight=hs,
        inputs=[str(p) for p in paths],
    )  # fmt: skip


def collect_agents(
    paths: Sequence[str | os.PathLike[str]],
    *,
    cascade: CascadeConfig | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: int | Stride = 1,
    models: Sequence[str] | None = None,
    planner: str | None = None,
    output_dir: str | os.PathLike[str] | None = None,
) -> tuple[pl.DataFrame, dict[str, str], HindsightSettings]:
    """The agents table of scenes, tables or folders (as ``replay stats`` reads them),
    in memory, the dataset of each scene (the name of the folder its file is in) and the
    hindsight settings of its truth columns. ``models``: the risk columns to compute
    (default: all). ``planner``: replay the scenes with that planner's truth beside the
    engine (tables are used as they are). ``output_dir``: the command's output folder,
    never read back."""
    found = resolve_inputs(
        [pathlib.Path(p) for p in paths],
        output_dir=None if output_dir is None else pathlib.Path(output_dir),
        output_stems=EVALUATION_TABLES,
    )
    check_tables_hindsight(bool(found.tables), hindsight)
    hs = hindsight or HindsightSettings()
    agents, _, _, _ = collect(
        found, cascade or CascadeConfig.default(), models=models, workers=workers,
        progress=progress, params=params, prediction=prediction, hindsight=hs, ego=ego,
        every=Stride.of(every), planner=planner,
    )  # fmt: skip
    datasets = datasets_of(scene_refs(found))
    tables = [r for r in scene_refs(found) if r.kind == "table"]
    if tables and "scene" in agents.columns:  # merged tables name their scenes themselves
        dirs = {r.dataset for r in tables}
        for s in agents["scene"].unique().to_list():
            if s not in datasets and len(dirs) == 1:
                datasets[s] = next(iter(dirs))
    return agents, datasets, hs
