"""Calibrating the cascade on scenes: the data, the thresholds, the provenance record.

:func:`collect` evaluates the stage models and survival analysis on every agent of every
frame of some scenes; :func:`calibrated_config` turns that into a cascade with the maths
of :mod:`risk.calibration`; :func:`provenance` records how (kept in the TOML).
``replay calibrate`` and ``replay experiment`` (its half-calibration) both use them.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import itertools
import pathlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from converters.scene.reader import open_scene
from replay.errors import ReplayError
from risk import MODELS, PredictionSettings, evaluate
from risk.calibration import (
    Calibration,
    calibrate_thresholds,
    cascade_keep,
    tier_thresholds_for_counts,
)
from risk.cascade import SURVIVAL_MODEL, CascadeConfig, Stage, Tier, assign_tiers

DEFAULT_STAGES = ("path_distance", "trajectory_distance", "gaussian")
#: The paper's tiers (Sec. VI): behavior gets every baseline-important survivor,
#: interactive 3-8 agents, cooperative 1-2; caps at the upper ends.
DEFAULT_TIERS = (
    Tier("behavior", 1e-25),
    Tier("interactive", 0.0, max_agents=8),
    Tier("cooperative", 0.0, max_agents=2),
)
DEFAULT_TIER_COUNTS = (5, 2)


@dataclass(frozen=True)
class CalibrationData:
    """Flattened agent-frames of many scenes (valid non-ego agents only).

    ``stage_risks (S, A)``, ``survival (A,)``, ``frame_index (A,)`` (global frame number).
    """

    stage_risks: np.ndarray
    survival: np.ndarray
    frame_index: np.ndarray
    frames: int
    scenes: int
    skipped_frames: int
    sources: tuple[str, ...]  # distinct metadata "source"/"dataset" values
    seeds: tuple[int, ...] = ()  # metadata "seed" of synthetic scenes


def collect(
    paths: Sequence[pathlib.Path], models: Sequence[str], *, progress: bool = True
) -> CalibrationData:
    """Evaluate ``models`` and survival analysis on every agent of every frame."""
    readers = [open_scene(p) for p in paths]
    names = [*models, SURVIVAL_MODEL]
    risks: list[list[np.ndarray]] = [[] for _ in names]
    frame_index: list[np.ndarray] = []
    frames = skipped = 0
    sources: set[str] = set()
    seeds: set[int] = set()
    total = sum(r.n_frames for r in readers)
    with tqdm(total=total, disable=None if progress else True, file=sys.stderr, unit="frame",
              desc="calibrate", leave=False) as bar:  # fmt: skip
        for reader in readers:
            meta = dict(reader.metadata)
            sources.add(meta.get("dataset") or meta.get("source") or meta.get("converter", "?"))
            if meta.get("seed", "").lstrip("-").isdigit():
                seeds.add(int(meta["seed"]))
            for entry in reader.entries():
                bar.update()
                if entry.frame is None:
                    skipped += 1
                    continue
                frame = entry.frame
                values = evaluate(frame, models=names)
                others = frame.others
                for k, name in enumerate(names):
                    risks[k].append(np.asarray(values[name], dtype=np.float64)[others])
                frame_index.append(np.full(int(others.sum()), frames, dtype=np.int64))
                frames += 1
    if frames == 0:
        raise ReplayError("no usable frame in the given scenes (every frame lacks its ego)")
    stacked = [np.concatenate(r) for r in risks]
    return CalibrationData(
        stage_risks=np.stack(stacked[:-1]) if models else np.empty((0, 0)),
        survival=stacked[-1],
        frame_index=np.concatenate(frame_index),
        frames=frames,
        scenes=len(paths),
        skipped_frames=skipped,
        sources=tuple(sorted(sources)),
        seeds=tuple(sorted(seeds)),
    )


def calibrated_config(
    data: CalibrationData,
    models: Sequence[str],
    *,
    max_fn_rate: float,
    tiers: Sequence[Tier],
    tier_counts: Sequence[int],
    baseline_threshold: float = 1e-25,
) -> tuple[CascadeConfig, Calibration]:
    """Stage thresholds (sequential, FN budget) and tier minimums (target counts).

    The first tier's minimum is the baseline threshold (every baseline-important survivor
    reaches it); tier ``k >= 1`` gets the survival risk that gives ``tier_counts[k - 1]``
    agents in the median frame (:func:`risk.calibration.tier_thresholds_for_counts`).
    """
    baseline = data.survival >= baseline_threshold
    cal = calibrate_thresholds(
        data.stage_risks, baseline, data.frame_index, models=models, max_fn_rate=max_fn_rate
    )
    survivors = cascade_keep(data.stage_risks, cal.thresholds)[-1]
    minimums = tier_thresholds_for_counts(
        data.survival[survivors], data.frame_index[survivors], tier_counts
    )
    new_tiers = [Tier(tiers[0].name, baseline_threshold, tiers[0].max_agents)]
    for tier, minimum in zip(tiers[1:], minimums, strict=True):
        # Never below the tier before: tiers are nested.
        minimum = max(minimum, new_tiers[-1].min_survival_risk)
        new_tiers.append(Tier(tier.name, minimum, tier.max_agents))
    config = CascadeConfig(
        stages=tuple(Stage(m, t) for m, t in zip(models, cal.thresholds, strict=True)),
        tiers=tuple(new_tiers),
        baseline_threshold=baseline_threshold,
    )
    return config, cal


def tier_means(config: CascadeConfig, data: CalibrationData) -> list[float]:
    """Mean agents per frame in each tier when ``config`` runs on the calibration data."""
    survivors = cascade_keep(data.stage_risks, [s.threshold for s in config.stages])[-1]
    tier = np.full(data.survival.size, -1, dtype=np.int64)
    # Tiers are assigned per frame; agent-frames are stored frame after frame.
    idx = np.flatnonzero(survivors)
    frames = data.frame_index[idx]
    bounds = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1], True])
    for a, b in itertools.pairwise(bounds):
        tier[idx[a:b]] = assign_tiers(data.survival[idx[a:b]], config.tiers)
    return [float((tier >= k).sum()) / data.frames for k in range(len(config.tiers))]


def provenance(
    config: CascadeConfig,
    cal: Calibration,
    data: CalibrationData,
    tier_mean: Sequence[float],
    command: str,
    tier_counts: Sequence[int],
    *,
    note: str = "",
) -> str:
    """The human-readable record of how the thresholds were made (kept in the TOML)."""
    try:
        version = importlib.metadata.version("riskreplay")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    today = datetime.datetime.now(datetime.UTC).date().isoformat()
    lines = [
        f"Made by: {command}",
        f"Date: {today}, riskreplay {version}",
        *([f"Note: {note.strip()}"] if note.strip() else []),
        f"Data: {data.scenes} scenes ({', '.join(data.sources)}), {data.frames} frames"
        f" ({data.skipped_frames} skipped: ego missing), {cal.agent_frames} agent-frames,"
        f" {cal.baseline_agents} baseline-important (survival R_S >= {config.baseline_threshold:g})",
        *([f"Seeds: {seed_ranges(data.seeds)}"] if data.seeds else []),
        f"Model parameters: {model_parameters()}",
        f"Max FN rate per stage: {cal.max_fn_rate:g} (of all baseline-important agent-frames);"
        f" FN share of the whole cascade on this data: {cal.total_fn_share:.4g}",
        "Stages (threshold: agents reaching it -> removed per frame, share of its input removed):",
    ]
    for s in cal.stages:
        lines.append(
            f"  {s.model}: {s.threshold:.6g}: {s.agents_in / data.frames:.1f} -> "
            f"{s.mean_removed_per_frame:.1f} removed ({100 * s.removed_share:.1f} %),"
            f" FN {s.false_negatives}"
        )
    lines.append(
        "Tiers: the first gets every baseline-important survivor (min = baseline threshold);"
        f" the others the survival risk giving {', '.join(map(str, tier_counts))} agents in"
        " the median frame (median over frames of the k-th largest survivor risk), capped"
        " at max_agents. Mean agents per frame on this data: "
        + ", ".join(f"{t.name} {m:.2f}" for t, m in zip(config.tiers, tier_mean, strict=True))
    )
    return "\n".join(lines) + "\n"


def seed_ranges(values: Sequence[int]) -> str:
    """``1, 2, 3, 7`` -> ``1-3, 7``."""
    runs: list[list[int]] = []
    for v in sorted(values):
        if runs and v == runs[-1][1] + 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def model_parameters() -> str:
    """The settings the baseline depends on (prediction horizon and step, survival)."""
    pred = PredictionSettings()
    survival = MODELS[SURVIVAL_MODEL].params_type()
    return f"defaults: prediction horizon {pred.horizon_s:g} s, step {pred.dt_s:g} s; {survival!r}"
