"""ROC metrics of a risk model against the baseline's important set (paper Sec. II, IV-B).

Per situation (one frame), agents are *positives* when the baseline marks them
important. A threshold keeps the agents whose score is ``>=`` it; then
``TPR = TP / (TP + FN)`` and ``FPR = FP / (FP + TN)``. Curves are averaged over the
situations where they are defined; a situation without positives has no TPR, one
without negatives has no FPR, and both are counted and reported, never averaged as 0.

Arrays first, options keyword-only. Scores are ``(N_i,)`` per situation with NaN for
entries that are not agents (the ego, invalid agents); those are ignored.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from risk.errors import RiskError

#: Above this many distinct observed scores, default thresholds use a grid (see
#: :func:`default_thresholds`).
MAX_DEFAULT_THRESHOLDS = 2048


class ConfusionCounts(NamedTuple):
    """Counts ``(K,)`` per threshold; int64."""

    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    tn: np.ndarray


@dataclass(frozen=True, eq=False)
class RocResult:
    """A threshold sweep over ``S`` situations and ``K`` thresholds.

    - ``thresholds`` ``(K,)`` ascending; ``tpr``, ``fpr`` ``(S, K)`` with NaN where
      undefined (no positives / no negatives in that situation); ``kept`` ``(S, K)``
      the number of agents kept;
    - ``mean_tpr``, ``mean_fpr``, ``std_tpr`` ``(K,)`` over the situations where each is
      defined (``std_tpr`` is the population standard deviation, ddof = 0: the spread of
      this set of situations, the paper's robustness measure); NaN when none is;
    - ``auc``: trapezoidal area under the mean curve, closed with (0, 0) (a threshold
      above every score keeps nothing) and (1, 1) (at or below the lowest score everything
      is kept); NaN when the mean curve is undefined;
    - ``n_situations``, ``n_no_positive`` (TPR undefined), ``n_no_negative`` (FPR
      undefined).
    """

    thresholds: np.ndarray
    tpr: np.ndarray
    fpr: np.ndarray
    kept: np.ndarray
    mean_tpr: np.ndarray
    mean_fpr: np.ndarray
    std_tpr: np.ndarray
    auc: float
    n_situations: int
    n_no_positive: int
    n_no_negative: int


def _situation(scores: np.ndarray, baseline: np.ndarray, i: int | None = None) -> tuple:
    s = np.asarray(scores, dtype=np.float64)
    b = np.asarray(baseline)
    where = "" if i is None else f"situation {i}: "
    if s.ndim != 1 or b.shape != s.shape:
        raise RiskError(
            f"{where}scores and baseline must both have shape (N,), got {s.shape} and {b.shape}"
        )
    if b.dtype != bool:
        raise RiskError(f"{where}baseline must be a boolean mask, got dtype {b.dtype}")
    if np.isinf(s).any():
        raise RiskError(f"{where}scores must be finite or NaN (not an agent)")
    return s, b


def confusion_counts(
    scores: np.ndarray, baseline: np.ndarray, thresholds: np.ndarray
) -> ConfusionCounts:
    """TP, FP, FN, TN ``(K,)`` of one situation for every threshold (keep ``score >= t``).

    ``scores`` ``(N,)`` (NaN = not an agent, ignored), ``baseline`` ``(N,)`` bool.
    Vectorised with sorted scores and ``searchsorted``: O((N + K) log N).
    """
    s, b = _situation(scores, baseline)
    t = np.asarray(thresholds, dtype=np.float64)
    if np.isnan(t).any():
        raise RiskError("thresholds must not be NaN")
    agent = ~np.isnan(s)
    pos = np.sort(s[agent & b])
    neg = np.sort(s[agent & ~b])
    tp = pos.size - np.searchsorted(pos, t, side="left")
    fp = neg.size - np.searchsorted(neg, t, side="left")
    return ConfusionCounts(
        tp=tp.astype(np.int64),
        fp=fp.astype(np.int64),
        fn=(pos.size - tp).astype(np.int64),
        tn=(neg.size - fp).astype(np.int64),
    )


def default_thresholds(
    scores: Sequence[np.ndarray], *, max_count: int = MAX_DEFAULT_THRESHOLDS
) -> np.ndarray:
    """Thresholds ``(K,)`` ascending for a sweep over these situations' scores.

    The union of all observed score values, so the sweep visits every operating point
    exactly. When there are more than ``max_count`` distinct values: a log-spaced grid
    from the smallest positive to the largest score (plus 0 when a score is 0), which
    suits risks spanning many decades (survival: 1e-300 to 1); a linear grid when scores
    are negative. The grid always includes the smallest and largest observed value.
    """
    finite = [np.asarray(s, dtype=np.float64) for s in scores]
    values = np.unique(np.concatenate([s[np.isfinite(s)] for s in finite] or [np.empty(0)]))
    if values.size == 0:
        raise RiskError("no scores to sweep: every situation is empty or all NaN")
    if values.size <= max_count:
        return values
    lo, hi = values[0], values[-1]
    if lo < 0:
        return np.linspace(lo, hi, max_count)
    positive = values[values > 0]
    grid = np.geomspace(positive[0], hi, max_count - (1 if lo == 0 else 0))
    grid[0], grid[-1] = positive[0], hi  # exact ends despite rounding
    return np.r_[0.0, grid] if lo == 0 else grid


def _nanmean_rows(a: np.ndarray) -> np.ndarray:
    """Column means ``(K,)`` of ``(S, K)`` over non-NaN rows; NaN when none."""
    defined = ~np.isnan(a)
    count = defined.sum(axis=0)
    total = np.where(defined, a, 0.0).sum(axis=0)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def roc_curve(
    scores: Sequence[np.ndarray],
    baselines: Sequence[np.ndarray],
    *,
    thresholds: np.ndarray | None = None,
) -> RocResult:
    """The ROC sweep of one model over situations (paper Fig. 4).

    ``scores``: per situation ``(N_i,)`` risks (NaN = not an agent); ``baselines``: per
    situation ``(N_i,)`` bool, the baseline's important agents. ``thresholds``: ``(K,)``
    (sorted ascending here); default :func:`default_thresholds`.
    """
    if len(scores) != len(baselines):
        raise RiskError(
            f"got {len(scores)} score arrays but {len(baselines)} baseline masks; "
            "need one of each per situation"
        )
    if len(scores) == 0:
        raise RiskError("no situations to evaluate")
    pairs = [_situation(s, b, i) for i, (s, b) in enumerate(zip(scores, baselines, strict=True))]
    t = (
        default_thresholds([s for s, _ in pairs])
        if thresholds is None
        else np.sort(np.asarray(thresholds, dtype=np.float64))
    )
    if t.ndim != 1 or t.size == 0:
        raise RiskError(f"thresholds must be a non-empty 1-D array, got shape {t.shape}")
    n_s, n_k = len(pairs), t.size
    tpr = np.full((n_s, n_k), np.nan)
    fpr = np.full((n_s, n_k), np.nan)
    kept = np.zeros((n_s, n_k), dtype=np.int64)
    for i, (s, b) in enumerate(pairs):  # a loop over situations, each vectorised over K
        c = confusion_counts(s, b, t)
        kept[i] = c.tp + c.fp
        if c.tp[0] + c.fn[0] > 0:
            tpr[i] = c.tp / (c.tp + c.fn)
        if c.fp[0] + c.tn[0] > 0:
            fpr[i] = c.fp / (c.fp + c.tn)
    no_pos = np.isnan(tpr[:, 0])
    no_neg = np.isnan(fpr[:, 0])
    mean_tpr = _nanmean_rows(tpr)
    mean_fpr = _nanmean_rows(fpr)
    std_tpr = np.full(n_k, np.nan) if no_pos.all() else tpr[~no_pos].std(axis=0)
    return RocResult(
        thresholds=t,
        tpr=tpr,
        fpr=fpr,
        kept=kept,
        mean_tpr=mean_tpr,
        mean_fpr=mean_fpr,
        std_tpr=std_tpr,
        auc=_auc(mean_fpr, mean_tpr),
        n_situations=n_s,
        n_no_positive=int(no_pos.sum()),
        n_no_negative=int(no_neg.sum()),
    )


def _auc(mean_fpr: np.ndarray, mean_tpr: np.ndarray) -> float:
    """Area under the mean curve, closed with (0, 0) and (1, 1)."""
    if np.isnan(mean_fpr).any() or np.isnan(mean_tpr).any():
        return float("nan")
    # Thresholds ascend, so both rates descend; walk from the strictest threshold.
    x = np.r_[0.0, mean_fpr[::-1], 1.0]
    y = np.r_[0.0, mean_tpr[::-1], 1.0]
    return float(np.sum(np.diff(x) * (y[1:] + y[:-1]) / 2.0))


def threshold_for_tpr(result: RocResult, target: float) -> float:
    """The highest threshold at which the mean TPR reaches ``target`` (in [0, 1]).

    Mean TPR never grows with the threshold, so every lower threshold reaches it too. A
    tolerance of 1e-12 absorbs rounding in the mean. Raises RiskError when TPR is
    undefined everywhere or no swept threshold reaches the target.
    """
    if not 0.0 <= target <= 1.0:
        raise RiskError(f"target TPR must be in [0, 1], got {target}")
    if np.isnan(result.mean_tpr).all():
        raise RiskError("TPR is undefined: no situation has a baseline-important agent")
    with np.errstate(invalid="ignore"):
        ok = result.mean_tpr >= target - 1e-12
    if not ok.any():
        raise RiskError(
            f"no threshold reaches a mean TPR of {target}; the best is "
            f"{np.nanmax(result.mean_tpr):.4g} (lower thresholds were not swept)"
        )
    return float(result.thresholds[ok].max())
