"""The mean-over-situations ROC sweep (:func:`risk.metrics.exact_sweep`) from per-scene
pieces that add up, for drivers that never hold the corpus's rows (issue 38).

:func:`risk.metrics.exact_sweep` is a cumulative sum, over the agent-frames sorted by
descending score, of three per-row weights that depend only on the row's own situation:
``1 / P_s`` for a positive (the mean TPR), ``1 / N_s`` for a negative (the mean FPR) and
``(2 k + 1) / P_s**2`` for the ``k``-th positive of its situation (the mean of TPR**2, so
the std). Situations lie inside one scene, so each scene's rows can be reduced to these
weights per bin of :mod:`risk.roc_counts`' fixed score grid (:func:`sweep_counts`), and
the scenes' bins added in any order (:func:`merge_sweeps`).

**Binned curve** (:func:`binned_sweep`): one point per grid bin, at the bin's lowest score.
Each such point is a point of the exact curve (every row of the bin and above has a score
``>=`` that threshold), so the mean TPR, FPR, std of TPR and kept agents there equal the
exact sweep's at that threshold (to rounding: sums in another order); the exact curve has
further points inside bins holding several distinct scores (*mixed* bins). The AUC of the
binned points differs from the exact one by at most ``auc_error_bound``
(:func:`risk.roc_counts.weighted_auc`).

**Exact points inside a bin** (:func:`points_in_bin`): the rows of the bin (a second pass
over the parts, :func:`rows_in_bins`) with the merged weights of every bin above give the
exact curve at each distinct score of the bin; the operating thresholds are found there
(:func:`threshold_for_mean_tpr`, :func:`youden_threshold`, :func:`tpr_above_lowest`);
the rows are kept merged per distinct score (:func:`collapse`).

Pure numpy; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from risk.errors import RiskError
from risk.metrics import VAR_ROUNDING, Sweep, trapezoid_auc
from risk.roc_counts import BinCounts, merge_counts, score_bins, weighted_auc, weighted_bin_counts


@dataclass(frozen=True, eq=False)
class SweepCounts:
    """A set of situations' mean-sweep weights per grid bin (the three share their bins):
    ``rates`` (positives: sum of ``1 / P_s``, negatives: sum of ``1 / N_s``), ``squares``
    (positives: sum of ``(2 k + 1) / P_s**2``) and ``counts`` (positive and negative
    rows). ``positive_situations``, ``negative_situations``: situations with a positive /
    a negative row (non-NaN scores)."""

    rates: BinCounts
    squares: BinCounts
    counts: BinCounts
    positive_situations: int
    negative_situations: int

    @property
    def nbytes(self) -> int:
        return self.rates.nbytes + self.squares.nbytes + self.counts.nbytes


@dataclass(frozen=True, eq=False)
class SweepRows:
    """Rows (non-NaN scores) with their mean-sweep weights: ``scores``, ``tpr``, ``fpr``,
    ``square``, ``positive`` ``(A,)``."""

    scores: np.ndarray
    tpr: np.ndarray
    fpr: np.ndarray
    square: np.ndarray
    positive: np.ndarray

    def take(self, mask: np.ndarray) -> SweepRows:
        return SweepRows(*(a[mask] for a in (self.scores, self.tpr, self.fpr, self.square,
                                             self.positive)))  # fmt: skip

    @staticmethod
    def concat(parts: Sequence[SweepRows]) -> SweepRows:
        if not parts:
            f = np.empty(0)
            return SweepRows(f, f, f, f, np.empty(0, dtype=bool))
        return SweepRows(
            *(np.concatenate([getattr(p, k) for p in parts])
              for k in ("scores", "tpr", "fpr", "square", "positive"))
        )  # fmt: skip


def collapse(rows: SweepRows) -> SweepRows:
    """The rows merged per distinct score, their weights summed (``positive``: the score
    has a positive row): the exact points need no more, and ties (a mass of zero scores)
    then cost one entry."""
    if rows.scores.size == 0:
        return rows
    values, code = np.unique(rows.scores, return_inverse=True)
    n = values.size
    return SweepRows(
        values,
        np.bincount(code, weights=rows.tpr, minlength=n),
        np.bincount(code, weights=rows.fpr, minlength=n),
        np.bincount(code, weights=rows.square, minlength=n),
        np.bincount(code, weights=rows.positive, minlength=n) > 0,
    )


def sweep_rows(scores: np.ndarray, situation: np.ndarray, positive: np.ndarray) -> SweepRows:
    """The weights of ``scores (A,)`` (NaN: not an agent, left out) of situations
    ``situation (A,)`` (any integer codes; every situation's rows must all be here)
    against ``positive (A,)`` bool, as :func:`risk.metrics.exact_sweep` weighs them."""
    s = np.asarray(scores, dtype=np.float64)
    sit = np.asarray(situation)
    pos = np.asarray(positive, dtype=bool)
    if not s.shape == sit.shape == pos.shape or s.ndim != 1:
        raise RiskError(f"scores {s.shape}, situation {sit.shape}, positive {pos.shape}")
    ok = ~np.isnan(s)
    s, pos = s[ok] + 0.0, pos[ok]
    _, code = np.unique(sit[ok], return_inverse=True)
    n_sit = int(code.max()) + 1 if code.size else 0
    p = np.bincount(code[pos], minlength=n_sit)
    n = np.bincount(code[~pos], minlength=n_sit)
    # k: positives of the same situation with a higher score (ties: any order; the sum
    # over a run of ties is the same, and ties share a grid bin)
    order = np.lexsort((-s, code))
    ranked = pos[order].astype(np.int64)
    before = np.cumsum(ranked) - ranked
    first = np.r_[0, np.flatnonzero(np.diff(code[order])) + 1] if code.size else np.empty(0, int)
    start = np.repeat(before[first], np.diff(np.r_[first, code.size]))
    k = np.empty(code.size, dtype=np.int64)
    k[order] = before - start
    pc, nc = np.maximum(p[code], 1).astype(np.float64), np.maximum(n[code], 1).astype(np.float64)
    return SweepRows(
        scores=s,
        tpr=np.where(pos, 1.0 / pc, 0.0),
        fpr=np.where(~pos, 1.0 / nc, 0.0),
        square=np.where(pos, (2.0 * k + 1.0) / pc**2, 0.0),
        positive=pos,
    )


def sweep_counts(
    rows: SweepRows, positive_situations: int, negative_situations: int
) -> SweepCounts:
    """The rows' weights per grid bin."""
    zero = np.zeros(rows.scores.size)
    pos = rows.positive.astype(np.float64)
    return SweepCounts(
        weighted_bin_counts(rows.scores, rows.tpr, rows.fpr),
        weighted_bin_counts(rows.scores, rows.square, zero),
        weighted_bin_counts(rows.scores, pos, 1.0 - pos),
        positive_situations,
        negative_situations,
    )


def situation_counts(
    situation: np.ndarray, positive: np.ndarray, scores: np.ndarray
) -> tuple[int, int]:
    """Situations with a positive and with a negative row (non-NaN scores)."""
    ok = ~np.isnan(np.asarray(scores, dtype=np.float64))
    sit, pos = np.asarray(situation)[ok], np.asarray(positive, dtype=bool)[ok]
    return int(np.unique(sit[pos]).size), int(np.unique(sit[~pos]).size)


def merge_sweeps(parts: Sequence[SweepCounts], max_bins: int | None = None) -> SweepCounts:
    """The sum of ``parts`` (any order; :func:`risk.roc_counts.merge_counts` per channel,
    the same bins in each)."""
    rates = merge_counts([p.rates for p in parts], max_bins)
    squares = merge_counts([p.squares for p in parts], max_bins)
    counts = merge_counts([p.counts for p in parts], max_bins)
    if not (np.array_equal(rates.bins, squares.bins) and np.array_equal(rates.bins, counts.bins)):
        raise RiskError("merged sweep channels have different bins")
    return SweepCounts(
        rates, squares, counts, sum(p.positive_situations for p in parts),
        sum(p.negative_situations for p in parts),
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class BinnedSweep:
    """The binned mean curve (``sweep``: a :class:`risk.metrics.Sweep` at each bin's
    lowest score, ascending), its AUC's bound and the cumulative weights (strictest
    first) that :func:`points_in_bin` continues."""

    sweep: Sweep
    auc_error_bound: float
    mixed_bins: int
    totals: tuple[float, float, float]  # sum of tpr, fpr weights, of tpr weights (squares' norm)


def _mean(cum: np.ndarray, total: float) -> np.ndarray:
    """As :func:`risk.metrics.exact_sweep`'s means: cumulative over total, at most 1."""
    if cum.size == 0 or total <= 0:
        return np.full(cum.size, np.nan)
    return np.minimum(cum / total, 1.0)


def _std(mean_sq: np.ndarray, mean: np.ndarray) -> np.ndarray:
    var = mean_sq - mean**2
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.where(var < VAR_ROUNDING, 0.0, var))


def binned_sweep(merged: SweepCounts, n_situations: int) -> BinnedSweep:
    """The curve of merged counts over ``n_situations`` situations with agents."""
    rates, counts = merged.rates, merged.counts
    desc = slice(None, None, -1)
    cp, cn = np.cumsum(rates.positives[desc]), np.cumsum(rates.negatives[desc])
    csq = np.cumsum(merged.squares.positives[desc])
    ck = np.cumsum(counts.positives[desc] + counts.negatives[desc])
    tot_p = float(cp[-1]) if cp.size else 0.0
    tot_n = float(cn[-1]) if cn.size else 0.0
    tpr, fpr, sq = _mean(cp, tot_p), _mean(cn, tot_n), _mean(csq, tot_p)
    std = _std(sq, tpr)
    _, bound = weighted_auc(rates)
    sweep = Sweep(
        thresholds=rates.low.copy(),
        mean_tpr=tpr[desc],
        mean_fpr=fpr[desc],
        std_tpr=std[desc],
        mean_kept=(ck / max(n_situations, 1))[desc],
        auc=trapezoid_auc(fpr, tpr),
        n_situations=n_situations,
        n_no_positive=n_situations - merged.positive_situations,
        n_no_negative=n_situations - merged.negative_situations,
    )
    mixed = int((rates.low < rates.high).sum())
    return BinnedSweep(sweep, bound, mixed, (tot_p, tot_n, tot_p))


def rows_in_bins(rows: SweepRows, merged: SweepCounts, bins: Sequence[int]) -> SweepRows:
    """The rows that fall in the merged grid's bins ``bins`` (indices into its arrays)."""
    wanted = merged.rates.bins[np.asarray(list(bins), dtype=np.int64)]
    return rows.take(np.isin(score_bins(rows.scores, merged.rates.level), wanted))


@dataclass(frozen=True, eq=False)
class BinPoints:
    """The exact curve at every distinct score of one bin: ``thresholds`` descending,
    ``mean_tpr``, ``mean_fpr``, ``std_tpr``."""

    thresholds: np.ndarray
    mean_tpr: np.ndarray
    mean_fpr: np.ndarray
    std_tpr: np.ndarray


def points_in_bin(
    binned: BinnedSweep, merged: SweepCounts, index: int, rows: SweepRows
) -> BinPoints:
    """The exact points of bin ``index`` of ``merged`` from its rows (every row of the
    corpus in that bin, :func:`rows_in_bins`) and the merged weights of the bins above."""
    bins = score_bins(rows.scores, merged.rates.level)
    r = rows.take(bins == merged.rates.bins[index])
    order = np.argsort(-r.scores, kind="stable")
    s = r.scores[order]
    last = np.r_[np.flatnonzero(s[1:] != s[:-1]), s.size - 1] if s.size else np.empty(0, int)
    above = slice(index + 1, None)
    tot_p, tot_n, _ = binned.totals
    cp = float(merged.rates.positives[above].sum()) + np.cumsum(r.tpr[order])[last]
    cn = float(merged.rates.negatives[above].sum()) + np.cumsum(r.fpr[order])[last]
    csq = float(merged.squares.positives[above].sum()) + np.cumsum(r.square[order])[last]
    tpr, fpr = _mean(cp, tot_p), _mean(cn, tot_n)
    return BinPoints(s[last], tpr, fpr, _std(_mean(csq, tot_p), tpr))


def crossing_bin(binned: BinnedSweep, target: float, tolerance: float) -> int | None:
    """The bin of the highest threshold whose mean TPR reaches ``target``: the highest
    bin whose lowest score reaches it (None: none does)."""
    ok = np.flatnonzero(binned.sweep.mean_tpr >= target - tolerance)
    return int(ok.max()) if ok.size else None


def threshold_for_mean_tpr(
    binned: BinnedSweep,
    index: int | None,
    points: BinPoints | None,
    target: float,
    tolerance: float,
) -> float:
    """The highest threshold at which the mean TPR reaches ``target`` (as
    :func:`replay.analysis.stats.compute`'s), from the crossing bin ``index`` and its
    exact points (None when the bin holds one score)."""
    if index is None:
        return -math.inf
    if points is not None:
        ok = points.mean_tpr >= target - tolerance
        if ok.any():
            return float(points.thresholds[ok].max())
    return float(binned.sweep.thresholds[index])


def youden_candidates(binned: BinnedSweep, merged: SweepCounts, tolerance: float) -> list[int]:
    """Mixed bins where a point could beat the binned curve's best mean TPR - mean FPR:
    inside bin ``b`` the TPR is at most its lowest score's, the FPR at least that of
    the bins above."""
    sw = binned.sweep
    j = np.nan_to_num(sw.mean_tpr - sw.mean_fpr, nan=-np.inf)
    if not j.size:
        return []
    tot_n = binned.totals[1]
    cn_desc = np.cumsum(merged.rates.negatives[::-1])
    fpr_above = (np.r_[0.0, cn_desc[:-1]] / tot_n)[::-1] if tot_n > 0 else np.full(j.size, np.nan)
    upper = np.nan_to_num(sw.mean_tpr - fpr_above, nan=-np.inf)
    mixed = merged.rates.low < merged.rates.high
    return [int(b) for b in np.flatnonzero(mixed & (upper >= j.max() - tolerance))]


def youden_threshold(
    binned: BinnedSweep, points: Mapping[int, BinPoints], tolerance: float
) -> float:
    """The threshold of the largest mean TPR - mean FPR over the binned points and the
    exact points of ``points``' bins (values within ``tolerance`` of the largest tie;
    the highest of ties keeps the fewest agents)."""
    sw = binned.sweep
    thr = [sw.thresholds] + [p.thresholds for p in points.values()]
    j = [sw.mean_tpr - sw.mean_fpr] + [p.mean_tpr - p.mean_fpr for p in points.values()]
    t, v = np.concatenate(thr), np.nan_to_num(np.concatenate(j), nan=-np.inf)
    return float(t[v >= v.max() - tolerance].max())


def tpr_above_lowest(binned: BinnedSweep, points: BinPoints | None) -> float:
    """The mean TPR at the second lowest distinct score (the highest mean TPR at a
    threshold above the lowest score); ``points``: the lowest bin's, when mixed."""
    sw = binned.sweep
    if points is not None:  # the lowest bin holds two scores or more
        tpr = points.mean_tpr[-2]
    elif sw.thresholds.size > 1:
        tpr = sw.mean_tpr[1]
    else:
        return math.nan
    return float(tpr) if np.isfinite(tpr) else math.nan
