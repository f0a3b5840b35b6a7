"""Pooled ROC curves from counts per score bin that add up over scenes.

The exact pooled ROC (:func:`risk.evaluation.pooled_roc`) sorts every agent-frame of the
corpus at once. Here each scene is reduced to :class:`BinCounts`: its positives and
negatives per bin of a fixed score grid, with the lowest and highest score seen in each
bin. Counts of scenes merge by adding (:func:`merge_counts`), in any order, so a driver
holds one merged curve per model and reference, never the rows.

**The grid** (:func:`score_bins`) does not depend on the data: a float64 score's bits,
mapped to an integer in score order, without their lowest ``52 - GRID_BITS`` mantissa
bits. Each bin is an interval of scores, ``2**GRID_BITS`` bins per power of two (relative
width ``2**-GRID_BITS``, about 2.4e-4), over every magnitude and sign.

**Exactness.** A bin holding a single score value (``low == high``) is exact: all its
pairs are ties, which the trapezoid AUC counts as half, as the exact sweep does. Only a
positive and a negative in the same *mixed* bin (``low < high``) may be ordered
differently by the exact curve (it counts them as 0 or 1, the binned curve as 1/2), so

    |AUC(binned) - AUC(exact)| <= sum over mixed bins of p_b * n_b / (2 * P * N),

which :func:`binned_roc` reports as ``auc_error_bound`` (0 when no bin is mixed). The
binned curve's points are points of the exact curve (the thresholds at bin lows), so the
TPR at a fixed FPR is never above the exact one and below it by at most the largest share
of positives in one mixed bin (``tpr_error_bound``).

**Bootstrap.** :func:`scene_bin_matrix` puts every scene's counts on at most
:data:`risk.evaluation.BOOT_BINS` coarse bins of the merged curve (consecutive bins
merged, as the exact bootstrap merges consecutive distinct scores), one column per scene
in a fixed scene order; :func:`binned_replicates` weighs the columns by the draws of
:func:`risk.evaluation.scene_draws`.

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from risk.errors import RiskError
from risk.evaluation import (
    BOOT_BINS,
    FPR_POINTS,
    RATE_TOLERANCE,
    reference_mask,
    replicate_curves,
    tpr_at_fpr,
)
from risk.metrics import trapezoid_auc

#: Mantissa bits of a score kept by the grid (of float64's 52).
GRID_BITS = 12
#: At most this many bins per merged curve (:func:`merge_counts`' ``max_bins`` in the
#: streamed evaluation): about 2.6 MB a curve.
MAX_CURVE_BINS = 1 << 16
#: The coarsest level: two bins, the negative scores and the others.
MAX_LEVEL = 63 - (52 - GRID_BITS)
_SHIFT = 52 - GRID_BITS
_MAGNITUDE = np.int64(0x7FFF_FFFF_FFFF_FFFF)


def score_bins(scores: np.ndarray, level: int = 0) -> np.ndarray:
    """``(A,)`` int64 bin of each finite or infinite score (not NaN) on the fixed grid
    (``level`` more mantissa bits dropped: see :func:`coarsen`); bins are ordered as the
    scores are (``a <= b`` implies ``bin(a) <= bin(b)``)."""
    s = np.asarray(scores, dtype=np.float64) + 0.0  # -0.0 -> +0.0: one zero
    if np.isnan(s).any():
        raise RiskError("score_bins: NaN is not a score (leave non-agents out first)")
    bits = s.view(np.int64)
    # Negative floats order backwards as integers: flip their magnitude bits.
    ordered = bits ^ ((bits >> 63) & _MAGNITUDE)
    return ordered >> (_SHIFT + level)


@dataclass(frozen=True, eq=False)
class BinCounts:
    """Positives and negatives per occupied grid bin: ``bins (K,)`` int64 ascending and
    distinct; ``positives``, ``negatives (K,)`` int64; ``low``, ``high (K,)`` float64:
    the lowest and the highest score in the bin."""

    bins: np.ndarray
    positives: np.ndarray
    negatives: np.ndarray
    low: np.ndarray
    high: np.ndarray
    level: int = 0  # mantissa bits dropped beyond the grid's (see coarsen)

    @classmethod
    def empty(cls) -> BinCounts:
        i, f = np.empty(0, np.int64), np.empty(0, np.float64)
        return cls(i, i.copy(), i.copy(), f, f.copy())

    @property
    def nbytes(self) -> int:
        return sum(
            a.nbytes for a in (self.bins, self.positives, self.negatives, self.low, self.high)
        )


def bin_counts(scores: np.ndarray, reference: np.ndarray) -> BinCounts:
    """The counts of ``scores (A,)`` (NaN: not an agent, left out) against ``reference
    (A,)`` label codes (1, 0, -1 = unknown, left out) or booleans."""
    include, positive = reference_mask(reference)
    s = np.asarray(scores, dtype=np.float64)
    if s.shape != include.shape:
        raise RiskError(f"scores {s.shape} and reference {include.shape} differ in shape")
    ok = include & ~np.isnan(s)
    return _grouped(score_bins(s[ok]), s[ok] + 0.0, positive[ok].astype(np.int64),
                    (~positive[ok]).astype(np.int64), s[ok] + 0.0)  # fmt: skip


def _grouped(
    bins: np.ndarray,
    low: np.ndarray,
    pos: np.ndarray,
    neg: np.ndarray,
    high: np.ndarray,
    level: int = 0,
) -> BinCounts:
    """Rows ``(bin, low, positives, negatives, high)`` summed per bin."""
    if bins.size == 0:
        e = BinCounts.empty()
        return BinCounts(e.bins, e.positives, e.negatives, e.low, e.high, level)
    order = np.argsort(bins, kind="stable")
    b = bins[order]
    start = np.r_[0, np.flatnonzero(b[1:] != b[:-1]) + 1]
    return BinCounts(
        b[start],
        np.add.reduceat(pos[order], start),
        np.add.reduceat(neg[order], start),
        np.minimum.reduceat(low[order], start),
        np.maximum.reduceat(high[order], start),
        level,
    )


def coarsen(counts: BinCounts, level: int) -> BinCounts:
    """``counts`` on the grid with ``level`` more mantissa bits dropped (each step merges
    pairs of neighbouring bins: bins stay intervals, twice as wide)."""
    if level < counts.level:
        raise RiskError(f"cannot refine counts of level {counts.level} to level {level}")
    if level == counts.level:
        return counts
    return _grouped(counts.bins >> (level - counts.level), counts.low, counts.positives,
                    counts.negatives, counts.high, level)  # fmt: skip


def merge_counts(parts: Sequence[BinCounts], max_bins: int | None = None) -> BinCounts:
    """The counts of the union of the agent-frames of ``parts`` (any order), on the
    coarsest level among them; with ``max_bins``, coarsened further until at most that
    many bins are left or :data:`MAX_LEVEL` is reached (two bins), so that a merged
    curve's memory is bounded whatever the corpus; the AUC bound of :func:`binned_roc`
    grows with the width of the bins that mix scores."""
    level = max((p.level for p in parts), default=0)
    parts = [coarsen(p, level) for p in parts if p.bins.size]
    if not parts:
        empty = np.empty(0)
        return _grouped(np.empty(0, np.int64), empty, empty, empty, empty, level)
    if len(parts) == 1:
        out = parts[0]
    else:
        bins, low, pos, neg, high = (
            np.concatenate([getattr(p, f) for p in parts])
            for f in ("bins", "low", "positives", "negatives", "high")
        )
        out = _grouped(bins, low, pos, neg, high, level)
    while max_bins is not None and out.bins.size > max_bins and out.level < MAX_LEVEL:
        out = coarsen(out, out.level + 1)
    return out


@dataclass(frozen=True, eq=False)
class BinnedRoc:
    """The pooled ROC at the grid's bins (see the module docstring): ``thresholds (K,)``
    ascending (each bin's lowest score; keep ``score >= threshold``), ``tpr``, ``fpr
    (K,)``, ``auc`` and its ``auc_error_bound``, ``tpr_error_bound``, ``n_positive``,
    ``n_negative`` and ``mixed_bins`` (bins holding more than one score value)."""

    thresholds: np.ndarray
    tpr: np.ndarray
    fpr: np.ndarray
    auc: float
    auc_error_bound: float
    tpr_error_bound: float
    n_positive: int
    n_negative: int
    mixed_bins: int

    def tpr_at(self, fpr: float) -> float:
        """The best TPR with an FPR at most ``fpr`` (as :func:`risk.evaluation.tpr_at_fpr`)."""
        return tpr_at_fpr(self.tpr[::-1], self.fpr[::-1], fpr)


def binned_roc(counts: BinCounts) -> BinnedRoc:
    """The pooled ROC of merged counts, with the bounds of its difference from the exact
    every-distinct-score curve."""
    p, n = counts.positives[::-1], counts.negatives[::-1]  # strictest first
    cp, cn = np.cumsum(p), np.cumsum(n)
    n_pos = int(cp[-1]) if cp.size else 0
    n_neg = int(cn[-1]) if cn.size else 0
    nan = np.full(cp.size, np.nan)
    tpr = cp / n_pos if n_pos else nan
    fpr = cn / n_neg if n_neg else nan
    mixed = counts.low < counts.high
    if n_pos and n_neg:
        pairs = float(np.sum(counts.positives[mixed] * counts.negatives[mixed].astype(np.float64)))
        auc_bound = pairs / (2.0 * n_pos * n_neg)
        tpr_bound = float(counts.positives[mixed].max(initial=0)) / n_pos
    else:
        auc_bound = tpr_bound = math.nan
    return BinnedRoc(
        thresholds=counts.low.copy(),
        tpr=tpr[::-1],
        fpr=fpr[::-1],
        auc=trapezoid_auc(fpr, tpr),
        auc_error_bound=auc_bound,
        tpr_error_bound=tpr_bound,
        n_positive=n_pos,
        n_negative=n_neg,
        mixed_bins=int(mixed.sum()),
    )


def coarse_edges(merged: BinCounts, max_bins: int = BOOT_BINS) -> np.ndarray:
    """``(K,)`` the coarse bin (0 = strictest) of each of ``merged``'s bins: at most
    ``max_bins`` runs of consecutive bins, as the exact bootstrap groups distinct
    scores (``group * n_bins // n_groups``, strictest first)."""
    if max_bins < 1:
        raise RiskError(f"max_bins must be >= 1, got {max_bins}")
    k = merged.bins.size
    n_bins = min(k, max_bins)
    strictest_first = np.arange(k)[::-1]  # bin K-1 (highest scores) is group 0
    return strictest_first * n_bins // max(k, 1)


def scene_bin_matrix(
    merged: BinCounts, scenes: Sequence[BinCounts], max_bins: int = BOOT_BINS
) -> tuple[np.ndarray, np.ndarray]:
    """``(positives, negatives)`` ``(bins, S)`` int64: each scene's counts (a column,
    in the order of ``scenes``) on the coarse bins of ``merged`` (strictest first).
    Every scene's bins must be among ``merged``'s (``merged`` is their merge)."""
    coarse = coarse_edges(merged, max_bins)
    n_bins = int(coarse.max()) + 1 if coarse.size else 0
    pos = np.zeros((n_bins, len(scenes)), dtype=np.int64)
    neg = np.zeros((n_bins, len(scenes)), dtype=np.int64)
    for j, scene in enumerate(scenes):  # one scene at a time: vectorised inside
        if not scene.bins.size:
            continue
        sc = coarsen(scene, merged.level)
        at = np.searchsorted(merged.bins, sc.bins)
        if (at >= merged.bins.size).any() or (
            merged.bins[np.minimum(at, merged.bins.size - 1)] != sc.bins
        ).any():
            raise RiskError("a scene's bins are not in the merged counts")
        pos[:, j] = np.bincount(coarse[at], weights=sc.positives, minlength=n_bins)
        neg[:, j] = np.bincount(coarse[at], weights=sc.negatives, minlength=n_bins)
    return pos, neg


def binned_replicates(
    pos: np.ndarray, neg: np.ndarray, draws: np.ndarray, fpr_points: Sequence[float] = FPR_POINTS
) -> tuple[np.ndarray, np.ndarray]:
    """AUC ``(B,)`` and TPR at each FPR ``(B, P)`` of the bootstrap replicates that weigh
    scene ``s`` (column ``s`` of :func:`scene_bin_matrix`) by ``draws[:, s]``."""
    if draws.shape[1] != pos.shape[1]:
        raise RiskError(f"draws for {draws.shape[1]} scenes, counts for {pos.shape[1]}")
    return replicate_curves(pos, neg, draws, fpr_points)


def recall_crossing(counts: BinCounts, target: float) -> tuple[int, int] | None:
    """Where the highest threshold keeping ``target`` of the positives lies: ``(i, j)``,
    the ``j``-th highest positive score (1 = the highest) in bin ``counts.bins[i]``;
    None when there is no positive. The threshold is that score (as
    :func:`risk.evaluation.threshold_for_recall` finds it on every row): the bin's
    ``low`` when it holds one value, else the scores of its positives decide
    (:func:`kth_highest`)."""
    if not 0.0 < target <= 1.0:  # 0 keeps nothing: the highest score of any row
        raise RiskError(f"target TPR must be in (0, 1], got {target}")
    n_pos = int(counts.positives.sum())
    if n_pos == 0:
        return None
    # The fewest positives n with n / P >= target, in the exact sweep's arithmetic.
    goal = target - RATE_TOLERANCE
    need = min(n_pos, max(1, math.ceil(n_pos * goal)))
    while need > 1 and (need - 1) / n_pos >= goal:
        need -= 1
    while need < n_pos and need / n_pos < goal:
        need += 1
    from_top = np.cumsum(counts.positives[::-1])
    k = int(np.searchsorted(from_top, need))  # first bin (from the top) reaching it
    i = counts.bins.size - 1 - k
    before = int(from_top[k - 1]) if k else 0
    return i, need - before


def kth_highest(values: np.ndarray, k: int) -> float:
    """The ``k``-th highest of ``values`` (1 = the highest)."""
    v = np.asarray(values, dtype=np.float64)
    if not 1 <= k <= v.size:
        raise RiskError(f"k = {k} outside 1 .. {v.size}")
    return float(np.partition(v, v.size - k)[v.size - k])


def weighted_bin_counts(
    scores: np.ndarray, positive_weights: np.ndarray, negative_weights: np.ndarray
) -> BinCounts:
    """:class:`BinCounts` with float weights instead of counts (rows of weight 0 on both
    sides still mark their bin's score range): the mean curve over situations weighs a
    positive by ``1 / P_s`` and a negative by ``1 / N_s`` (:func:`situation_weights`)."""
    s = np.asarray(scores, dtype=np.float64) + 0.0
    pw = np.asarray(positive_weights, dtype=np.float64)
    nw = np.asarray(negative_weights, dtype=np.float64)
    if not s.shape == pw.shape == nw.shape:
        raise RiskError(f"scores {s.shape} and weights {pw.shape}, {nw.shape} differ in shape")
    return _grouped(score_bins(s), s, pw, nw, s)


def situation_weights(
    situations: np.ndarray, positive: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(A,)`` weights of the mean ROC over situations (:func:`risk.metrics.exact_sweep`):
    ``1 / P_s`` for a positive of situation ``s`` with ``P_s`` positives, ``1 / N_s`` for
    a negative; 0 on the other side."""
    _, sit = np.unique(np.asarray(situations), return_inverse=True)
    pos = np.asarray(positive, dtype=bool)
    p = np.bincount(sit[pos], minlength=sit.max(initial=-1) + 1)
    n = np.bincount(sit[~pos], minlength=sit.max(initial=-1) + 1)
    with np.errstate(divide="ignore"):
        return (
            np.where(pos, 1.0 / np.maximum(p[sit], 1), 0.0),
            np.where(~pos, 1.0 / np.maximum(n[sit], 1), 0.0),
        )


def weighted_auc(counts: BinCounts) -> tuple[float, float]:
    """The AUC of the weighted curve (:func:`weighted_bin_counts`, merged) and the bound
    of its difference from the exact every-distinct-score curve: the weighted pairs in
    mixed bins, ``sum w+_b w-_b / (2 W+ W-)`` (as :func:`binned_roc`'s). NaN without a
    positive or a negative weight."""
    p, n = counts.positives[::-1], counts.negatives[::-1]  # strictest first
    cp, cn = np.cumsum(p), np.cumsum(n)
    if not cp.size or cp[-1] <= 0 or cn[-1] <= 0:
        return math.nan, math.nan
    tpr = np.minimum(cp / cp[-1], 1.0)  # as risk.metrics' mean curve: ends at exactly 1
    fpr = np.minimum(cn / cn[-1], 1.0)
    mixed = counts.low < counts.high
    bound = float(np.sum(counts.positives[mixed] * counts.negatives[mixed]))
    return trapezoid_auc(fpr, tpr), bound / (2.0 * float(cp[-1]) * float(cn[-1]))
