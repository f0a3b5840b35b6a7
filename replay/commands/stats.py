"""``replay stats``: dataset statistics of scenes or of tables from ``replay run --table``."""

from __future__ import annotations

import pathlib
import sys
import time

import click

from base.guard import OutputGuard
from replay.commands.ego_options import ego_option, every_option
from replay.commands.settings_option import load_cascade, set_option
from replay.engine import Stride
from replay.inputs import collect, resolve_inputs
from replay.limits import WORKERS, model_names
from replay.pool import default_workers
from replay.stats import (
    DEFAULT_ERRORS_MODEL,
    DatasetStats,
)
from replay.stats.files import OUTPUT_TABLES
from replay.stats.run import run_stats
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
@click.option(
    "--workers",
    type=WORKERS,
    default=None,
    help="Processes replaying scenes in parallel. Default: the number of CPUs.",
)
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
    """
    names = model_names(models)
    chosen = resolve_models(names) if names is not None else None
    resolve_models([errors_model])
    cascade = load_cascade(cascade_file, sets)
    found = resolve_inputs(inputs, output_dir=out_dir, output_stems=OUTPUT_TABLES)
    guard = OutputGuard(inputs=(*found.scenes, *found.tables, cascade_file), folders=(out_dir,))
    with guard:  # checked and locked before the replays; all files appear together
        engine_models = None
        if chosen is not None:
            engine_models = list(dict.fromkeys([*chosen, errors_model, "survival"]))
        times: dict[str, float] = {}
        start = time.perf_counter()
        agents, frames, stage_names, tier_names = collect(
            found,
            cascade,
            models=engine_models,
            workers=workers or default_workers(),
            progress=progress,
            ego=ego,
            every=every,
        )
        times["replay / read"] = time.perf_counter() - start
        result = run_stats(
            agents,
            frames,
            out_dir,
            models=chosen,
            errors_model=errors_model,
            stage_names=stage_names,
            tier_names=tier_names,
            cascade=cascade,
            inputs=[str(p) for p in (*found.scenes, *found.tables)],
            plots=plots,
            times=times,
        )
    click.echo(format_stats(result.stats, times))
    click.echo("Wrote:")
    for path in result.files.values():
        click.echo(f"  {path}")


def format_stats(stats: DatasetStats, times: dict[str, float] | None = None) -> str:
    """The end-of-run summary: situations, each model's AUC and operating points, the
    cascade."""
    s = stats.summary
    sit = s["situations"]
    lines = [
        f"{sit['total']} situations ({sit['with_agents']} with agents): baseline empty in "
        f"{sit['empty_baseline']} (TPR undefined), full in {sit['full_baseline']} (FPR "
        f"undefined), no agents in {sit['without_agents']}; "
        f"{s['baseline']['mean_important_per_situation']:.1f} important agents per situation",
        f"  {'model':<22}{'AUC':>7}{'σTPR@.95':>10}{'FPR@.95':>9}{'kept@.95':>10}{'kept@1':>8}",
    ]
    for name, m in s["models"].items():
        p95, p1 = m["points"]["tpr_0.95"], m["points"]["tpr_1"]
        lines.append(
            f"  {name:<22}{m['auc']:>7.3f}{_f(p95['std_tpr'], '.3f'):>10}"
            f"{_f(p95['mean_fpr'], '.3f'):>9}{p95['mean_kept']:>10.1f}{p1['mean_kept']:>8.1f}"
        )
    c = s["cascade"]
    funnel = " -> ".join(f"{x['mean_kept']:.1f}" for x in c["stages"])
    fns = ", ".join(str(x["false_negatives"]) for x in c["stages"])
    lines.append(
        f"Cascade: {c['mean_others']:.1f} -> {funnel} agents per situation; FN per stage "
        f"(cumulative) {fns} of {c['baseline_agent_frames']} important agent-frames"
    )
    if c.get("compute"):
        comp = c["compute"]
        timed = c["timed_situations"]
        where = "" if timed == c["situations"] else f" (the {timed} replayed situations)"
        med_c, med_s = comp["median_cascade_time_s"], comp["median_survival_all_time_s"]
        lines.append(
            f"  compute{where}, median per situation: cascade {1e3 * med_c:.2f} ms vs "
            f"survival analysis on all agents {1e3 * med_s:.2f} ms ({med_c / med_s:.2f}x)"
        )
    if times:
        lines.append("Time: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()))
    return "\n".join(lines)


def _f(value: float | None, fmt: str) -> str:
    return "n/a" if value is None or value != value else format(value, fmt)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(stats())
