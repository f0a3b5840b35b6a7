"""Exact medians and quantiles of values that arrive in pieces (scene by scene), without
holding them all: two passes over the pieces.

1. **Counts.** Each piece's values are counted on the fixed grid of
   :mod:`risk.roc_counts` (:func:`value_counts`: every value a "positive"); counts of
   pieces add in any order (:func:`risk.roc_counts.merge_counts`, bounded by its
   ``max_bins``). The merged counts tell which grid bin holds each order statistic a
   quantile needs (:func:`locate`), and its rank inside the bin.
2. **Values.** A second pass keeps only the values in those bins (:func:`in_bins`); the
   order statistics are picked from them (:func:`pick`).

From the order statistics, :func:`median_of` and :func:`quantile_of` compute what
``np.median`` and ``np.quantile`` (linear) compute from all the values: the same
neighbours, combined by numpy itself, so the result is bit-identical (tested against
numpy). Only NaN-free values are counted (the caller leaves NaN out).

Memory: the merged counts (at most ``max_bins`` bins) and the values of the few bins
that hold the order statistics (a bin is 2**-12 of its value wide at the finest level).

Pure numpy; no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from risk.errors import RiskError
from risk.roc_counts import MAX_CURVE_BINS, BinCounts, bin_counts, merge_counts, score_bins


def value_counts(values: np.ndarray) -> BinCounts:
    """The grid counts of ``values`` (no NaN), all as positives."""
    v = np.asarray(values, dtype=np.float64)
    return bin_counts(v, np.ones(v.shape, dtype=bool))


def median_ranks(n: int) -> tuple[int, ...]:
    """The 0-based ranks (ascending) ``np.median`` reads among ``n`` values: the middle
    one, or the middle two."""
    if n <= 0:
        return ()
    return (n // 2,) if n % 2 else (n // 2 - 1, n // 2)


def quantile_ranks(n: int, q: float) -> tuple[int, int, float]:
    """``(lower rank, upper rank, weight)`` that ``np.quantile(values, q)`` (method
    ``linear``) interpolates between among ``n`` sorted values: its virtual index
    ``(n - 1) * q``, past the last value the largest."""
    if n <= 0:
        raise RiskError("a quantile of no value")
    virtual = (n - 1) * np.float64(q)
    if virtual >= n - 1:
        return n - 1, n - 1, 0.0
    lower = int(np.floor(virtual))
    return lower, lower + 1, float(virtual - lower)


def locate(counts: BinCounts, ranks: Sequence[int]) -> dict[int, tuple[int, int]]:
    """Per rank (0-based, ascending) among the counted values: ``(grid bin, rank within
    that bin)``."""
    total = np.cumsum(counts.positives)
    out = {}
    for k in sorted(set(ranks)):
        if not 0 <= k < (int(total[-1]) if total.size else 0):
            raise RiskError(f"rank {k} outside the {int(total[-1]) if total.size else 0} values")
        i = int(np.searchsorted(total, k + 1))
        out[k] = (int(counts.bins[i]), k - (int(total[i - 1]) if i else 0))
    return out


def in_bins(values: np.ndarray, bins: np.ndarray, level: int) -> np.ndarray:
    """The values (no NaN) that fall in grid ``bins`` at ``level``."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0 or bins.size == 0:
        return v[:0]
    return v[np.isin(score_bins(v, level), bins)]


def pick(kept: np.ndarray, located: Mapping[int, tuple[int, int]], level: int) -> dict[int, float]:
    """The order statistics: per rank, the value at its rank within its bin among
    ``kept`` (every value of the located bins, from :func:`in_bins`)."""
    v = np.asarray(kept, dtype=np.float64)
    bins = score_bins(v, level)
    out = {}
    for rank, (b, k) in located.items():
        inside = np.sort(v[bins == b])
        if k >= inside.size:
            raise RiskError(f"bin {b} holds {inside.size} values, not the {k + 1} counted")
        out[rank] = float(inside[k])
    return out


def median_of(n: int, stats: Mapping[int, float]) -> float:
    """``np.median`` of the ``n`` values whose order statistics :func:`median_ranks`
    names are ``stats``."""
    middle = np.array([stats[k] for k in median_ranks(n)], dtype=np.float64)
    return float(np.median(middle))


def quantile_of(n: int, q: float, stats: Mapping[int, float]) -> float:
    """``np.quantile(values, q)`` (linear) of the ``n`` values whose order statistics
    :func:`quantile_ranks` names are ``stats``: numpy interpolates the same two
    neighbours with the same weight (a two-value array at quantile ``weight``)."""
    lower, upper, weight = quantile_ranks(n, q)
    pair = np.array([stats[lower], stats[upper]], dtype=np.float64)
    return float(np.quantile(pair, weight))


class OrderStatistics:
    """Order statistics of values given in pieces, exact, in two passes: :meth:`count`
    every piece, :meth:`want` the ranks, :meth:`keep` every piece again (the same values,
    in any order), then :meth:`value` / :meth:`median` / :meth:`quantile`."""

    #: Pieces' counts merged at once (fewer sorts of the merged counts).
    BATCH = 32

    def __init__(self, max_bins: int = MAX_CURVE_BINS) -> None:
        self.max_bins = max_bins
        self.n = 0
        self._pending: list[BinCounts] = []
        self._counts: BinCounts | None = None
        self._located: dict[int, tuple[int, int]] = {}
        self._bins = np.empty(0, np.int64)
        self._kept: list[np.ndarray] = []
        self._stats: dict[int, float] | None = None

    def count(self, values: np.ndarray) -> None:
        """Pass 1: a piece's values (no NaN)."""
        v = np.asarray(values, dtype=np.float64)
        if v.size == 0:
            return
        self.n += int(v.size)
        self._pending.append(value_counts(v))
        if len(self._pending) >= self.BATCH:
            self._merge()

    def _merge(self) -> None:
        given = [self._counts] if self._counts is not None else []
        self._counts = merge_counts([*given, *self._pending], max_bins=self.max_bins)
        self._pending = []

    def want(self, ranks: Sequence[int]) -> None:
        """End of pass 1: the 0-based ranks (ascending order) to find."""
        self._merge()
        assert self._counts is not None
        self._located = locate(self._counts, ranks) if self.n else {}
        self._bins = np.unique([b for b, _ in self._located.values()]).astype(np.int64)

    def keep(self, values: np.ndarray) -> None:
        """Pass 2: a piece's values again; only those in the wanted ranks' bins stay."""
        if self._counts is not None and self._bins.size:
            self._kept.append(in_bins(values, self._bins, self._counts.level))

    def value(self, rank: int) -> float:
        """The value at ``rank`` (one of :meth:`want`'s)."""
        if self._stats is None:
            assert self._counts is not None
            kept = np.concatenate(self._kept) if self._kept else np.empty(0)
            self._stats = pick(kept, self._located, self._counts.level)
            self._kept = []
        return self._stats[rank]

    def median(self) -> float | None:
        """``np.median`` of the values (None when there is none); wants
        :func:`median_ranks`."""
        return (
            median_of(self.n, {k: self.value(k) for k in median_ranks(self.n)}) if self.n else None
        )

    def quantile(self, q: float) -> float | None:
        """``np.quantile(values, q)`` (None when there is none); wants
        :func:`quantile_ranks`."""
        if not self.n:
            return None
        lower, upper, _ = quantile_ranks(self.n, q)
        return quantile_of(self.n, q, {lower: self.value(lower), upper: self.value(upper)})
