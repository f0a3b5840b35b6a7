"""The test oracle of :func:`risk.metrics.exact_sweep`: the ROC sweep written plainly.

One loop over situations, each a full ``(K,)`` row of TPR and FPR from
:func:`risk.metrics.confusion_counts`, then column means and stds over the ``(S, K)``
matrices: slow and obvious, with nothing shared with the cumulative-sum sweep but the
definitions (keep ``score >= threshold``; undefined rates are NaN and left out of the
means; AUC closed with (0, 0) and (1, 1)).

It used to be the product's ``risk.metrics.roc_curve`` (with a 2048-point threshold grid
for large inputs); the product now has one sweep, the exact one, and this is its oracle.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from risk.errors import RiskError
from risk.metrics import _situation, confusion_counts


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


def observed_thresholds(scores: Sequence[np.ndarray]) -> np.ndarray:
    """Every distinct finite score of these situations, ascending (the exact sweep's
    thresholds)."""
    finite = [np.asarray(s, dtype=np.float64) for s in scores]
    values = np.unique(np.concatenate([s[np.isfinite(s)] for s in finite] or [np.empty(0)]))
    if values.size == 0:
        raise RiskError("no scores to sweep: every situation is empty or all NaN")
    return values


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
    (sorted ascending here); default :func:`observed_thresholds`.
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
        observed_thresholds([s for s, _ in pairs])
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
