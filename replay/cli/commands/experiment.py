"""``replay experiment``: the paper's large-scale experiment on synthetic situations."""

from __future__ import annotations

import pathlib
import sys
import time

import click

from outputs.transaction import OutputGuard
from replay.analysis.experiment import (
    ExperimentResult,
    ExperimentSettings,
    findings,
    lane_width,
    model_times_ms,
    run_experiment,
    write_experiment,
)
from replay.analysis.stats import DEFAULT_ERRORS_MODEL
from replay.analysis.stats.run import format_stats
from replay.cli.limits import SEEDS, SITUATIONS, WORKERS
from replay.core.pool import default_workers
from risk.cascade import CascadeConfig
from risk.registry import resolve_models


@click.command("experiment")
@click.option(
    "--situations",
    type=click.IntRange(2, SITUATIONS.max),
    default=500,
    show_default=True,
    help="Synthetic situations to draw (the paper used about 500).",
)
@click.option(
    "--seed",
    type=SEEDS,
    default=0,
    show_default=True,
    help="Seed of the whole experiment; situation i uses SeedSequence(seed, spawn_key=(i,)).",
)
@click.option(
    "--workers",
    type=WORKERS,
    default=None,
    help="Worker processes for generating and replaying. Default: the number of CPUs.",
)
@click.option(
    "-o",
    "--output",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=pathlib.Path),
    help="Folder for report.md, the tables, summary.json and the plots (created if needed).",
)
@click.option(
    "--errors-model",
    default=DEFAULT_ERRORS_MODEL,
    show_default=True,
    help="The model of the false-negative / false-positive plot (the paper's Fig. 5).",
)
@click.option(
    "--cascade",
    "cascade_file",
    type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    help="Cascade TOML to evaluate. Default: the survival-calibrated cascade shipped with "
    "riskreplay (the paper's).",
)
@click.option(
    "--calibrate-half/--no-calibrate-half",
    default=True,
    show_default=True,
    help="Also calibrate a cascade on the first half of the situations and test it on the "
    "second half.",
)
@click.option(
    "--report",
    "report_copy",
    type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="Also write the report to this file, with image links relative to it (e.g. "
    "docs/experiment-report.md beside -o docs/experiment).",
)
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="Progress bars on stderr."
)
def experiment(
    situations: int,
    seed: int,
    workers: int | None,
    out_dir: pathlib.Path,
    errors_model: str,
    cascade_file: pathlib.Path | None,
    calibrate_half: bool,
    report_copy: pathlib.Path | None,
    progress: bool,
) -> None:
    """Reproduce the paper's large-scale experiment (Sec. V-B) and write report.md.

    Draws synthetic four-way intersection situations with the paper's ranges (30-100
    agents, 5-100 m gaps, 0-25 m/s), runs every risk model and the filter cascade on each
    (in parallel worker processes), and compares every model's ROC curve, AUC and
    robustness (std of TPR across situations) with the paper's findings, one by one.
    Also measures what the paper only proposed: the cascade's false negatives and its
    compute against survival analysis on all agents.

    \b
    Writes into OUTPUT:
      report.md               the comparison with the paper, with the plots
      roc.png, robustness.png, errors.png, cascade_funnel*.png
      summary.json, roc / errors / funnel / per_frame / per_scene (.parquet and .csv)
    """
    resolve_models([errors_model])
    # the paper's experiment: the survival-calibrated cascade unless another is given
    cascade = (
        CascadeConfig.from_toml(cascade_file) if cascade_file else CascadeConfig.named("survival")
    )
    settings = ExperimentSettings(
        situations=situations,
        seed=seed,
        workers=workers or default_workers(),
        errors_model=errors_model,
        calibrate_half=calibrate_half,
    )
    if report_copy is not None and not report_copy.parent.is_dir():
        raise click.UsageError(f"--report: the folder {report_copy.parent} does not exist")
    guard = OutputGuard(inputs=(cascade_file,), files=(report_copy,), folders=(out_dir,))
    with guard:  # checked and locked at once; every file appears together
        start = time.perf_counter()
        result = run_experiment(settings, progress=progress, cascade=cascade)
        files = write_experiment(
            result,
            out_dir,
            command=_command(settings, cascade_file, out_dir, report_copy),
            report_copy=report_copy,
        )
    total = time.perf_counter() - start
    click.echo(_summary(result, total))
    click.echo("Wrote:")
    for path in files.values():
        click.echo(f"  {path}")


def _command(
    settings: ExperimentSettings,
    cascade_file: pathlib.Path | None,
    out_dir: pathlib.Path,
    report_copy: pathlib.Path | None,
) -> str:
    parts = [
        "replay experiment",
        f"--situations {settings.situations}",
        f"--seed {settings.seed}",
        f"--workers {settings.workers}",
    ]
    if settings.errors_model != DEFAULT_ERRORS_MODEL:
        parts.append(f"--errors-model {settings.errors_model}")
    if cascade_file:
        parts.append(f"--cascade {cascade_file.name}")
    if not settings.calibrate_half:
        parts.append("--no-calibrate-half")
    parts.append(f"-o {out_dir}")
    if report_copy is not None:
        parts.append(f"--report {report_copy}")
    return " ".join(parts)


def _summary(result: ExperimentResult, total_s: float) -> str:
    items = findings(
        result.stats,
        model_times_ms(result),
        lane_width_m=lane_width(result),
        model_times=result.tables.model_time_s,
    )
    lines = [format_stats(result.stats)]
    if items:
        lines.append(
            "The paper's findings: " + ", ".join(f"{k} {f.verdict}" for k, f in enumerate(items, 1))
        )
    times = ", ".join(f"{k} {v:.1f} s" for k, v in result.times_s.items())
    lines.append(f"Time: {times}; total {total_s:.1f} s")
    return "\n".join(lines)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(experiment())
