"""Compute, write and plot the statistics of collected tables: the shared tail of
``replay stats``, ``replay batch`` and (for its tables) ``replay experiment``."""

from __future__ import annotations

import pathlib
import time
from collections.abc import Sequence
from dataclasses import dataclass

import polars as pl

from replay.analysis.stats.compute import DatasetStats, compute_stats
from replay.analysis.stats.files import write_stats
from replay.analysis.stats.plots import plot_all
from risk.cascade import CascadeConfig


@dataclass(frozen=True, eq=False)
class StatsRun:
    stats: DatasetStats
    files: dict[str, pathlib.Path]


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
    start = time.perf_counter()
    files = write_stats(stats, out_dir)
    times["write tables"] = time.perf_counter() - start
    if plots:
        start = time.perf_counter()
        files.update(plot_all(stats, out_dir))
        times["plots"] = time.perf_counter() - start
    return StatsRun(stats, files)
