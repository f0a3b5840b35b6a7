"""Calibrating the cascade's thresholds against the survival-analysis baseline.

Pure maths on arrays: the caller evaluates every stage's model and survival analysis on
all agents of many frames and passes the results flattened to agent-frames (one entry per
valid non-ego agent per frame). Every model is a function of the ego and one agent only,
so an agent's risk on a cascade sub-frame equals its risk on the whole frame: running the
stages on the flattened arrays reproduces the cascade exactly.

Choices the spec leaves open (documented here and in ``docs/cascade.md``):

- The false-negative budget of every stage is ``floor(max_fn_rate * B)`` agent-frames,
  ``B`` the number of baseline-important agent-frames in the whole calibration set (not
  those reaching the stage), so the budgets add up: the cascade as a whole drops at most
  ``S * max_fn_rate`` of the baseline.
- Thresholds sit a relative ``1e-9`` below the critical baseline agent's risk, so that
  last-bit differences between evaluating a model on all agents and on a sub-frame can
  never flip that agent (a threshold of 0 stays 0).
- When a stage may drop every baseline agent that reaches it (or none reaches it), its
  "highest threshold" is unbounded: the result is ``inf`` (the stage drops everything),
  reported as such rather than invented.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from risk.errors import RiskError

#: Relative safety margin below the critical risk (see the module docstring).
THRESHOLD_MARGIN = 1e-9


class CalibrationError(RiskError):
    """Calibration input that cannot give thresholds (empty, mismatched shapes, ...)."""


@dataclass(frozen=True)
class StageCalibration:
    """One calibrated stage and what it does on the calibration data."""

    model: str
    threshold: float
    agents_in: int  # agent-frames reaching the stage
    removed: int  # agent-frames the stage drops
    mean_removed_per_frame: float
    removed_share: float  # removed / agents_in (NaN when nothing reaches the stage)
    false_negatives: int  # baseline-important agent-frames this stage drops
    fn_share: float  # false_negatives / all baseline-important agent-frames


@dataclass(frozen=True)
class Calibration:
    """The result of :func:`calibrate_thresholds`."""

    stages: tuple[StageCalibration, ...]
    frames: int
    agent_frames: int
    baseline_agents: int
    max_fn_rate: float

    @property
    def thresholds(self) -> tuple[float, ...]:
        return tuple(s.threshold for s in self.stages)

    @property
    def total_fn_share(self) -> float:
        """Share of the baseline the whole cascade drops on the calibration data."""
        if self.baseline_agents == 0:
            return math.nan
        return sum(s.false_negatives for s in self.stages) / self.baseline_agents


def cascade_keep(stage_risks: np.ndarray, thresholds: Sequence[float]) -> np.ndarray:
    """Kept mask ``(S, A)`` of a cascade on flattened agent-frames.

    ``stage_risks``: ``(S, A)`` risk of each stage's model on every agent-frame;
    an agent-frame is kept after stage ``s`` when it was kept after ``s - 1`` and its
    stage-``s`` risk is ``>= thresholds[s]`` (NaN is never kept).
    """
    risks = np.nan_to_num(np.asarray(stage_risks, dtype=np.float64), nan=-np.inf)
    passes = risks >= np.asarray(thresholds, dtype=np.float64)[:, None]
    return np.logical_and.accumulate(passes, axis=0)


def highest_threshold(risks_of_important: np.ndarray, allowed_drops: int) -> float:
    """The highest threshold that drops at most ``allowed_drops`` of these risks.

    A threshold ``t`` drops every risk ``< t``; with the risks sorted ascending,
    ``t = r[allowed_drops]`` drops at most ``allowed_drops`` (fewer on ties) and any higher
    ``t`` drops more. ``inf`` when all may be dropped.
    """
    r = np.sort(np.asarray(risks_of_important, dtype=np.float64))
    if allowed_drops >= r.size:
        return math.inf
    critical = float(r[allowed_drops])
    return critical * (1.0 - THRESHOLD_MARGIN) if critical > 0 else critical


def calibrate_thresholds(
    stage_risks: np.ndarray,
    baseline: np.ndarray,
    frame_index: np.ndarray,
    *,
    models: Sequence[str],
    max_fn_rate: float = 0.0,
) -> Calibration:
    """Sequential calibration, as the cascade runs.

    Shapes: ``stage_risks (S, A)``, ``baseline (A,)`` bool (survival risk >= the baseline
    threshold), ``frame_index (A,)`` int (which frame an agent-frame belongs to; only the
    number of distinct frames is used, for per-frame means). Stage ``s`` gets the highest
    threshold that drops at most ``floor(max_fn_rate * B)`` baseline agent-frames among
    those stages ``0..s-1`` kept.
    """
    risks = np.asarray(stage_risks, dtype=np.float64)
    base = np.asarray(baseline, dtype=bool)
    frames = np.asarray(frame_index)
    if risks.ndim != 2 or risks.shape[0] != len(models):
        raise CalibrationError(f"stage risks must have shape ({len(models)}, A), got {risks.shape}")
    if base.shape != (risks.shape[1],) or frames.shape != base.shape:
        raise CalibrationError("baseline and frame_index must have one entry per agent-frame")
    if not 0.0 <= max_fn_rate <= 1.0:
        raise CalibrationError(f"max_fn_rate must be in [0, 1], got {max_fn_rate}")
    n_frames = int(np.unique(frames).size)
    if n_frames == 0:
        raise CalibrationError("no agent-frames to calibrate on (scenes without other agents)")
    n_base = int(base.sum())
    if n_base == 0:
        raise CalibrationError(
            "no baseline-important agent in the calibration data: nothing to calibrate against"
        )
    # The tiny tolerance keeps e.g. 0.29 * 100 from flooring to 28.
    allowed = math.floor(max_fn_rate * n_base + 1e-9)

    stages = []
    reaching = np.ones(base.shape, dtype=bool)
    for s, model in enumerate(models):
        r = np.nan_to_num(risks[s], nan=-np.inf)
        threshold = highest_threshold(r[reaching & base], allowed)
        keep = reaching & (r >= threshold)
        dropped = reaching & ~keep
        n_in = int(reaching.sum())
        stages.append(
            StageCalibration(
                model=model,
                threshold=threshold,
                agents_in=n_in,
                removed=int(dropped.sum()),
                mean_removed_per_frame=float(dropped.sum()) / n_frames,
                removed_share=float(dropped.sum()) / n_in if n_in else math.nan,
                false_negatives=int((dropped & base).sum()),
                fn_share=float((dropped & base).sum()) / n_base,
            )
        )
        reaching = keep
    return Calibration(
        stages=tuple(stages),
        frames=n_frames,
        agent_frames=int(base.size),
        baseline_agents=n_base,
        max_fn_rate=float(max_fn_rate),
    )


def tier_thresholds_for_counts(
    survival: np.ndarray, frame_index: np.ndarray, target_counts: Sequence[int]
) -> tuple[float, ...]:
    """Survival-risk minimums that give each tier ``target_counts[k]`` agents in the median
    frame.

    ``survival (K,)`` and ``frame_index (K,)`` describe the cascade's survivors. For a
    target ``c`` each frame proposes its ``c``-th largest survival risk (its smallest when
    it has fewer survivors: then every survivor qualifies); the threshold is the median
    of the proposals over the frames that have survivors. Tiers are nested, so a target
    count is also capped by the tier before it at run time.
    """
    risk = np.asarray(survival, dtype=np.float64)
    frames = np.asarray(frame_index)
    if risk.shape != frames.shape or risk.ndim != 1:
        raise CalibrationError("survival and frame_index must be (K,) arrays of equal length")
    if risk.size == 0:
        raise CalibrationError("no survivors to choose tier thresholds from")
    order = np.lexsort((-risk, frames))  # by frame, riskiest first within a frame
    f_sorted, r_sorted = frames[order], risk[order]
    starts = np.flatnonzero(np.r_[True, f_sorted[1:] != f_sorted[:-1]])
    ends = np.r_[starts[1:], f_sorted.size]  # exclusive
    result = []
    for c in target_counts:
        if c < 1:
            raise CalibrationError(f"tier target counts must be >= 1, got {c}")
        pick = np.minimum(starts + c - 1, ends - 1)
        result.append(float(np.median(r_sorted[pick])))
    return tuple(result)
