"""Calibrating the cascade's thresholds against the survival-analysis baseline.

Pure maths on arrays: the caller evaluates every stage's model and survival analysis on
all agents of many frames and passes the results flattened to agent-frames (one entry per
valid non-ego agent per frame). Every model is a function of the ego and one agent only,
so an agent's risk on a cascade sub-frame equals its risk on the whole frame: running the
stages on the flattened arrays reproduces the cascade exactly.

Each calibration also comes in parts, for a caller that reads a corpus one scene at a
time and never holds all of its agent-frames (issue 38): the thresholds from what alone
moves them (the baseline-important agent-frames' risks; each unit's least score among its
important agents), the rest from counts that add up over scenes. The whole-array
functions are built from those parts, so both give the same numbers.

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

import dataclasses
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

    The same in parts (per scene, without holding every agent-frame): :func:`fn_budget`,
    :func:`sequential_thresholds` on the baseline-important agent-frames only, then
    :func:`stage_counts` summed over the parts and :func:`calibration_from_counts`.
    """
    risks = np.asarray(stage_risks, dtype=np.float64)
    base = np.asarray(baseline, dtype=bool)
    frames = np.asarray(frame_index)
    if risks.ndim != 2 or risks.shape[0] != len(models):
        raise CalibrationError(f"stage risks must have shape ({len(models)}, A), got {risks.shape}")
    if base.shape != (risks.shape[1],) or frames.shape != base.shape:
        raise CalibrationError("baseline and frame_index must have one entry per agent-frame")
    n_frames = int(np.unique(frames).size)
    n_base = int(base.sum())
    allowed = fn_budget(max_fn_rate, n_frames, n_base)
    thresholds = sequential_thresholds(risks[:, base], allowed)
    return calibration_from_counts(
        models,
        thresholds,
        stage_counts(risks, base, thresholds),
        frames=n_frames,
        agent_frames=int(base.size),
        baseline_agents=n_base,
        max_fn_rate=max_fn_rate,
    )


def fn_budget(max_fn_rate: float, frames: int, baseline_agents: int) -> int:
    """Each stage's false-negative budget, ``floor(max_fn_rate * B)``; raises
    CalibrationError for a rate outside [0, 1] or data without frames or without a
    baseline-important agent-frame."""
    if not 0.0 <= max_fn_rate <= 1.0:
        raise CalibrationError(f"max_fn_rate must be in [0, 1], got {max_fn_rate}")
    if frames == 0:
        raise CalibrationError("no agent-frames to calibrate on (scenes without other agents)")
    if baseline_agents == 0:
        raise CalibrationError(
            "no baseline-important agent in the calibration data: nothing to calibrate against"
        )
    # The tiny tolerance keeps e.g. 0.29 * 100 from flooring to 28.
    return math.floor(max_fn_rate * baseline_agents + 1e-9)


def sequential_thresholds(baseline_risks: np.ndarray, allowed: int) -> tuple[float, ...]:
    """Each stage's threshold from the baseline-important agent-frames alone
    (``baseline_risks (S, B)``; the others never move a threshold): the highest that
    drops at most ``allowed`` of those the stages before it kept. Their order does not
    matter."""
    risks = np.nan_to_num(np.asarray(baseline_risks, dtype=np.float64), nan=-np.inf)
    reaching = np.ones(risks.shape[1], dtype=bool)
    thresholds = []
    for r in risks:
        threshold = highest_threshold(r[reaching], allowed)
        reaching &= r >= threshold
        thresholds.append(threshold)
    return tuple(thresholds)


def stage_counts(
    stage_risks: np.ndarray, baseline: np.ndarray, thresholds: Sequence[float]
) -> np.ndarray:
    """``(3, S)`` int64 for the cascade ``thresholds`` on some agent-frames: per stage the
    agent-frames reaching it, those it drops, and the baseline-important ones it drops.
    Additive: the counts of a corpus are the sums of its scenes'."""
    risks = np.asarray(stage_risks, dtype=np.float64)
    base = np.asarray(baseline, dtype=bool)
    if risks.shape[0] == 0:
        return np.zeros((3, 0), dtype=np.int64)
    keep = cascade_keep(risks, thresholds)
    reaching = np.vstack([np.ones((1, base.size), dtype=bool), keep[:-1]])
    dropped = reaching & ~keep
    return np.stack([reaching.sum(axis=1), dropped.sum(axis=1), (dropped & base).sum(axis=1)])


def calibration_from_counts(
    models: Sequence[str],
    thresholds: Sequence[float],
    counts: np.ndarray,
    *,
    frames: int,
    agent_frames: int,
    baseline_agents: int,
    max_fn_rate: float,
) -> Calibration:
    """The :class:`Calibration` of ``thresholds`` from the summed :func:`stage_counts`
    (``frames``: distinct frames with an agent-frame, for per-frame means)."""
    stages = []
    for s, model in enumerate(models):
        n_in, removed, fn = (int(c) for c in counts[:, s])
        stages.append(
            StageCalibration(
                model=model,
                threshold=thresholds[s],
                agents_in=n_in,
                removed=removed,
                mean_removed_per_frame=float(removed) / frames,
                removed_share=float(removed) / n_in if n_in else math.nan,
                false_negatives=fn,
                fn_share=float(fn) / baseline_agents,
            )
        )
    return Calibration(
        stages=tuple(stages),
        frames=frames,
        agent_frames=agent_frames,
        baseline_agents=baseline_agents,
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
    count is also capped by the tier before it at run time. In parts:
    :func:`tier_proposals` per scene, :func:`median_proposals` of them all.
    """
    risk = np.asarray(survival, dtype=np.float64)
    frames = np.asarray(frame_index)
    if risk.shape != frames.shape or risk.ndim != 1:
        raise CalibrationError("survival and frame_index must be (K,) arrays of equal length")
    if risk.size == 0:
        raise CalibrationError("no survivors to choose tier thresholds from")
    return median_proposals(tier_proposals(risk, frames, target_counts))


def tier_proposals(
    survival: np.ndarray, frame_index: np.ndarray, target_counts: Sequence[int]
) -> np.ndarray:
    """``(F, C)``: each frame's proposal for each target count (see
    :func:`tier_thresholds_for_counts`), for the ``F`` frames with survivors, frame by
    frame in the order of their numbers."""
    for c in target_counts:
        if c < 1:
            raise CalibrationError(f"tier target counts must be >= 1, got {c}")
    risk = np.asarray(survival, dtype=np.float64)
    frames = np.asarray(frame_index)
    if risk.size == 0:
        return np.empty((0, len(target_counts)))
    order = np.lexsort((-risk, frames))  # by frame, riskiest first within a frame
    f_sorted, r_sorted = frames[order], risk[order]
    starts = np.flatnonzero(np.r_[True, f_sorted[1:] != f_sorted[:-1]])
    ends = np.r_[starts[1:], f_sorted.size]  # exclusive
    columns = [r_sorted[np.minimum(starts + c - 1, ends - 1)] for c in target_counts]
    return np.stack(columns, axis=1) if columns else np.empty((starts.size, 0))


def median_proposals(proposals: np.ndarray) -> tuple[float, ...]:
    """The tier minimums: the median over frames of ``proposals (F, C)`` (the frames'
    order does not matter)."""
    if proposals.shape[0] == 0:
        raise CalibrationError("no survivors to choose tier thresholds from")
    return tuple(float(np.median(proposals[:, k])) for k in range(proposals.shape[1]))


# ---------------------------------------------------------------------- with a guarantee
# Calibration against a reference that is not a risk model (what planners react to):
# thresholds chosen so that, with probability at least C over the draw of the
# calibration units, a new unit of the same distribution has an important agent dropped
# with probability at most A. Finite-sample and distribution-free: the order-statistic
# (binomial) rule on unit-level scores, split over the stages by Bonferroni.


def binomial_cdf(k: int, n: int, p: float) -> float:
    """``P(Binomial(n, p) <= k)``, summed in log space (no scipy needed)."""
    if k < 0:
        return 0.0
    if k >= n or p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 0.0
    log_p, log_q = math.log(p), math.log1p(-p)
    terms = [
        math.lgamma(n + 1)
        - math.lgamma(i + 1)
        - math.lgamma(n - i + 1)
        + i * log_p
        + (n - i) * log_q
        for i in range(k + 1)
    ]
    top = max(terms)
    return min(1.0, math.exp(top) * sum(math.exp(t - top) for t in terms))


def allowed_unit_drops(n: int, miss_rate: float, confidence: float) -> int:
    """The largest ``k`` whose order statistic keeps the guarantee: ``t = X_(k+1)`` (the
    ``k + 1``-th smallest of ``n`` unit scores, so that ``k`` calibration units fall
    below it) has ``P(F(t) > A) = P(Binomial(n, A) <= k) <= 1 - C``; -1 when even
    ``k = 0`` does not (too few units)."""
    delta = 1.0 - confidence
    k = -1
    while k + 1 < n and binomial_cdf(k + 1, n, miss_rate) <= delta:
        k += 1
    return k


def units_needed(miss_rate: float, confidence: float) -> int:
    """The fewest units for which any threshold keeps the guarantee: ``(1 - A)^n <= 1 - C``
    (299 for A = 1 %, C = 95 %)."""
    if not (0.0 < miss_rate < 1.0 and 0.0 < confidence < 1.0):
        raise CalibrationError(
            f"miss rate and confidence must lie in (0, 1), got {miss_rate:g}, {confidence:g}"
        )
    return math.ceil(math.log(1.0 - confidence) / math.log1p(-miss_rate) - 1e-12)


def _nan_low(values: np.ndarray) -> np.ndarray:
    """NaN as ``-inf`` (never kept); infinities stay infinite."""
    return np.nan_to_num(
        np.asarray(values, dtype=np.float64), nan=-np.inf, posinf=np.inf, neginf=-np.inf
    )


def unit_minimum(scores: np.ndarray, important: np.ndarray, units: np.ndarray) -> np.ndarray:
    """Per unit with an important agent, the least score of its important agents
    ``(U,)``, in the order of the sorted unit codes. A threshold at or below it drops
    none of that unit's important agents. NaN counts as ``-inf`` (never kept)."""
    s = _nan_low(scores)
    imp = np.asarray(important, dtype=bool)
    codes, inverse = np.unique(np.asarray(units)[imp], return_inverse=True)
    out = np.full(codes.size, np.inf)
    np.minimum.at(out, inverse, s[imp])
    return out


@dataclass(frozen=True)
class GuaranteedStage:
    """One stage calibrated with the order-statistic rule."""

    model: str
    threshold: float
    drops_allowed: int  # calibration units whose least important score may fall below
    units_dropped: int  # calibration units with an important agent this stage drops
    agents_dropped: int  # important agent-frames this stage drops (alone, on all)


@dataclass(frozen=True)
class GuaranteedCalibration:
    """The result of :func:`calibrate_with_guarantee`; :meth:`guarantee` is the TOML's
    ``[guarantee]`` table."""

    stages: tuple[GuaranteedStage, ...]
    miss_rate: float
    confidence: float
    unit: str
    units: int  # calibration units with at least one important agent
    positives: int  # important agent-frames
    stage_miss_rate: float
    stage_confidence: float

    @property
    def thresholds(self) -> tuple[float, ...]:
        return tuple(s.threshold for s in self.stages)

    def guarantee(self) -> dict[str, object]:
        return {
            "miss_rate": self.miss_rate,
            "confidence": self.confidence,
            "unit": self.unit,
            "units": self.units,
            "positives": self.positives,
            "rule": "order statistic (binomial), Bonferroni over the stages",
            "stage_miss_rate": self.stage_miss_rate,
            "stage_confidence": self.stage_confidence,
            "statement": self.statement(),
        }

    def statement(self) -> str:
        return (
            f"with probability >= {self.confidence:g} over the calibration data, a new "
            f"{self.unit} like the {self.units} calibration {self.unit}s with an important "
            f"agent has one of its important agents dropped with probability <= "
            f"{self.miss_rate:g} (so the expected share of its important agents dropped is "
            f"<= {self.miss_rate:g})"
        )


def calibrate_with_guarantee(
    stage_scores: np.ndarray,
    important: np.ndarray,
    units: np.ndarray,
    *,
    models: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str = "scene",
) -> GuaranteedCalibration:
    """Thresholds with a stated guarantee (see the section comment above).

    ``stage_scores (S, A)``: each stage's risk on every agent-frame (``+inf`` for agents
    no stage may drop, e.g. kept by the corridor stage; ``-inf`` for agents dropped
    whatever the thresholds, e.g. by the reachability bound); ``important (A,)``: the
    reference's label; ``units (A,)``: the unit (scene) of each agent-frame. Agents of a
    unit are not independent, units are assumed to be: each unit contributes one score
    per stage, the least of its important agents'.

    The miss budget is split evenly over the ``S`` stages (Bonferroni): each gets miss
    rate ``A / S`` at confidence ``1 - (1 - C) / S``, and its threshold is the order
    statistic of :func:`allowed_unit_drops` on its unit scores (computed on all of a
    unit's important agents, not only those earlier stages kept, so that each stage's
    bound holds alone), less :data:`THRESHOLD_MARGIN`, and never below 0. A new unit is
    missed only when some stage misses it: probability <= ``A`` with confidence >= ``C``.
    Raises CalibrationError, saying how many units are needed, when there are too few.
    """
    scores = np.asarray(stage_scores, dtype=np.float64)
    imp = np.asarray(important, dtype=bool)
    unit_codes = np.asarray(units)
    n_stages = len(models)
    if scores.ndim != 2 or scores.shape[0] != n_stages:
        raise CalibrationError(f"stage scores must have shape ({n_stages}, A), got {scores.shape}")
    if imp.shape != (scores.shape[1],) or unit_codes.shape != imp.shape:
        raise CalibrationError("important and units must have one entry per agent-frame")
    if n_stages == 0:
        raise CalibrationError("no stage to calibrate")
    minima = np.stack([unit_minimum(scores[s], imp, unit_codes) for s in range(n_stages)])
    cal = calibrate_unit_minima(
        minima, models=models, miss_rate=miss_rate, confidence=confidence, unit=unit,
        positives=int(imp.sum()),
    )  # fmt: skip
    return with_agents_dropped(cal, important_dropped(scores, imp, cal.thresholds).tolist())


def calibrate_unit_minima(
    minima: np.ndarray,
    *,
    models: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str,
    positives: int,
) -> GuaranteedCalibration:
    """:func:`calibrate_with_guarantee` from its per-unit summary: ``minima (S, U)``, each
    stage's :func:`unit_minimum` of the ``U`` units with an important agent (in any
    order: a corpus's are its scenes' side by side), ``positives`` the important
    agent-frames. Each stage's ``agents_dropped`` is 0 here: count them with
    :func:`important_dropped` (summed over the scenes) and :func:`with_agents_dropped`."""
    per_units = np.asarray(minima, dtype=np.float64)
    n_stages = len(models)
    if n_stages == 0:
        raise CalibrationError("no stage to calibrate")
    if per_units.ndim != 2 or per_units.shape[0] != n_stages:
        raise CalibrationError(
            f"unit minima must have shape ({n_stages}, U), got {per_units.shape}"
        )
    stage_miss = miss_rate / n_stages
    stage_conf = 1.0 - (1.0 - confidence) / n_stages
    need = units_needed(stage_miss, stage_conf)
    n_units = int(per_units.shape[1])
    if n_units < need:
        per = (
            ""
            if n_stages == 1
            else f" ({n_stages} stages: {stage_miss:.3g} at {stage_conf:.4g} each)"
        )
        raise CalibrationError(
            f"miss rate {miss_rate:g} at confidence {confidence:g}{per} needs at least "
            f"{need} {unit}s with a planner-important agent; the data has {n_units}. Give "
            f"more scenes, or ask for a larger miss rate or a lower confidence"
        )
    k = allowed_unit_drops(n_units, stage_miss, stage_conf)
    stages = []
    for model, per_unit in zip(models, per_units, strict=True):
        forced = int(np.isneginf(per_unit).sum())
        if forced > k:
            raise CalibrationError(
                f"{forced} {unit}s have an important agent that no threshold of {model} can "
                f"keep (dropped ahead of the stages, e.g. by the reachability bound), more "
                f"than the {k} the guarantee allows"
            )
        threshold = max(highest_threshold(per_unit, k), 0.0)
        stages.append(
            GuaranteedStage(
                model=model,
                threshold=threshold,
                drops_allowed=k,
                units_dropped=int((per_unit < threshold).sum()),
                agents_dropped=0,
            )
        )
    return GuaranteedCalibration(
        stages=tuple(stages),
        miss_rate=float(miss_rate),
        confidence=float(confidence),
        unit=unit,
        units=n_units,
        positives=int(positives),
        stage_miss_rate=stage_miss,
        stage_confidence=stage_conf,
    )


def important_dropped(
    stage_scores: np.ndarray, important: np.ndarray, thresholds: Sequence[float]
) -> np.ndarray:
    """``(S,)`` int64: the important agent-frames each stage alone drops at
    ``thresholds`` (additive over scenes)."""
    scores = _nan_low(stage_scores)
    imp = np.asarray(important, dtype=bool)
    below = scores < np.asarray(thresholds, dtype=np.float64)[:, None]
    return (below & imp[None, :]).sum(axis=1).astype(np.int64)


def with_agents_dropped(
    cal: GuaranteedCalibration, agents_dropped: Sequence[int]
) -> GuaranteedCalibration:
    """``cal`` with each stage's ``agents_dropped`` set (see :func:`important_dropped`)."""
    stages = tuple(
        dataclasses.replace(s, agents_dropped=int(n))
        for s, n in zip(cal.stages, agents_dropped, strict=True)
    )
    return dataclasses.replace(cal, stages=stages)
