"""``replay evaluate``'s workflow as one library function: every scene replayed (or table
read) as a job on an engine (:mod:`replay.jobs`) into ``OUT/parts/``, every model
evaluated against every reference from the parts one scene at a time
(:mod:`replay.analysis.evaluation.streaming`: the driver never holds the corpus's rows),
optionally the sensitivity sweep (:mod:`replay.analysis.evaluation.sensitivity`, which
does hold the defaults' rows), and the files and the report.

The maths is :mod:`risk.evaluation` and :mod:`risk.roc_counts`; this module only puts
the steps in order. The
outputs appear together at the end (:class:`outputs.transaction.OutputGuard`); the parts
and ``failures.csv`` are written as scenes finish, so that a rerun resumes.
"""

from __future__ import annotations

import pathlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from outputs.transaction import OutputGuard
from replay.analysis.evaluation.collect import (
    EVALUATION_TABLES,
    check_tables_hindsight,
)
from replay.analysis.evaluation.corpus import EvaluationError, EvaluationSettings
from replay.analysis.evaluation.files import format_evaluation, write_evaluation
from replay.analysis.evaluation.report import write_report
from replay.analysis.evaluation.sensitivity import (
    SweepResult,
    format_sweep,
    run_sweep,
    sweep_subset,
    write_sweep,
)
from replay.analysis.evaluation.streaming import StreamSettings, evaluate_parts
from replay.analysis.stats.collect import TablesSettings, collected_parts, tables_job
from replay.core.engine import EVERY_FRAME, Stride
from replay.jobs import JobReport, resolve_inputs, run_jobs, scene_refs
from replay.jobs.scenes import check_not_outputs
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings


@dataclass(frozen=True)
class SensitivityRequest:
    """The sensitivity sweep's own settings (``--sensitivity-*``)."""

    bootstrap: int = 200  # bootstrap replicates of each variant
    every: Stride | None = None  # frame stride of the sweep (None: the evaluation's)
    scenes: int = 1  # every K-th scene of each folder (1: all)


@dataclass(frozen=True)
class EngineChoice:
    """Where the per-scene jobs run (``--engine``, ``--workers``, ``--ray-address``)."""

    name: str = "local"
    workers: int | None = None
    address: str | None = None


@dataclass
class EvaluationRun:
    """What :func:`run_evaluation` computed and wrote."""

    summary: dict[str, Any]
    sweep: SweepResult | None = None
    files: dict[str, pathlib.Path] = field(default_factory=dict)
    jobs: JobReport | None = None


def _quiet(text: str) -> None:
    pass


#: The files an evaluation writes into its output folder (besides its plots).
_OUTPUT_NAMES = (
    "summary.json",
    *(f"{t}{x}" for t in EVALUATION_TABLES for x in (".parquet", ".csv")),
)


def check_report_path(report_path: pathlib.Path | None, out_dir: pathlib.Path) -> None:
    """A report inside OUTPUT must be a ``.md`` file: any other name there may be one of
    the evaluation's own files (``OUTPUT/summary.json`` was refused only after the whole
    evaluation had run)."""
    if report_path is None or report_path.suffix.lower() == ".md":
        return
    if report_path.absolute().parent == out_dir.absolute():
        raise EvaluationError(
            f"--report {report_path}: lies in the output folder beside the evaluation's own"
            f" files; name a .md file (e.g. {out_dir / 'report.md'}) or put it elsewhere"
        )


def run_evaluation(
    inputs: Sequence[pathlib.Path],
    out_dir: pathlib.Path,
    *,
    cascade: CascadeConfig,
    settings: EvaluationSettings,
    hindsight: HindsightSettings | None = None,
    workers: int = 1,
    progress: bool = True,
    ego: int | str | None = None,
    every: Stride = EVERY_FRAME,
    plots: bool = True,
    sensitivity: SensitivityRequest | None = None,
    report_path: pathlib.Path | None = None,
    command: str = "",
    extra_inputs: Sequence[pathlib.Path | None] = (),
    show: Callable[[str], None] = _quiet,
    planner: str | None = None,
    report_note: str = "",
    engine: EngineChoice | None = None,
) -> EvaluationRun:
    """Evaluate the scenes or tables ``inputs`` into ``out_dir`` (and the Markdown report
    ``report_path``, made by ``command``). ``show`` receives the evaluation's and the
    sweep's text as soon as each is computed. ``extra_inputs`` (a cascade file) are
    refused as outputs like ``inputs``. ``planner``: replay the scenes with that planner's
    truth beside the engine. ``engine``: where the scenes run (default: ``workers``
    local processes). Scenes that fail are listed in ``OUT/failures.csv`` and left out;
    raises EvaluationError when every scene failed."""
    check_report_path(report_path, out_dir)  # before anything runs (issue 36)
    engine = engine or EngineChoice("local", workers)
    found = resolve_inputs(list(inputs), output_dir=out_dir, output_stems=EVALUATION_TABLES)
    check_tables_hindsight(bool(found.tables), hindsight)
    if sensitivity is not None and found.tables:
        raise EvaluationError(
            "--sensitivity replays the scenes with other settings; give .mcap scenes, not tables"
        )
    report_dir = None if report_path is None else report_path.with_suffix("")
    check_not_outputs(found, out_dir, _OUTPUT_NAMES)
    # One guard for every input (the files inside folders too) and every output, the
    # report included: a report given a scene's path replaced that scene (issue 31).
    guard = OutputGuard(
        inputs=[*inputs, *found.scenes, *found.tables, *extra_inputs],
        folders=(out_dir, report_dir), files=(report_path,),
    )  # fmt: skip
    hs = hindsight or HindsightSettings()
    with guard:  # checked and locked at once; every file appears together
        start = time.perf_counter()
        job = tables_job(
            TablesSettings(cascade=cascade, ego=ego, every=every, hindsight=hs, planner=planner)
        )
        report = run_jobs(
            job, scene_refs(found), out_dir, engine=engine.name, workers=engine.workers,
            ray_address=engine.address, progress=progress, desc="evaluate: scenes",
        )  # fmt: skip
        if report.failures and report.done:  # at once: the evaluation may yet fail
            show(report.describe())
        parts = collected_parts(report, cascade)  # checks the tables' cascade stages
        datasets = parts.datasets
        read_s = time.perf_counter() - start
        start = time.perf_counter()
        # One scene's rows at a time (issue 38): the driver never holds the corpus's rows.
        streamed = evaluate_parts(
            report.parts("agents"), StreamSettings.of(settings, hs), datasets=datasets,
            hindsight=hs, inputs=[str(p) for p in inputs], evaluation=settings,
        )  # fmt: skip
        summary = streamed.summary
        summary["settings"]["planner"] = planner
        summary["failed_scenes"] = [f.scene for f in report.failures]
        summary["time_s"] = {"replay / read": read_s, "evaluation": time.perf_counter() - start}
        show(format_evaluation(summary))
        run = EvaluationRun(summary, jobs=report)
        if sensitivity is not None:
            start = time.perf_counter()
            subset = sweep_subset(found.scenes, sensitivity.scenes)
            same = (
                sensitivity.scenes == 1
                and sensitivity.every in (None, every)
                and not report.failures
            )
            # The sweep streams every variant's parts (issue 38); it is given the
            # defaults' part files rather than replaying them.
            run.sweep = run_sweep(
                subset, defaults=report if same else None,
                datasets=datasets if same else None, cascade=cascade, hindsight=hs,
                settings=replace(settings, n_boot=sensitivity.bootstrap),
                workers=engine.workers or workers, progress=progress, ego=ego,
                every=sensitivity.every or every, engine=engine.name,
                ray_address=engine.address,
            )  # fmt: skip
            summary["sensitivity"] = {
                "scenes": len(subset), "every": str(sensitivity.every or every),
                "bootstrap": sensitivity.bootstrap, "time_s": run.sweep.time_s,
            }  # fmt: skip
            summary["time_s"]["sensitivity"] = time.perf_counter() - start
            run.files.update(write_sweep(run.sweep, out_dir, plots=plots))
            show(format_sweep(run.sweep))
        run.files.update(
            write_evaluation(
                summary, out_dir, roc=streamed.roc, positives=streamed.positives, plots=plots
            )
        )
        if report_path is not None:  # same guard: it may not replace an input or output
            pending = guard.pending()  # the plots above, not yet renamed into place
            pngs = {p: pending.get(p, p) for p in run.files.values() if p.suffix == ".png"}
            run.files.update(
                write_report(
                    report_path, summary, streamed.positives, out_dir=out_dir, sweep=run.sweep,
                    command=command, datasets=datasets, note=report_note, plots=pngs,
                )
            )  # fmt: skip
    return run
