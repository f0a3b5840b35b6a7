"""Compute, write and plot the statistics of collected tables: the shared tail of
``replay stats``, ``replay batch`` and (for its tables) ``replay experiment``; and
``replay stats``' workflow from its inputs (:func:`stats_of_inputs`: every scene a job on
an engine, :mod:`replay.jobs`, its tables streamed to ``OUT/parts/``)."""

from __future__ import annotations

import os
import pathlib
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import polars as pl

from outputs.transaction import OutputGuard
from replay.analysis.stats.collect import TablesSettings, collected_parts, tables_job
from replay.analysis.stats.compute import DatasetStats, compute_stats
from replay.analysis.stats.files import OUTPUT_TABLES, write_stats
from replay.analysis.stats.plots import plot_all
from replay.analysis.stats.streaming import StatsPart, stream_stats
from replay.core.engine import Stride
from replay.jobs import JobReport, resolve_inputs, run_jobs, scene_refs
from replay.jobs.scenes import check_not_outputs
from risk.cascade import CascadeConfig


@dataclass(frozen=True, eq=False)
class StatsRun:
    stats: DatasetStats
    files: dict[str, pathlib.Path]
    jobs: JobReport | None = None


def run_stats(
    agents: pl.DataFrame,
    frames: pl.DataFrame,
    out_dir: pathlib.Path,
    *,
    models: Sequence[str] | None,
    errors_model: str,
    stage_names: Sequence[str],
    tier_names: Sequence[str],
    cascade: CascadeConfig,
    inputs: Sequence[str],
    plots: bool,
    times: dict[str, float],
) -> StatsRun:
    """Compute the statistics, write their tables and (``plots``) their plots into
    ``out_dir``; adds each step's wall time to ``times``."""
    start = time.perf_counter()
    stats = compute_stats(
        agents,
        frames,
        models=models,
        errors_model=errors_model,
        stage_names=stage_names,
        tier_names=tier_names,
        baseline_threshold=cascade.baseline_threshold,
        inputs=inputs,
    )
    times["statistics"] = time.perf_counter() - start
    return write_and_plot(stats, out_dir, plots=plots, times=times)


def write_and_plot(
    stats: DatasetStats, out_dir: pathlib.Path, *, plots: bool, times: dict[str, float]
) -> StatsRun:
    """Write the tables and (``plots``) the plots of ``stats`` into ``out_dir``; adds
    each step's wall time to ``times``."""
    start = time.perf_counter()
    files = write_stats(stats, out_dir)
    times["write tables"] = time.perf_counter() - start
    if plots:
        start = time.perf_counter()
        files.update(plot_all(stats, out_dir))
        times["plots"] = time.perf_counter() - start
    return StatsRun(stats, files)


def stats_of_inputs(
    inputs: Sequence[pathlib.Path],
    out_dir: pathlib.Path,
    *,
    cascade: CascadeConfig,
    models: Sequence[str] | None,
    errors_model: str,
    workers: int | None,
    progress: bool,
    ego: int | str | None = None,
    every: int | Stride = 1,
    plots: bool = True,
    extra_inputs: Sequence[pathlib.Path | None] = (),
    engine: str = "local",
    ray_address: str | None = None,
    show: Callable[[str], None] | None = None,
) -> tuple[StatsRun, dict[str, float]]:
    """``replay stats``: replay the scenes and read the tables of ``inputs`` as jobs on
    ``engine`` (their tables go to ``OUT/parts/`` as they finish; complete scenes of an
    earlier run are skipped; failures are listed in ``OUT/failures.csv`` and left out),
    then compute, write and plot their statistics into ``out_dir``
    (:class:`outputs.transaction.OutputGuard`: these files appear together;
    ``extra_inputs``, a cascade file, are refused as outputs too). Returns the run and
    each step's wall time."""
    found = resolve_inputs(
        list(inputs), output_dir=pathlib.Path(out_dir), output_stems=OUTPUT_TABLES
    )
    names = ["summary.json", *(f"{t}{x}" for t in OUTPUT_TABLES for x in (".parquet", ".csv"))]
    check_not_outputs(found, pathlib.Path(out_dir), names)
    guard = OutputGuard(inputs=(*found.scenes, *found.tables, *extra_inputs), folders=(out_dir,))
    with guard:  # checked and locked before the replays; all files appear together
        engine_models = None
        if models is not None:
            engine_models = tuple(dict.fromkeys([*models, errors_model, "survival"]))
        times: dict[str, float] = {}
        start = time.perf_counter()
        job = tables_job(
            TablesSettings(cascade=cascade, models=engine_models, ego=ego, every=Stride.of(every))
        )
        report = run_jobs(
            job, scene_refs(found), out_dir, engine=engine, workers=workers,
            ray_address=ray_address, progress=progress, desc="stats: scenes",
        )  # fmt: skip
        if show is not None and report.failures and report.done:  # the stats may yet fail
            show(report.describe())
        parts = collected_parts(report, cascade)
        times["replay / read"] = time.perf_counter() - start
        # the inputs as given (scenes first), without those that failed
        given = {pathlib.Path(os.path.abspath(p)): p for p in (*found.scenes, *found.tables)}
        complete = {d.ref.path for d in report.done}
        done = [str(p) for a, p in given.items() if a in complete]
        # One part at a time (issue 38): the driver never holds the corpus's rows.
        pairs = [
            StatsPart(pathlib.Path(d.tables["agents"]), pathlib.Path(d.tables["frames"]))
            for d in report.done
        ]
        with tempfile.TemporaryDirectory(prefix="replay-stats-") as scratch:
            start = time.perf_counter()
            stats = stream_stats(
                pairs, pathlib.Path(scratch), models=models, errors_model=errors_model,
                stage_names=parts.stage_names, tier_names=parts.tier_names,
                baseline_threshold=cascade.baseline_threshold, inputs=done,
            )  # fmt: skip
            times["statistics"] = time.perf_counter() - start
            result = write_and_plot(stats, out_dir, plots=plots, times=times)
    return StatsRun(result.stats, result.files, report), times


#: How this AUC is computed, and why ``replay evaluate``'s differs (0.615 against 0.771
#: on the same scenes surprised a user; issue 31).
STATS_AUC_NOTE = (
    "AUC: area under the mean of the per-situation ROC curves against the survival"
    " baseline (each situation's TPR and FPR averaged at every threshold, as the paper"
    " does); 'replay evaluate' pools all agent-frames into one curve, so its AUCs differ"
)


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
        STATS_AUC_NOTE,
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
