"""``replay evaluate``: every model against the survival baseline and against what really
happened (the hindsight truth), over scenes or tables, with scene-bootstrap intervals.

The workflow is :func:`replay.analysis.evaluation.run.run_evaluation` (the scenes as jobs
on :mod:`replay.jobs`); the corpus steps are :mod:`replay.analysis.evaluation.corpus`
(:func:`replay.analysis.evaluation.collect.evaluate_inputs`: the evaluation without
writing files); the sensitivity sweep is :mod:`replay.analysis.evaluation.sensitivity`."""

from __future__ import annotations

import pathlib
import sys

import click

from replay.analysis.evaluation.corpus import (
    DEFAULT_GROUPINGS,
    GROUPINGS,
    HINDSIGHT_WINDOWS,
    EvaluationSettings,
    check_groupings,
)
from replay.analysis.evaluation.run import EngineChoice, SensitivityRequest, run_evaluation
from replay.cli.ego_options import StrideParam, ego_option, every_option
from replay.cli.engine_options import check_engine_options, engine_options
from replay.cli.limits import RISK_THRESHOLDS, FiniteRange, model_names, refuse_idle
from replay.cli.settings_option import CASCADE_NAMES_HELP, CascadeFile, load_cascade, set_option
from replay.core.engine import Stride
from risk.hindsight import HindsightSettings


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
    "--cascade", "cascade_file", type=CascadeFile(),
    help="Cascade TOML for the scenes. Default: the calibrated cascade shipped with riskreplay. "
    + CASCADE_NAMES_HELP,
)  # fmt: skip
@click.option(
    "--baseline-threshold", type=RISK_THRESHOLDS, default=None,
    help="Survival risk at or above which an agent is important. Default: 1e-25 (the paper's).",
)  # fmt: skip
@click.option(
    "--truth-horizon", type=FiniteRange(), default=None, help="Hindsight horizon, s. Default: 5."
)
@click.option(
    "--truth-gap",
    type=FiniteRange(),
    default=None,
    help="Interaction when the box gap is at most this, m. Default: 0.5.",
)
@click.option(
    "--truth-pet",
    type=FiniteRange(),
    default=None,
    help="Interaction when the PET is at most this, s. Default: 1.",
)
@click.option(
    "--truth-coverage", type=FiniteRange(), default=None,
    help="Share of the horizon both agents must be recorded for a negative. Default: 1.",
)  # fmt: skip
@click.option(
    "--hindsight-windows", type=click.Choice(HINDSIGHT_WINDOWS), default="complete",
    show_default=True,
    help="Score hindsight on complete windows only (the whole horizon recorded for ego and "
    "agent, positives and negatives alike), or on any window (positives seen in censored "
    "windows count too: the rule before). The other rule is reported beside it.",
)  # fmt: skip
@click.option(
    "--planner", default=None,
    help="Replay the scenes with this planner beside the engine (idm, fop, fiss, fiss_plus) "
    "and score every model against planner truth: the agents whose removal alone changes "
    "the plan. Tables are used as they are (their planner_label column, if any).",
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
@engine_options
@click.option(
    "--sensitivity/--no-sensitivity", default=False, show_default=True,
    help="Also run the sensitivity sweep over the baseline's choices (survival threshold, "
    "tau_esc, uncertainty growth, horizon, closest-encounter rule, circle radii): each "
    "variant re-thresholds or recomputes only the models it changes, on the same inputs, "
    "--ego and --every. Writes sensitivity*.parquet/.csv and sensitivity.png.",
)  # fmt: skip
@click.option("--sensitivity-bootstrap", type=click.IntRange(min=0), default=200, show_default=True,
              help="Bootstrap replicates per sensitivity variant.")  # fmt: skip
@click.option("--sensitivity-every", type=StrideParam(), default=None,
              help="Frame stride of the sweep (K frames or Ts seconds). Default: --every.")  # fmt: skip
@click.option("--sensitivity-scenes", type=click.IntRange(min=1), default=1, show_default=True,
              help="The sweep takes every K-th scene of each folder (1: all).")  # fmt: skip
@click.option(
    "--report", "report_path", default=None,
    type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="Also write a Markdown report of the evaluation (and the sweep, with "
    "--sensitivity) to this .md file, its plots into the folder of the same name without "
    ".md (e.g. docs/recorded-evaluation.md and docs/recorded-evaluation/).",
)  # fmt: skip
@click.option(
    "--report-note", default="",
    help="A sentence for the report's 'What was evaluated' (e.g. how tables given as inputs "
    "were made, or which scenes were left out and why).",
)  # fmt: skip
@click.option("--plots/--no-plots", default=True, show_default=True, help="Write the PNG plots.")
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="Progress bar on stderr."
)
@set_option
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
    hindsight_windows: str,
    planner: str | None,
    groupings: str,
    calibration_sites: str | None,
    n_boot: int,
    ego: int | str | None,
    every: Stride,
    seed: int,
    workers: int | None,
    plots: bool,
    progress: bool,
    engine: str = "local",
    ray_address: str | None = None,
    sensitivity: bool = False,
    sensitivity_bootstrap: int = 200,
    sensitivity_every: Stride | None = None,
    sensitivity_scenes: int = 1,
    report_path: pathlib.Path | None = None,
    report_note: str = "",
    sets: tuple[str, ...] = (),
) -> None:
    """Which agents does each filter drop that really came close?

    INPUTS are MCAP scenes, tables written by 'replay run --table' (.parquet or .csv,
    with the truth_* columns), or folders of them, as for 'replay stats'. Every model is
    scored against every reference the table carries: the survival baseline, the
    hindsight truth (the agent came within --truth-gap of the ego, or crossed its path
    within --truth-pet, within --truth-horizon of the recorded future; on complete
    windows by default, see --hindsight-windows), the planner truth (--planner), and
    the dataset's own labels (label_<name> columns). A reference the inputs lack, or
    one without positives, is reported as such. The dataset of a scene is the name of
    the folder its file is in.

    \b
    Writes into OUTPUT:
      summary.json              AUC, TPR at FPR 1/5/10 %, miss rates with 95 % scene-
                                bootstrap intervals, per dataset and kind; the cascade's
                                misses per stage; thresholds moved between sites; the
                                budgets; how the references agree
      budgets.parquet/.csv      share of each reference's positives kept per frame by the
                                top K of each model, nearest K, radius R, the cascade
      roc.parquet/.csv          pooled ROC points, every model x reference
      miss_rates.parquet/.csv   every miss rate as a row (all, per group)
      positives.parquet/.csv    every agent that really came close, and what dropped it
      roc_hindsight.png, miss_rate_by_<grouping>.png, budget_<reference>.png

      failures.csv              the scenes that failed (one line each; left out)
      parts/                    every scene's tables and its done-marker: a rerun into
                                OUTPUT skips complete scenes (see docs/batch.md)

    Exits non-zero when no reference has a positive or every scene failed; scenes that
    fail while others succeed are listed (and in failures.csv), with exit code 0.
    """
    from replay.core.pool import default_workers
    from risk.registry import resolve_models

    refuse_idle(
        "--sensitivity", sensitivity, "sensitivity_bootstrap", "sensitivity_every",
        "sensitivity_scenes",
    )  # fmt: skip
    refuse_idle("--report", report_path is not None, "report_note")
    check_engine_options(engine, ray_address)

    names = model_names(models)
    chosen = tuple(resolve_models(names)) if names is not None else None
    by = check_groupings(_names(groupings))
    cascade = load_cascade(cascade_file, sets)
    given = {
        "horizon_s": truth_horizon, "gap_m": truth_gap, "pet_s": truth_pet,
        "coverage": truth_coverage,
    }  # fmt: skip
    custom = {k: v for k, v in given.items() if v is not None}
    settings = EvaluationSettings(
        models=chosen,
        baseline_threshold=cascade.baseline_threshold
        if baseline_threshold is None
        else baseline_threshold,
        groupings=by,
        calibration_sites=tuple(_names(calibration_sites)) if calibration_sites else None,
        n_boot=n_boot,
        seed=seed,
        hindsight_windows=hindsight_windows,
    )
    sweep = (
        SensitivityRequest(sensitivity_bootstrap, sensitivity_every, sensitivity_scenes)
        if sensitivity
        else None
    )
    run = run_evaluation(
        inputs, out_dir, cascade=cascade, settings=settings,
        hindsight=HindsightSettings(**custom) if custom else None,
        workers=workers or default_workers(), progress=progress, ego=ego, every=every,
        plots=plots, sensitivity=sweep, report_path=report_path, planner=planner,
        report_note=report_note, engine=EngineChoice(engine, workers, ray_address),
        command=" ".join(["replay", "evaluate", *sys.argv[2:]]) if len(sys.argv) > 1 else "",
        extra_inputs=(cascade_file,), show=click.echo,
    )  # fmt: skip
    click.echo("Time: " + ", ".join(f"{k} {v:.1f} s" for k, v in run.summary["time_s"].items()))
    if run.jobs is not None:
        click.echo(f"Scenes: {run.jobs.describe()}")
    click.echo("Wrote:")
    for path in run.files.values():
        click.echo(f"  {path}")
