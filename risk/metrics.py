"""ROC metrics of a risk model against the baseline's important set (paper Sec. II, IV-B).

Per situation (one frame), agents are *positives* when the baseline marks them
important. A threshold keeps the agents whose score is ``>=`` it; then
``TPR = TP / (TP + FN)`` and ``FPR = FP / (FP + TN)``. Curves are averaged over the
situations where they are defined; a situation without positives has no TPR, one
without negatives has no FPR, and both are counted and reported, never averaged as 0.

- :func:`exact_sweep`: the mean ROC curve of one model over many situations, exact at
  every distinct score, in O(A log A) for ``A`` agent-frames (the one sweep of the
  project: ``replay stats`` and ``replay experiment`` use it);
- :func:`confusion_counts`: TP, FP, FN, TN of one situation at given thresholds;
- :func:`threshold_for_tpr`: the operating point of a sweep for a target mean TPR.

The tests check :func:`exact_sweep` against a plain per-situation loop
(``tests/roc_oracle.py``). Scores use NaN for entries that are not agents (the ego,
invalid agents); those are ignored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from risk.errors import RiskError

#: Variances of TPR below this are rounding (see :func:`exact_sweep`); std < 3e-7.
VAR_ROUNDING = 1e-13


class ConfusionCounts(NamedTuple):
    """Counts ``(K,)`` per threshold; int64."""

    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    tn: np.ndarray


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


@dataclass(frozen=True, eq=False)
class SortedScores:
    """Included agent-frames sorted by descending score, ready for weighted sweeps.

    ``scores (A',)`` descending; ``positive (A',)`` bool; ``cluster (A',)`` cluster
    codes; ``group_end (K,)``: index of the last agent-frame of each run of equal scores
    (one operating point each, strictest first).
    """

    scores: np.ndarray
    positive: np.ndarray
    cluster: np.ndarray
    group_end: np.ndarray

    @classmethod
    def build(
        cls,
        scores: np.ndarray,
        positive: np.ndarray,
        cluster: np.ndarray | None = None,
        *,
        finite: bool = True,
    ) -> SortedScores:
        """Sort ``scores (A,)`` (NaN: not an agent, left out) riskiest first, stable (ties
        keep their input order), with ``positive (A,)`` and ``cluster (A,)`` alongside.
        ``finite``: refuse infinite scores (the pooled evaluation's thresholds must be
        finite; the mean sweep takes them)."""
        s = np.asarray(scores, dtype=np.float64)
        p = np.asarray(positive, dtype=bool)
        c = np.zeros(s.size, dtype=np.int64) if cluster is None else np.asarray(cluster)
        if s.shape != p.shape or s.shape != c.shape or s.ndim != 1:
            raise RiskError(
                f"scores, positive and cluster must all have shape (A,), got {s.shape}, "
                f"{p.shape} and {c.shape}"
            )
        if finite and np.isinf(s).any():
            raise RiskError("scores must be finite or NaN (not an agent)")
        ok = ~np.isnan(s)
        order = np.argsort(-s[ok], kind="stable")
        sd = s[ok][order]
        end = np.flatnonzero(np.r_[sd[1:] != sd[:-1], True]) if sd.size else np.empty(0, int)
        return cls(sd, p[ok][order], c[ok][order].astype(np.int64), end)

    def at_thresholds(self, weights: np.ndarray) -> np.ndarray:
        """``(K,)``: the sum of ``weights`` (one per sorted agent-frame) over the agent-frames
        each operating point keeps (``score >= threshold``), strictest first."""
        return np.cumsum(weights)[self.group_end]

    def rates(self, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(tpr, fpr)`` ``(K,)`` at each operating point, strictest first (weights
        ``(A',)`` per sorted agent-frame; default 1). NaN when there is no positive (or
        no negative)."""
        w = np.ones(self.scores.size) if weights is None else weights
        wp = np.cumsum(np.where(self.positive, w, 0.0))
        wn = np.cumsum(np.where(self.positive, 0.0, w))
        tot_p, tot_n = (wp[-1], wn[-1]) if wp.size else (0.0, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            tpr = wp[self.group_end] / tot_p if tot_p > 0 else np.full(self.group_end.size, np.nan)
            fpr = wn[self.group_end] / tot_n if tot_n > 0 else np.full(self.group_end.size, np.nan)
        return tpr, fpr

    def kept_before(self, threshold: float) -> int:
        """How many sorted agent-frames have ``score >= threshold``."""
        return int(np.searchsorted(-self.scores, -threshold, side="right"))


@dataclass(frozen=True, eq=False)
class Sweep:
    """A model's mean ROC curve over ``S`` situations, exact at every distinct score.

    - ``thresholds (K,)`` ascending: every distinct non-NaN score;
    - ``mean_tpr``, ``mean_fpr (K,)``: over the situations where each rate is defined
      (a positive / a negative present); ``std_tpr (K,)``: population std (ddof = 0) of
      the TPR over the same situations as ``mean_tpr`` (the paper's robustness measure);
      ``mean_kept (K,)``: agents with ``score >= threshold``, mean over all situations;
    - ``auc``: trapezoids under the mean curve, closed with (0, 0) (a threshold above every
      score keeps nothing) and (1, 1) (at or below the lowest score everything is kept);
      NaN when the mean curve is undefined;
    - ``n_situations``, ``n_no_positive`` (TPR undefined), ``n_no_negative`` (FPR
      undefined).
    """

    thresholds: np.ndarray
    mean_tpr: np.ndarray
    mean_fpr: np.ndarray
    std_tpr: np.ndarray
    mean_kept: np.ndarray
    auc: float
    n_situations: int
    n_no_positive: int
    n_no_negative: int


def exact_sweep(
    scores: np.ndarray,
    situation: np.ndarray,
    baseline: np.ndarray,
    *,
    n_situations: int | None = None,
) -> Sweep:
    """The mean ROC curve of ``scores (A,)`` at every distinct score, in O(A log A).

    ``situation (A,)``: each agent-frame's situation, integers in ``[0, S)``;
    ``baseline (A,)`` bool: the baseline's important agents; ``n_situations``: ``S``
    (default ``situation.max() + 1``; situations without any agent-frame count in
    ``mean_kept`` only).

    Why it is exact without an ``(S, K)`` matrix: lowering the threshold past an agent's
    score adds ``1 / P_s`` to its situation's TPR, so the mean TPR is a cumulative sum
    of per-agent weights ``1 / (P_s S_P)`` over the agents sorted by score (``S_P``
    situations with a positive). For the std, TPR_s^2 rises from ``(k/P_s)^2`` to
    ``((k+1)/P_s)^2`` when the ``(k+1)``-th positive of situation ``s`` (by descending
    score) enters; tied agents enter together, so any order among them gives the same
    sum. NaN scores (not an agent) are ignored.
    """
    s = np.asarray(scores, dtype=np.float64)
    sit_all = np.asarray(situation)
    base_all = np.asarray(baseline)
    if s.ndim != 1 or sit_all.shape != s.shape or base_all.shape != s.shape:
        raise RiskError(
            "scores, situation and baseline must all have shape (A,), got "
            f"{s.shape}, {sit_all.shape} and {base_all.shape}"
        )
    if base_all.dtype != bool:
        raise RiskError(f"baseline must be a boolean mask, got dtype {base_all.dtype}")
    if sit_all.size and (not np.issubdtype(sit_all.dtype, np.integer) or sit_all.min() < 0):
        raise RiskError("situation must hold integer situation indices >= 0")
    n_sit = int(sit_all.max()) + 1 if n_situations is None and sit_all.size else n_situations
    ok = ~np.isnan(s)
    base, sit = base_all[ok], sit_all[ok].astype(np.int64)
    if not ok.any() or not n_sit:
        raise RiskError("no agent has a risk value (every score is NaN)")
    pos = np.bincount(sit[base], minlength=n_sit)
    neg = np.bincount(sit[~base], minlength=n_sit)
    n_pos_sits, n_neg_sits = int((pos > 0).sum()), int((neg > 0).sum())
    srt = SortedScores.build(s, base_all, sit_all, finite=False)  # riskiest first
    b_desc, sit_desc = srt.positive, srt.cluster
    with np.errstate(divide="ignore", invalid="ignore"):
        w_tpr = np.where(b_desc, 1.0 / pos[sit_desc], 0.0)
        w_fpr = np.where(~b_desc, 1.0 / neg[sit_desc], 0.0)
        w_sq = np.where(b_desc, (2.0 * _rank_in_situation(sit_desc, b_desc) + 1.0)
                        / pos[sit_desc] ** 2, 0.0)  # fmt: skip
    # The last agent of each run of equal scores closes that threshold.
    last = srt.group_end
    cum_tpr, cum_fpr, cum_sq = (srt.at_thresholds(w) for w in (w_tpr, w_fpr, w_sq))
    mean_tpr = _normalised(cum_tpr, n_pos_sits)
    mean_fpr = _normalised(cum_fpr, n_neg_sits)
    # E[TPR^2] is 1 when everyone is kept, like the mean: normalise it the same way.
    mean_sq = _normalised(cum_sq, n_pos_sits)
    var = mean_sq - mean_tpr**2
    # E[x^2] - E[x]^2 leaves rounding of a few eps where the spread is 0; sqrt would
    # blow that up to ~1e-8, so variances below VAR_ROUNDING count as 0.
    std = np.sqrt(np.where(var < VAR_ROUNDING, 0.0, var))
    kept = (last + 1) / n_sit
    rev = slice(None, None, -1)  # descending -> ascending thresholds
    return Sweep(
        thresholds=srt.scores[last][rev],
        mean_tpr=mean_tpr[rev],
        mean_fpr=mean_fpr[rev],
        std_tpr=std[rev],
        mean_kept=kept[rev],
        auc=trapezoid_auc(mean_fpr, mean_tpr),
        n_situations=n_sit,
        n_no_positive=n_sit - n_pos_sits,
        n_no_negative=n_sit - n_neg_sits,
    )


def _rank_in_situation(sit: np.ndarray, positive: np.ndarray) -> np.ndarray:
    """For agents sorted by descending score: how many positives of the same situation
    come before each agent (``(A,)``; only meaningful for positives)."""
    order = np.argsort(sit, kind="stable")  # by situation, keeping the score order
    pos_sorted = positive[order].astype(np.int64)
    before = np.cumsum(pos_sorted) - pos_sorted  # positives before, over all situations
    s_sorted = sit[order]
    first = np.r_[0, np.flatnonzero(s_sorted[1:] != s_sorted[:-1]) + 1]
    group_start = np.repeat(before[first], np.diff(np.r_[first, s_sorted.size]))
    rank = np.empty(sit.size, dtype=np.int64)
    rank[order] = before - group_start
    return rank


def _normalised(cum: np.ndarray, n_sits: int) -> np.ndarray:
    """Mean rates from cumulative weights; the last entry (everyone kept) is exactly 1,
    so that rounding never hides the TPR = 1 operating point."""
    if n_sits == 0 or cum.size == 0 or cum[-1] <= 0:
        return np.full(cum.size, np.nan)
    return np.minimum(cum / cum[-1], 1.0)


def trapezoid_auc(fpr_desc: np.ndarray, tpr_desc: np.ndarray) -> float:
    """The area under a ROC curve given from its strictest threshold on ``(K,)``:
    trapezoids, closed with (0, 0) (a threshold above every score keeps nothing) and
    (1, 1) (at or below the lowest score everything is kept); NaN when the curve is empty
    or undefined anywhere. The one AUC of the project (the mean sweep, the pooled
    evaluation and its bootstrap, through :func:`trapezoid_auc_rows`)."""
    if tpr_desc.size == 0 or np.isnan(fpr_desc).any() or np.isnan(tpr_desc).any():
        return math.nan
    return float(trapezoid_auc_rows(fpr_desc[None, :], tpr_desc[None, :])[0])


def trapezoid_auc_rows(fpr_desc: np.ndarray, tpr_desc: np.ndarray) -> np.ndarray:
    """:func:`trapezoid_auc` of each row of ``(B, K)`` curves, ``(B,)`` (NaN where a row
    has a NaN rate)."""
    ones = np.ones((fpr_desc.shape[0], 1))
    x = np.concatenate([0 * ones, fpr_desc, ones], axis=1)
    y = np.concatenate([0 * ones, tpr_desc, ones], axis=1)
    return np.sum(np.diff(x, axis=1) * (y[:, 1:] + y[:, :-1]) / 2, axis=1)


class _Curve(Protocol):
    thresholds: np.ndarray
    mean_tpr: np.ndarray


def threshold_for_tpr(result: _Curve, target: float) -> float:
    """The highest threshold of a sweep at which the mean TPR reaches ``target`` (in
    [0, 1]).

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
