"""``replay stats``: dataset statistics of scenes or of tables from ``replay run --table``."""

from __future__ import annotations

import pathlib
import sys

import click

from replay.analysis.stats import DEFAULT_ERRORS_MODEL
from replay.analysis.stats.run import format_stats, stats_of_inputs
from replay.cli.ego_options import ego_option, every_option
from replay.cli.engine_options import check_engine_options, engine_options
from replay.cli.limits import model_names
from replay.cli.settings_option import load_cascade, set_option
from replay.core.engine import Stride
from risk.registry import resolve_models


@click.command("stats")
@click.argument(
    "inputs", nargs=-1, required=True, type=click.Path(exists=True, path_type=pathlib.Path)
)
@click.option(
    "-o",
    "--output",
    "out_dir",
    required=True,
    type=click.Path(file_okay=False, path_type=pathlib.Path),
    help="Folder for the tables, summary.json and plots (created if needed).",
)
@click.option(
    "--models",
    default=None,
    help="Models to compare, comma-separated (see 'replay models'). Default: all nine.",
)
@click.option(
    "--errors-model",
    default=DEFAULT_ERRORS_MODEL,
    show_default=True,
    help="The model whose false negatives and false positives over the threshold are "
    "exported (the paper's Fig. 5 uses closest encounter + 2D headway).",
)
@click.option(
    "--cascade",
    "cascade_file",
    type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    help="Cascade TOML for the scenes (and the tier order of CSV tables). "
    "Default: the calibrated cascade shipped with riskreplay.",
)
@engine_options
@ego_option("Default: each scene's recorded ego. Applies to scenes, not to tables.")
@every_option
@click.option("--plots/--no-plots", default=True, show_default=True, help="Write the PNG plots.")
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="Progress bar on stderr."
)
@set_option
def stats(
    inputs: tuple[pathlib.Path, ...],
    out_dir: pathlib.Path,
    models: str | None,
    errors_model: str,
    cascade_file: pathlib.Path | None,
    workers: int | None,
    ego: int | str | None,
    every: Stride,
    plots: bool,
    progress: bool,
    engine: str = "local",
    ray_address: str | None = None,
    sets: tuple[str, ...] = (),
) -> None:
    """How well each risk model filters against the survival baseline, over a dataset.

    INPUTS are MCAP scenes, tables written by 'replay run --table' (.parquet or .csv),
    or folders of them. Scenes are replayed (every model on every agent, and the
    cascade; no .rrd); tables are read as they are. A situation is one frame of one
    scene seen by one ego (with --ego all, every moving agent is an ego in turn).

    \b
    Writes into OUTPUT:
      roc.parquet/.csv        mean ROC curve of every model (exact threshold sweep)
      errors.parquet/.csv     FN and FP over the threshold of --errors-model
      funnel.parquet/.csv     the cascade: agents after each stage, tiers, FN, time
      per_frame, per_scene    one row per situation / scene (.parquet and .csv)
      summary.json            AUC, std of TPR at TPR 0.95 and 1, kept agents, counts
      roc.png, errors.png, cascade_funnel.png
      failures.csv            the inputs that failed (one line each; left out)
      parts/                  every scene's tables and done-marker: a rerun skips
                              complete scenes (see docs/batch.md)

    Exits non-zero when every input failed.
    """
    check_engine_options(engine, ray_address)
    names = model_names(models)
    chosen = resolve_models(names) if names is not None else None
    resolve_models([errors_model])
    cascade = load_cascade(cascade_file, sets)
    result, times = stats_of_inputs(
        inputs, out_dir, cascade=cascade, models=chosen, errors_model=errors_model,
        workers=workers, progress=progress, ego=ego, every=every, plots=plots,
        extra_inputs=(cascade_file,), engine=engine, ray_address=ray_address, show=click.echo,
    )  # fmt: skip
    click.echo(format_stats(result.stats, times))
    if result.jobs is not None:
        click.echo(f"Scenes: {result.jobs.describe()}")
    click.echo("Wrote:")
    for path in result.files.values():
        click.echo(f"  {path}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(stats())
