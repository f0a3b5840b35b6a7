"""Running the paper's experiment: situations drawn, replayed in worker processes,
half-calibrated, and their statistics computed (no files written; :mod:`.report` writes).

See :mod:`replay.analysis.experiment` for what the experiment measures and the choices made.
"""

from __future__ import annotations

import math
import os
import pathlib
import re
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import polars as pl

from converters.synthetic import SyntheticSettings, generate_situation
from replay.analysis.scene_calibration import (
    DEFAULT_STAGES,
    DEFAULT_TIER_COUNTS,
    DEFAULT_TIERS,
    CalibrationData,
    calibrated_config,
)
from replay.analysis.stats import (
    DEFAULT_ERRORS_MODEL,
    DatasetStats,
    cascade_frame_row,
    cascade_summary,
    compute_stats,
    frames_table,
)
from replay.core.pool import LocalEngine, chunks, default_workers, parallel_map
from replay.core.worker import replay_scene
from replay.errors import ReplayError
from risk import MODELS, evaluate
from risk.cascade import CascadeConfig, run_cascade
from risk.errors import RiskError

PAPER_RANGES = {"agents": (30, 100), "gaps_m": (5.0, 100.0), "speeds_mps": (0.0, 25.0)}


# ---------------------------------------------------------------------- one chunk
@dataclass(frozen=True, eq=False)
class ChunkResult:
    """The tables of some situations and the time each part took (s, summed)."""

    agents: pl.DataFrame
    frames: pl.DataFrame
    extra_frames: dict[str, pl.DataFrame]  # cascade name -> frames table
    generate_s: float
    engine_s: float
    extra_s: float
    model_time_s: dict[str, list[float]] = field(default_factory=dict)  # model -> per frame


@dataclass(frozen=True)
class SituationTask:
    """What a worker needs to replay some situations (picklable)."""

    indices: tuple[int, ...]
    seed: int
    cascade: CascadeConfig
    extra_cascades: tuple[tuple[str, CascadeConfig], ...] = ()
    settings: SyntheticSettings | None = None  # None: the defaults
    time_models: bool = True  # also time each model alone on every frame


def situation_seed(seed: int, index: int) -> int:
    """The generator seed of situation ``index`` of an experiment with ``seed``."""
    ss = np.random.SeedSequence(seed, spawn_key=(index,))
    return int(ss.generate_state(1, dtype=np.uint64)[0])


def situation_name(index: int) -> str:
    return f"situation_{index:05d}"


def run_situations(task: SituationTask) -> ChunkResult:
    """Generate and replay the situations of one task (runs in a worker process)."""
    agents, frames = [], []
    model_time_s: dict[str, list[float]] = {m: [] for m in MODELS} if task.time_models else {}
    extra_rows: dict[str, list[dict[str, Any]]] = {name: [] for name, _ in task.extra_cascades}
    gen_s = engine_s = extra_s = 0.0
    for i in task.indices:
        start = time.perf_counter()
        scene = generate_situation(task.settings, seed=situation_seed(task.seed, i))
        gen_s += time.perf_counter() - start
        start = time.perf_counter()
        tables = replay_scene(scene, name=situation_name(i), cascade=task.cascade)
        engine_s += time.perf_counter() - start
        agents.append(tables.agents)
        frames.append(tables.frames)
        start = time.perf_counter()
        for name, config in task.extra_cascades:
            tiers = [t.name for t in config.tiers]
            for k, frame in enumerate(scene.frames):
                row = cascade_frame_row(run_cascade(frame, config), tiers)
                extra_rows[name].append(
                    {"scene": situation_name(i), "frame": k, "t_s": frame.t, **row}
                )
        extra_s += time.perf_counter() - start
        for frame in scene.frames:
            for name in model_time_s:
                # Alone: its own prediction included, as a filter stage would run it.
                start = time.perf_counter()
                evaluate(frame, models=[name])
                model_time_s[name].append(time.perf_counter() - start)
    extra = {
        name: frames_table(
            extra_rows[name], config.stage_names, [t.name for t in config.tiers], timed=True
        )
        for name, config in task.extra_cascades
    }
    return ChunkResult(
        pl.concat(agents), pl.concat(frames), extra, gen_s, engine_s, extra_s, model_time_s
    )


def merge(results: Iterable[ChunkResult]) -> ChunkResult:
    results = list(results)
    names = results[0].extra_frames.keys() if results else ()
    return ChunkResult(
        agents=pl.concat([r.agents for r in results]),
        frames=pl.concat([r.frames for r in results]),
        extra_frames={n: pl.concat([r.extra_frames[n] for r in results]) for n in names},
        generate_s=sum(r.generate_s for r in results),
        engine_s=sum(r.engine_s for r in results),
        extra_s=sum(r.extra_s for r in results),
        model_time_s={
            m: [t for r in results for t in r.model_time_s.get(m, [])]
            for m in (results[0].model_time_s if results else {})
        },
    )


# ---------------------------------------------------------------------- calibration
@dataclass(frozen=True, eq=False)
class HalfCalibration:
    """A cascade calibrated on the first half and its results on the second half."""

    config: CascadeConfig | None
    train_situations: int
    test_situations: int
    train_baseline: int  # baseline-important agent-frames of the first half
    reason: str = ""  # why there is no config (when config is None)


def calibrate_on(agents: pl.DataFrame) -> tuple[CascadeConfig | None, str]:
    """The cascade calibrated on an agents table with ``replay calibrate``'s defaults
    (stages path distance, trajectory distance, 2D Gaussians; no false negative allowed;
    the paper's tiers with 5 and 2 agents in the median frame); ``(None, reason)`` when
    the data cannot give thresholds."""
    if agents.height == 0:
        return None, "no agent-frames in the first half"
    frame_index = (
        agents.select(pl.struct("scene", "frame").rank("dense")).to_series().to_numpy() - 1
    )
    data = CalibrationData(
        stage_risks=np.stack([agents[f"risk_{m}"].to_numpy() for m in DEFAULT_STAGES]),
        survival=agents["risk_survival"].to_numpy(),
        frame_index=frame_index.astype(np.int64),
        frames=int(frame_index.max()) + 1,
        scenes=int(agents["scene"].n_unique()),
        skipped_frames=0,
        sources=("synthetic four-way intersection",),
    )
    try:
        config, _ = calibrated_config(
            data,
            DEFAULT_STAGES,
            max_fn_rate=0.0,
            tiers=DEFAULT_TIERS,
            tier_counts=DEFAULT_TIER_COUNTS,
        )
    except RiskError as exc:
        return None, str(exc)
    return config, ""


# ---------------------------------------------------------------------- the experiment
@dataclass(frozen=True)
class ExperimentSettings:
    """How to run the experiment."""

    situations: int = 500
    seed: int = 0
    workers: int = field(default_factory=default_workers)
    errors_model: str = DEFAULT_ERRORS_MODEL
    calibrate_half: bool = True
    synthetic: SyntheticSettings | None = None  # None: the paper's ranges


@dataclass(frozen=True, eq=False)
class ExperimentResult:
    settings: ExperimentSettings
    cascade: CascadeConfig
    stats: DatasetStats
    tables: ChunkResult
    half: HalfCalibration | None
    cascade_test_half: dict[str, dict[str, Any]]  # "default"/"calibrated" -> summary
    times_s: dict[str, float]  # stage -> wall time
    files: dict[str, pathlib.Path] = field(default_factory=dict)
    load_before: float = math.nan  # 1-minute load average when the run started


def run_experiment(
    settings: ExperimentSettings, *, progress: bool = True, cascade: CascadeConfig | None = None
) -> ExperimentResult:
    """Generate, replay and analyse the situations (no files written)."""
    if settings.situations < 2:
        raise ReplayError(f"the experiment needs at least 2 situations, got {settings.situations}")
    cascade = cascade or CascadeConfig.named("survival")  # (the paper's cascade)
    n, workers = settings.situations, max(1, settings.workers)
    load_before = load_average()
    half_n = n // 2 if settings.calibrate_half else n
    times: dict[str, float] = {}
    pool = LocalEngine(workers) if workers > 1 else None
    try:
        start = time.perf_counter()
        first = _replay(range(half_n), settings, cascade, (), pool, progress, "situations 1/2")
        times["replay (first half)"] = time.perf_counter() - start
        half = None
        extra: tuple[tuple[str, CascadeConfig], ...] = ()
        if settings.calibrate_half:
            start = time.perf_counter()
            config, reason = calibrate_on(first.agents)
            half = HalfCalibration(
                config, half_n, n - half_n, int(first.agents["baseline"].sum()), reason
            )
            extra = (("calibrated", config),) if config is not None else ()
            times["calibration"] = time.perf_counter() - start
        start = time.perf_counter()
        second = (
            _replay(range(half_n, n), settings, cascade, extra, pool, progress, "situations 2/2")
            if half_n < n
            else None
        )
        times["replay (second half)"] = time.perf_counter() - start
    finally:
        if pool is not None:
            pool.close(cancel=True)
    tables = merge([first, second] if second is not None else [first])
    start = time.perf_counter()
    stats = compute_stats(
        tables.agents,
        tables.frames,
        errors_model=settings.errors_model,
        stage_names=cascade.stage_names,
        tier_names=[t.name for t in cascade.tiers],
        baseline_threshold=cascade.baseline_threshold,
        inputs=[f"{n} synthetic situations, seed {settings.seed}"],
    )
    test: dict[str, dict[str, Any]] = {}
    if second is not None and second.frames.height:
        tiers = [t.name for t in cascade.tiers]
        test["default"] = cascade_summary(second.frames, cascade.stage_names, tiers)
        if half is not None and half.config is not None:
            cfg = half.config
            test["calibrated"] = cascade_summary(
                second.extra_frames["calibrated"], cfg.stage_names, [t.name for t in cfg.tiers]
            )
    times["statistics"] = time.perf_counter() - start
    times["generate (sum over workers)"] = tables.generate_s
    times["models + cascade (sum over workers)"] = tables.engine_s
    if tables.model_time_s:
        times["each model alone for timing (sum over workers)"] = sum(
            sum(t) for t in tables.model_time_s.values()
        )
    return ExperimentResult(
        settings, cascade, stats, tables, half, test, times, load_before=load_before
    )


def load_average() -> float:
    """The 1-minute load average (NaN where the OS has none)."""
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):
        return math.nan


def _replay(
    indices: range,
    settings: ExperimentSettings,
    cascade: CascadeConfig,
    extra: tuple[tuple[str, CascadeConfig], ...],
    pool: LocalEngine | None,
    progress: bool,
    desc: str,
) -> ChunkResult:
    parts = chunks(list(indices), settings.workers)
    tasks = [
        SituationTask(tuple(p), settings.seed, cascade, extra, settings.synthetic) for p in parts
    ]
    results = parallel_map(
        run_situations,
        tasks,
        workers=settings.workers,
        progress=progress,
        desc=desc,
        weights=[len(p) for p in parts],
        engine=pool,
    )
    return merge(results)


def calibration_seeds(config: CascadeConfig) -> tuple[int, int] | None:
    """The seed range named in a cascade's provenance (``Seeds: a-b``), if any."""
    m = re.search(r"Seeds:\s*(\d+)\s*-\s*(\d+)", config.provenance)
    return (int(m.group(1)), int(m.group(2))) if m else None


def lane_width(result: ExperimentResult) -> float:
    """The lane width (m) of the synthetic map the situations were drawn on."""
    return (result.settings.synthetic or SyntheticSettings()).intersection.lane_width_m


def model_times_ms(result: ExperimentResult, *, stat: str = "median") -> dict[str, float]:
    """Per-situation time (ms) of each model evaluated alone: median (default; robust to
    the other processes sharing the cores) or mean."""
    reduce = np.median if stat == "median" else np.mean
    return {m: 1e3 * float(reduce(t)) for m, t in result.tables.model_time_s.items() if t}
