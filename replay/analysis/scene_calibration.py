"""Calibrating the cascade on scenes: the data, the thresholds, the provenance record.

:func:`collect` evaluates the stage models and survival analysis on every agent of every
frame of some scenes; :func:`calibrated_config` turns that into a cascade with the maths
of :mod:`risk.calibration`; :func:`provenance` records how (kept in the TOML).
``replay experiment`` (its half-calibration) uses them on the whole data.
``replay calibrate`` runs :func:`streamed_calibration` on the scenes' parts
(:func:`risk_parts`) instead: the same thresholds, tiers and counts, one scene read at a
time, without holding every agent-frame (issue 38); the whole-data path is its tests'
oracle.
"""

from __future__ import annotations

import contextlib
import datetime
import importlib.metadata
import itertools
import pathlib
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from converters.scene.reader import open_scene
from replay.errors import ReplayError
from replay.jobs import Inputs, Job, JobReport, SceneOutput, SceneRef, fingerprint, scene_refs
from replay.jobs.place import JobPlace, every_done, run_job
from risk import MODELS, PredictionSettings, evaluate
from risk.calibration import (
    Calibration,
    calibrate_thresholds,
    calibration_from_counts,
    cascade_keep,
    fn_budget,
    median_proposals,
    sequential_thresholds,
    stage_counts,
    tier_proposals,
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


@dataclass(frozen=True)
class RiskSettings:
    """The survival calibration's job: the stage models (the survival model is added)."""

    models: tuple[str, ...]


#: The table of the survival calibration's job (``OUT/parts/risks/``).
RISKS = "risks"


def risks_scene(ref: SceneRef, settings: RiskSettings) -> SceneOutput:
    """One scene's agent-frames: every stage model's risk (``stage_<k>``) and survival
    analysis's (``survival``) for every valid non-ego agent of every frame with its ego,
    and the frame's number among those (``frame``); the counts and the metadata's source
    and seed in the partial."""
    reader = open_scene(ref.path)
    meta = dict(reader.metadata)
    names = [*settings.models, SURVIVAL_MODEL]
    risks: list[list[np.ndarray]] = [[] for _ in names]
    frame_index: list[np.ndarray] = []
    frames = skipped = 0
    for entry in reader.entries():
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
    seed = meta.get("seed", "")
    partial = {
        "frames": frames,
        "skipped_frames": skipped,
        "source": meta.get("dataset") or meta.get("source") or meta.get("converter", "?"),
        "seed": int(seed) if seed.lstrip("-").isdigit() else None,
    }
    if not frames:
        return SceneOutput({}, partial)
    columns = {"frame": np.concatenate(frame_index)}
    for k in range(len(names)):
        label = "survival" if k == len(names) - 1 else f"stage_{k}"
        columns[label] = np.concatenate(risks[k])
    return SceneOutput({RISKS: pl.DataFrame(columns)}, partial)


@dataclass(frozen=True)
class CalibrationCorpus:
    """What the provenance and the report say of the scenes (no agent-frame):
    :class:`CalibrationData` without its arrays."""

    frames: int
    scenes: int
    skipped_frames: int
    sources: tuple[str, ...]
    seeds: tuple[int, ...] = ()


@dataclass(frozen=True)
class RiskPart:
    """One complete scene of the risks job: its table (None: no frame with its ego) and
    its partial summary (frames, skipped frames, source, seed)."""

    key: str
    table: pathlib.Path | None
    partial: Mapping[str, Any]

    def read(self, stages: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(stage_risks (S, A), survival (A,), frame (A,))`` of the scene (empty without
        a table); ``frame`` numbers the scene's frames from 0."""
        if self.table is None:
            return np.empty((stages, 0)), np.empty(0), np.empty(0, dtype=np.int64)
        df = pl.read_parquet(self.table)
        risks = (
            np.stack([df[f"stage_{k}"].to_numpy() for k in range(stages)])
            if stages
            else np.empty((0, df.height))
        )
        return risks, df["survival"].to_numpy(), df["frame"].to_numpy()


def risk_parts(
    paths: Sequence[pathlib.Path],
    models: Sequence[str],
    place: JobPlace,
    *,
    reports: list[JobReport] | None = None,
) -> list[RiskPart]:
    """Evaluate ``models`` and survival analysis on every agent of every frame: one job
    per scene (:func:`risks_scene`) on the engine of ``place``; every complete scene's
    part in scene-key order (nothing read). Its parts are a cache: a rerun into the same
    folder with the same models reads the complete scenes. ``reports`` receives the
    job's report (its failures: scenes left out)."""
    settings = RiskSettings(tuple(models))
    job = Job("calibrate-risks", risks_scene, settings,
              fingerprint("calibrate-risks", {"settings": repr(settings)}))  # fmt: skip
    refs = scene_refs(Inputs(tuple(pathlib.Path(p) for p in paths), ()))
    report = run_job(job, refs, place, "calibrate")
    if reports is not None:
        reports.append(report)
    every_done(report)
    return [
        RiskPart(d.ref.key, pathlib.Path(d.tables[RISKS]) if RISKS in d.tables else None, d.partial)
        for d in report.done
    ]


def corpus_of(parts: Sequence[RiskPart]) -> CalibrationCorpus:
    """The scenes' counts, sources and seeds from their partials; fails (one line) when
    no frame has its ego."""
    partials = [part.partial for part in parts]
    frames = sum(int(p["frames"]) for p in partials)
    if frames == 0:
        raise ReplayError("no usable frame in the given scenes (every frame lacks its ego)")
    return CalibrationCorpus(
        frames=frames,
        scenes=len(parts),
        skipped_frames=sum(int(p["skipped_frames"]) for p in partials),
        sources=tuple(sorted({str(p["source"]) for p in partials})),
        seeds=tuple(sorted({int(p["seed"]) for p in partials if p["seed"] is not None})),
    )


def collect(
    paths: Sequence[pathlib.Path],
    models: Sequence[str],
    *,
    progress: bool = True,
    place: JobPlace | None = None,
    reports: list[JobReport] | None = None,
) -> CalibrationData:
    """Every agent-frame of :func:`risk_parts` (default: this process, into a temporary
    folder), read back in scene-key order (frames numbered across the scenes in that
    order): the whole data, for small runs and tests (``replay calibrate`` streams the
    parts instead: :func:`streamed_calibration`)."""
    with contextlib.ExitStack() as stack:
        if place is None:
            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="replay-calibrate-"))
            place = JobPlace(pathlib.Path(tmp), "local", 1, None, progress)
        return gather(risk_parts(paths, models, place, reports=reports), models)


def gather(parts: Sequence[RiskPart], models: Sequence[str]) -> CalibrationData:
    """The parts' agent-frames side by side, frames numbered across the scenes in the
    parts' order."""
    corpus = corpus_of(parts)
    stage_risks: list[np.ndarray] = []
    survival: list[np.ndarray] = []
    frame_index: list[np.ndarray] = []
    frames = 0
    for part in parts:
        risks, surv, frame = part.read(len(models))
        stage_risks.append(risks)
        survival.append(surv)
        frame_index.append(frame + frames)
        frames += int(part.partial["frames"])
    return CalibrationData(
        stage_risks=np.concatenate(stage_risks, axis=1) if models else np.empty((0, 0)),
        survival=np.concatenate(survival),
        frame_index=np.concatenate(frame_index),
        frames=corpus.frames,
        scenes=corpus.scenes,
        skipped_frames=corpus.skipped_frames,
        sources=corpus.sources,
        seeds=corpus.seeds,
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
    return _tiered_config(models, cal.thresholds, tiers, minimums, baseline_threshold), cal


def _tiered_config(
    models: Sequence[str],
    thresholds: Sequence[float],
    tiers: Sequence[Tier],
    minimums: Sequence[float],
    baseline_threshold: float,
) -> CascadeConfig:
    new_tiers = [Tier(tiers[0].name, baseline_threshold, tiers[0].max_agents)]
    for tier, minimum in zip(tiers[1:], minimums, strict=True):
        # Never below the tier before: tiers are nested.
        minimum = max(minimum, new_tiers[-1].min_survival_risk)
        new_tiers.append(Tier(tier.name, minimum, tier.max_agents))
    return CascadeConfig(
        stages=tuple(Stage(m, t) for m, t in zip(models, thresholds, strict=True)),
        tiers=tuple(new_tiers),
        baseline_threshold=baseline_threshold,
    )


def tier_means(config: CascadeConfig, data: CalibrationData) -> list[float]:
    """Mean agents per frame in each tier when ``config`` runs on the calibration data."""
    totals = _tier_totals(data.stage_risks, data.survival, data.frame_index, config)
    return [float(t) / data.frames for t in totals]


def _tier_totals(
    stage_risks: np.ndarray, survival: np.ndarray, frame_index: np.ndarray, config: CascadeConfig
) -> np.ndarray:
    """``(T,)`` int64: agent-frames in tier ``k`` or above when ``config`` runs on these
    agent-frames (additive over scenes)."""
    survivors = cascade_keep(stage_risks, [s.threshold for s in config.stages])[-1]
    tier = np.full(survival.size, -1, dtype=np.int64)
    # Tiers are assigned per frame; agent-frames are stored frame after frame.
    idx = np.flatnonzero(survivors)
    frames = frame_index[idx]
    bounds = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1], True])
    for a, b in itertools.pairwise(bounds):
        tier[idx[a:b]] = assign_tiers(survival[idx[a:b]], config.tiers)
    return np.array([(tier >= k).sum() for k in range(len(config.tiers))], dtype=np.int64)


def streamed_calibration(
    parts: Sequence[RiskPart],
    models: Sequence[str],
    *,
    max_fn_rate: float,
    tiers: Sequence[Tier],
    tier_counts: Sequence[int],
    baseline_threshold: float = 1e-25,
) -> tuple[CascadeConfig, Calibration, CalibrationCorpus, list[float]]:
    """:func:`calibrated_config` and :func:`tier_means` over the scenes' parts, one scene
    at a time, in any order of the parts: the same config, calibration and means
    without holding every agent-frame (issue 38). Three passes: the baseline-important
    agent-frames' stage risks (the only ones that move a threshold), then the stage
    counts and each frame's tier proposals for those thresholds, then the tier counts.
    What it holds grows with the baseline-important agent-frames (S floats each) and
    the frames (one proposal per tier count each), not with all agent-frames."""
    corpus = corpus_of(parts)
    n_stages = len(models)
    baseline_risks: list[np.ndarray] = []
    n_frames = n_rows = n_base = 0
    for part in parts:  # pass 1: what decides the thresholds
        risks, survival, frame = part.read(n_stages)
        base = survival >= baseline_threshold
        baseline_risks.append(risks[:, base])
        n_frames += int(np.unique(frame).size)
        n_rows += int(base.size)
        n_base += int(base.sum())
    allowed = fn_budget(max_fn_rate, n_frames, n_base)
    thresholds = sequential_thresholds(np.concatenate(baseline_risks, axis=1), allowed)
    del baseline_risks
    counts = np.zeros((3, n_stages), dtype=np.int64)
    proposals: list[np.ndarray] = []
    for part in parts:  # pass 2: what those thresholds do, each frame's tier proposals
        risks, survival, frame = part.read(n_stages)
        counts += stage_counts(risks, survival >= baseline_threshold, thresholds)
        survivors = cascade_keep(risks, thresholds)[-1]
        proposals.append(tier_proposals(survival[survivors], frame[survivors], tier_counts))
    cal = calibration_from_counts(
        models, thresholds, counts, frames=n_frames, agent_frames=n_rows,
        baseline_agents=n_base, max_fn_rate=max_fn_rate,
    )  # fmt: skip
    minimums = median_proposals(np.concatenate(proposals))
    config = _tiered_config(models, thresholds, tiers, minimums, baseline_threshold)
    totals = np.zeros(len(config.tiers), dtype=np.int64)
    for part in parts:  # pass 3: the tiers' counts
        totals += _tier_totals(*part.read(n_stages), config)
    return config, cal, corpus, [float(t) / corpus.frames for t in totals]


def provenance(
    config: CascadeConfig,
    cal: Calibration,
    data: CalibrationData | CalibrationCorpus,
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
