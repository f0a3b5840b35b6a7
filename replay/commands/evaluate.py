"""``replay evaluate``: every model against the survival baseline and against what really
happened (the hindsight truth), over scenes or tables, with scene-bootstrap intervals.

:func:`evaluate_inputs` is the same without writing files (notebooks, the sensitivity
sweep). It lives here because the input collection it shares with ``replay stats``
(:func:`replay.commands.stats.collect`) does; the library part is
:mod:`replay.evaluation`."""

from __future__ import annotations

import os
import pathlib
import time
from collections.abc import Sequence
from typing import Any

import click
import polars as pl

from base.guard import OutputGuard
from replay.commands.ego_options import ego_option, every_option
from replay.engine import Stride
from replay.evaluation import (
    DEFAULT_GROUPINGS,
    GROUPINGS,
    EvaluationError,
    EvaluationSettings,
    evaluate_agents,
)
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings


def evaluate_inputs(
    paths: Sequence[str | os.PathLike[str]],
    *,
    cascade: Any = None,
    params: Any = None,
    prediction: Any = None,
    hindsight: HindsightSettings | None = None,
    settings: EvaluationSettings | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: Any = 1,
) -> dict[str, Any]:
    """Replay (scenes) or read (tables) the inputs and evaluate them; the summary dict.

    ``params`` (model name -> parameters) and ``prediction`` go to every model evaluation
    of the replayed scenes; tables are read as they were written. This is what
    ``replay evaluate`` runs, without writing files."""
    agents, datasets, hs = collect_agents(
        paths, cascade=cascade, params=params, prediction=prediction, hindsight=hindsight,
        workers=workers, progress=progress, ego=ego, every=every,
    )  # fmt: skip
    return evaluate_agents(
        agents, settings=settings, datasets=datasets, hindsight=hs,
        inputs=[str(p) for p in paths],
    )  # fmt: skip


def collect_agents(
    paths: Sequence[str | os.PathLike[str]],
    *,
    cascade: Any = None,
    params: Any = None,
    prediction: Any = None,
    hindsight: HindsightSettings | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: Any = 1,
) -> tuple[pl.DataFrame, dict[str, str], HindsightSettings]:
    """The agents table of scenes, tables or folders (as ``replay stats`` reads them),
    the dataset of each scene (the name of the folder its file is in) and the hindsight
    settings of its truth columns."""
    from replay.commands.stats import collect, resolve_inputs, scene_names

    found = resolve_inputs([pathlib.Path(p) for p in paths])
    if found.tables and hindsight is not None and hindsight != HindsightSettings():
        raise EvaluationError(
            "tables carry the hindsight truth they were written with; to evaluate other "
            "--truth-* settings give the .mcap scenes"
        )
    hs = hindsight or HindsightSettings()
    agents, _, _, _ = collect(
        found,
        cascade or CascadeConfig.default(),
        models=None,
        workers=workers,
        progress=progress,
        params=params,
        prediction=prediction,
        hindsight=hs,
        ego=ego,
        every=Stride.of(every),
    )
    files = [*found.scenes, *found.tables]
    names = scene_names(files)
    datasets = {n: p.resolve().parent.name for n, p in zip(names, files, strict=True)}
    if "scene" in agents.columns:  # merged tables name their scenes themselves
        table_dirs = {p.resolve().parent.name for p in found.tables}
        for s in agents["scene"].unique().to_list():
            if s not in datasets and len(table_dirs) == 1:
                datasets[s] = next(iter(table_dirs))
    return agents, datasets, hs


def _names(text: str | None) -> list[str]:
    return [x.strip() for x in (text or "").split(",") if x.strip()]


@click.command("evaluate")
@click.argument(
    "inputs", nargs=-1, required=True, type=click.Path(exists=True, path_type=pathlib.Path)
)
@click.option(
    "-o", "--output", "out_dir", required=True,
    type=click.Path(file_okay=False, path_type=pathlib.Path),
    help="Folder for summary.json, the tables and the plots (created if needed).",
)  # fmt: skip
@click.option("--models", default=None, help="Models to evaluate, comma-separated. Default: all.")
@click.option(
    "--cascade", "cascade_file", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    help="Cascade TOML for the scenes. Default: the calibrated cascade shipped with riskreplay.",
)  # fmt: skip
@click.option(
    "--baseline-threshold", type=float, default=None,
    help="Survival risk at or above which an agent is important. Default: 1e-25 (the paper's).",
)  # fmt: skip
@click.option("--truth-horizon", type=float, default=None, help="Hindsight horizon, s. Default: 5.")
@click.option(
    "--truth-gap",
    type=float,
    default=None,
    help="Interaction when the box gap is at most this, m. Default: 0.5.",
)
@click.option(
    "--truth-pet",
    type=float,
    default=None,
    help="Interaction when the PET is at most this, s. Default: 1.",
)
@click.option(
    "--truth-coverage", type=float, default=None,
    help="Share of the horizon both agents must be recorded for a negative. Default: 1.",
)  # fmt: skip
@click.option(
    "--by", "groupings", default=",".join(DEFAULT_GROUPINGS), show_default=True,
    help=f"Break results down by these, comma-separated ({', '.join(GROUPINGS)}).",
)  # fmt: skip
@click.option(
    "--calibration-sites", default=None,
    help="Recording sites whose thresholds are tested on the others, comma-separated. "
    "Default: every other site in sorted order.",
)  # fmt: skip
@click.option("--bootstrap", "n_boot", type=click.IntRange(min=0), default=1000, show_default=True,
              help="Scene-bootstrap replicates for the 95 % intervals (0: none).")  # fmt: skip
@ego_option("Default: each scene's recorded ego. Applies to scenes, not to tables.")
@every_option
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the bootstrap.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Processes replaying scenes in parallel. Default: the number of CPUs.")  # fmt: skip
@click.option("--plots/--no-plots", default=True, show_default=True, help="Write the PNG plots.")
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="Progress bar on stderr."
)
def evaluate(
    inputs: tuple[pathlib.Path, ...],
    out_dir: pathlib.Path,
    models: str | None,
    cascade_file: pathlib.Path | None,
    baseline_threshold: float | None,
    truth_horizon: float | None,
    truth_gap: float | None,
    truth_pet: float | None,
    truth_coverage: float | None,
    groupings: str,
    calibration_sites: str | None,
    n_boot: int,
    ego: int | str | None,
    every: Stride,
    seed: int,
    workers: int | None,
    plots: bool,
    progress: bool,
) -> None:
    """Which agents does each filter drop that really came close?

    INPUTS are MCAP scenes, tables written by 'replay run --table' (.parquet or .csv,
    with the truth_* columns), or folders of them, as for 'replay stats'. Every model is
    scored against two references: the survival baseline and the hindsight truth (the
    agent came within --truth-gap of the ego, or crossed its path within --truth-pet,
    within --truth-horizon of the recorded future; censored frames are left out and
    counted). The dataset of a scene is the name of the folder its file is in.

    \b
    Writes into OUTPUT:
      summary.json              AUC, TPR at FPR 1/5/10 %, miss rates with 95 % scene-
                                bootstrap intervals, per dataset and kind; the cascade's
                                misses per stage; thresholds moved between sites
      roc.parquet/.csv          pooled ROC points, every model x reference
      miss_rates.parquet/.csv   every miss rate as a row (all, per group)
      positives.parquet/.csv    every agent that really came close, and what dropped it
      roc_hindsight.png, miss_rate_by_<grouping>.png

    Exits non-zero when no agent came close (every rate against hindsight undefined).
    """
    from replay.evaluation import check_groupings, format_evaluation, write_evaluation
    from replay.pool import default_workers
    from risk.registry import resolve_models

    chosen = tuple(resolve_models(_names(models))) if models else None
    by = check_groupings(_names(groupings))
    cascade = CascadeConfig.from_toml(cascade_file) if cascade_file else CascadeConfig.default()
    given = {
        "horizon_s": truth_horizon, "gap_m": truth_gap, "pet_s": truth_pet,
        "coverage": truth_coverage,
    }  # fmt: skip
    custom = {k: v for k, v in given.items() if v is not None}
    hindsight = HindsightSettings(**custom) if custom else None
    settings = EvaluationSettings(
        models=chosen,
        baseline_threshold=cascade.baseline_threshold
        if baseline_threshold is None
        else baseline_threshold,
        groupings=by,
        calibration_sites=tuple(_names(calibration_sites)) if calibration_sites else None,
        n_boot=n_boot,
        seed=seed,
    )
    guard = OutputGuard(inputs=[*inputs, cascade_file], folders=(out_dir,))
    with guard:  # checked and locked at once; every file appears together
        start = time.perf_counter()
        agents, datasets, hs = collect_agents(
            inputs, cascade=cascade, hindsight=hindsight, workers=workers or default_workers(),
            progress=progress, ego=ego, every=every,
        )  # fmt: skip
        read_s = time.perf_counter() - start
        start = time.perf_counter()
        summary = evaluate_agents(
            agents, settings=settings, datasets=datasets, hindsight=hs,
            inputs=[str(p) for p in inputs],
        )  # fmt: skip
        summary["time_s"] = {"replay / read": read_s, "evaluation": time.perf_counter() - start}
        files = write_evaluation(summary, agents, out_dir, datasets=datasets, plots=plots)
    click.echo(format_evaluation(summary))
    click.echo("Time: " + ", ".join(f"{k} {v:.1f} s" for k, v in summary["time_s"].items()))
    click.echo("Wrote:")
    for path in files.values():
        click.echo(f"  {path}")
