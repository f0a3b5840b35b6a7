"""risk.roc_counts: pooled ROC from per-scene bin counts, against the exact full-rows
computation (risk.evaluation.pooled_roc, the bootstrap of evaluate_scores) and a plain
pairwise oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk.errors import RiskError
from risk.evaluation import (
    FPR_POINTS,
    _replicates,
    bootstrap_weights,
    pooled_roc,
    scene_draws,
    threshold_for_recall,
    tpr_at_fpr,
)
from risk.metrics import SortedScores
from risk.roc_counts import (
    GRID_BITS,
    BinCounts,
    bin_counts,
    binned_replicates,
    binned_roc,
    coarsen,
    kth_highest,
    merge_counts,
    recall_crossing,
    scene_bin_matrix,
    score_bins,
)


def pairwise_auc(scores: np.ndarray, reference: np.ndarray) -> float:
    """Slow and obvious: the share of (positive, negative) pairs ordered right, ties 1/2."""
    ok = (reference >= 0) & ~np.isnan(scores)
    pos = [s for s, r in zip(scores[ok], reference[ok], strict=True) if r == 1]
    neg = [s for s, r in zip(scores[ok], reference[ok], strict=True) if r == 0]
    if not pos or not neg:
        return math.nan
    total = 0.0
    for p in pos:
        for n in neg:
            total += 1.0 if p > n else 0.5 if p == n else 0.0
    return total / (len(pos) * len(neg))


# ---------------------------------------------------------------------- hand cases
def test_distinct_scores_give_the_exact_curve():
    scores = np.array([0.1, 0.2, 0.3, 0.4])
    ref = np.array([0, 1, 0, 1], dtype=np.int8)
    roc = binned_roc(bin_counts(scores, ref))
    assert roc.auc == pytest.approx(0.75)  # 3 of 4 pairs ordered right
    assert roc.auc_error_bound == 0.0 and roc.mixed_bins == 0
    exact = pooled_roc(scores, ref)
    np.testing.assert_array_equal(roc.thresholds, exact.thresholds)
    np.testing.assert_allclose(roc.tpr, exact.tpr)
    np.testing.assert_allclose(roc.fpr, exact.fpr)


def test_unknown_and_nan_are_left_out():
    scores = np.array([0.1, np.nan, 0.3, 0.4, 5.0])
    ref = np.array([0, 1, 0, 1, -1], dtype=np.int8)
    roc = binned_roc(bin_counts(scores, ref))
    assert (roc.n_positive, roc.n_negative) == (1, 2)
    assert roc.auc == pytest.approx(1.0)


def test_a_mixed_bin_is_within_its_stated_bound():
    # 1.0 and 1.0 + 1e-9 share a bin: the binned curve calls the pair a tie (1/2), the
    # exact one orders it (1): the error is the whole bound.
    scores = np.array([1.0, 1.0 + 1e-9])
    ref = np.array([0, 1], dtype=np.int8)
    assert score_bins(scores)[0] == score_bins(scores)[1]
    roc = binned_roc(bin_counts(scores, ref))
    assert pooled_roc(scores, ref).auc == pytest.approx(1.0)
    assert roc.auc == pytest.approx(0.5)
    assert roc.auc_error_bound == pytest.approx(0.5)
    assert roc.mixed_bins == 1


def test_exact_ties_cost_nothing():
    scores = np.array([0.0, 0.0, 0.0, 2.0])
    ref = np.array([1, 0, 0, 1], dtype=np.int8)
    roc = binned_roc(bin_counts(scores, ref))
    assert roc.auc_error_bound == 0.0
    assert roc.auc == pytest.approx(pairwise_auc(scores, ref))  # (0.5 + 0.5 + 1 + 1) / 4


def test_grid_orders_signs_zeros_and_infinities():
    values = np.array([-np.inf, -1e300, -2.0, -1.0, -1e-300, -0.0, 0.0, 5e-324, 1.0, 1e300, np.inf])
    bins = score_bins(values)
    assert (np.diff(bins) >= 0).all()
    assert bins[5] == bins[6]  # -0.0 and 0.0 are one score
    assert bins[3] < bins[8]
    with pytest.raises(RiskError):
        score_bins(np.array([np.nan]))


def test_no_positive_gives_nan():
    roc = binned_roc(bin_counts(np.array([0.1, 0.2]), np.array([0, 0], dtype=np.int8)))
    assert math.isnan(roc.auc) and roc.n_positive == 0


def test_scene_draws_are_the_bootstrap_weights_draws():
    names = np.array(["b", "a", "c", "a"])
    codes, counts = bootstrap_weights(names, n_boot=7, seed=3)
    np.testing.assert_array_equal(counts, scene_draws(3, n_boot=7, seed=3))
    np.testing.assert_array_equal(codes, [1, 0, 2, 0])
    assert (scene_draws(5, n_boot=4, seed=1).sum(axis=1) == 5).all()


# ---------------------------------------------------------------------- properties
score_values = st.one_of(
    st.integers(-5, 5).map(float),  # many exact ties
    st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False, width=32).map(float),
    st.integers(0, 5).map(lambda k: 1.0 + k * 1e-6),  # distinct scores in one bin
)
rows = st.lists(st.tuples(score_values, st.sampled_from([-1, 0, 1]), st.integers(0, 4)),
                min_size=1, max_size=60)  # fmt: skip


def _arrays(data: list[tuple[float, int, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s = np.array([d[0] for d in data], dtype=np.float64)
    r = np.array([d[1] for d in data], dtype=np.int8)
    c = np.array([d[2] for d in data], dtype=np.int64)
    return s, r, c


@settings(max_examples=150, deadline=None)
@given(rows)
def test_binned_auc_is_the_exact_auc_within_the_bound(data):
    s, r, _ = _arrays(data)
    roc = binned_roc(bin_counts(s, r))
    exact = pooled_roc(s, r).auc
    oracle = pairwise_auc(s, r)
    if math.isnan(oracle):
        assert math.isnan(roc.auc)
        return
    assert exact == pytest.approx(oracle, abs=1e-12)
    assert abs(roc.auc - exact) <= roc.auc_error_bound + 1e-12
    if roc.mixed_bins == 0:
        assert roc.auc == pytest.approx(exact, abs=1e-12)
    for f in FPR_POINTS:  # binned points are exact points: never above, within the bound
        full = pooled_roc(s, r)
        e = tpr_at_fpr(full.tpr[::-1], full.fpr[::-1], f)
        b = roc.tpr_at(f)
        assert b <= e + 1e-12
        assert e - b <= roc.tpr_error_bound + 1e-12


@settings(max_examples=100, deadline=None)
@given(rows, st.randoms(use_true_random=False))
def test_merging_scenes_in_any_order_is_counting_them_together(data, rnd):
    s, r, c = _arrays(data)
    whole = bin_counts(s, r)
    parts = [bin_counts(s[c == k], r[c == k]) for k in range(5)]
    rnd.shuffle(parts)
    merged = merge_counts(parts)
    for field in ("bins", "positives", "negatives", "low", "high"):
        np.testing.assert_array_equal(getattr(merged, field), getattr(whole, field))


@settings(max_examples=60, deadline=None)
@given(rows, st.integers(0, 2**16))
def test_bootstrap_from_scene_counts_equals_the_full_rows_bootstrap(data, seed):
    # Integer scores: every distinct score is its own bin, so the coarse bins of the
    # merged counts are the exact bootstrap's groups of distinct scores.
    s, r, c = _arrays(data)
    s = np.round(s) % 7
    n_scenes = 5
    draws = scene_draws(n_scenes, n_boot=20, seed=seed)
    include = r >= 0
    srt = SortedScores.build(np.where(include, s, np.nan), r == 1, c)
    scenes = [bin_counts(s[c == k], r[c == k]) for k in range(n_scenes)]
    merged = merge_counts(scenes)
    if srt.scores.size == 0:
        assert merged.bins.size == 0
        return
    auc_full, tpr_full, _ = _replicates(srt, draws, [], FPR_POINTS)
    pos, neg = scene_bin_matrix(merged, scenes)
    auc, tpr = binned_replicates(pos, neg, draws)
    np.testing.assert_allclose(auc, auc_full, equal_nan=True, atol=1e-12)
    np.testing.assert_allclose(tpr, tpr_full, equal_nan=True, atol=1e-12)


@settings(max_examples=150, deadline=None)
@given(rows, st.sampled_from([1e-9, 0.3, 0.5, 0.95, 1.0]))
def test_the_recall_threshold_from_counts_is_the_exact_one(data, target):
    s, r, _ = _arrays(data)
    counts = bin_counts(s, r)
    exact = threshold_for_recall(s, r, target)
    crossing = recall_crossing(counts, target)
    if crossing is None:
        assert exact == -math.inf
        return
    i, j = crossing
    b = counts.bins[i]
    in_bin = s[(r == 1) & ~np.isnan(s)]
    in_bin = in_bin[score_bins(in_bin) == b]
    assert kth_highest(in_bin, j) == exact
    if counts.low[i] == counts.high[i]:
        assert counts.low[i] == exact


def test_recall_crossing_by_hand():
    # Positives 4, 3, 2, 1 (one per bin): 95 % of 4 needs all 4 -> the lowest, 1.0; 50 %
    # needs 2 -> 3.0.
    counts = bin_counts(np.array([1.0, 2.0, 3.0, 4.0, 0.5]), np.array([1, 1, 1, 1, 0], np.int8))
    assert counts.low[recall_crossing(counts, 0.95)[0]] == 1.0
    assert counts.low[recall_crossing(counts, 0.5)[0]] == 3.0
    assert recall_crossing(bin_counts(np.array([1.0]), np.array([0], np.int8)), 0.5) is None
    assert kth_highest(np.array([3.0, 1.0, 2.0]), 1) == 3.0
    with pytest.raises(RiskError):
        kth_highest(np.array([1.0]), 2)
    with pytest.raises(RiskError):
        recall_crossing(counts, 0.0)


@settings(max_examples=100, deadline=None)
@given(rows, st.integers(2, 8))
def test_a_capped_merge_is_coarser_and_stays_within_its_bound(data, cap):
    s, r, c = _arrays(data)
    scenes = [bin_counts(s[c == k], r[c == k]) for k in range(5)]
    merged = merge_counts(scenes, max_bins=cap)
    assert merged.bins.size <= cap
    whole = bin_counts(s, r)
    assert merged.positives.sum() == whole.positives.sum()
    # the same bins as coarsening the whole at once
    again = coarsen(whole, merged.level)
    np.testing.assert_array_equal(again.bins, merged.bins)
    np.testing.assert_array_equal(again.negatives, merged.negatives)
    np.testing.assert_array_equal(again.bins, np.unique(score_bins(s[(r >= 0)], merged.level)))
    roc = binned_roc(merged)
    exact = pooled_roc(s, r).auc
    if not math.isnan(exact):
        assert abs(roc.auc - exact) <= roc.auc_error_bound + 1e-12
    # scenes of a finer level go onto the merged bins
    pos, neg = scene_bin_matrix(merged, scenes)
    assert pos.sum() == merged.positives.sum() and neg.sum() == merged.negatives.sum()


def test_coarsen_by_hand():
    counts = bin_counts(np.array([1.0, 1.5, 3.0]), np.array([1, 0, 1], np.int8))
    assert counts.bins.size == 3
    one = coarsen(counts, GRID_BITS)  # one bin per power of two: 1.0 and 1.5 together
    assert one.bins.size == 2 and one.low[0] == 1.0 and one.high[0] == 1.5
    assert (list(one.positives), list(one.negatives)) == ([1, 1], [1, 0])
    with pytest.raises(RiskError):
        coarsen(one, 0)


def test_scene_bins_must_be_in_the_merge():
    a = bin_counts(np.array([1.0]), np.array([1], dtype=np.int8))
    b = bin_counts(np.array([2.0]), np.array([0], dtype=np.int8))
    with pytest.raises(RiskError):
        scene_bin_matrix(a, [b])
    assert BinCounts.empty().nbytes == 0


# ---------------------------------------------------------------- situation-mean curve
def _situation_auc(scores, situations, positive, max_bins=None):
    from risk.roc_counts import situation_weights, weighted_auc, weighted_bin_counts

    pw, nw = situation_weights(situations, positive)
    counts = merge_counts([weighted_bin_counts(scores, pw, nw)], max_bins)
    return weighted_auc(counts)


def test_situation_mean_auc_by_hand():
    # Situation 0 ranks its positive first (0.9 > 0.1), situation 1 last (0.2 < 0.8).
    # Mean curve from the strictest threshold: (fpr, tpr) = (0, .5), (.5, .5), (.5, 1),
    # (1, 1): area 0.25 + 0.5 = 0.75; one score per bin, so no bound.
    scores = np.array([0.9, 0.1, 0.2, 0.8])
    auc, bound = _situation_auc(scores, np.array([0, 0, 1, 1]), np.array([1, 0, 1, 0], bool))
    assert auc == pytest.approx(0.75, abs=1e-15) and bound == 0.0
    # No negative anywhere: undefined.
    auc, _ = _situation_auc(scores, np.zeros(4, int), np.ones(4, bool))
    assert math.isnan(auc)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.booleans(), st.sampled_from([None, 4]))
def test_situation_mean_auc_matches_the_exact_sweep_within_its_bound(seed, few, max_bins):
    from risk.metrics import exact_sweep

    rng = np.random.default_rng(seed)
    n = int(rng.integers(4, 80))
    scores = rng.integers(0, 5, n).astype(float) if few else rng.random(n)
    situations = rng.integers(0, 6, n)
    positive = rng.random(n) < 0.4
    if positive.all() or not positive.any():
        positive[0] = not positive[0]
    auc, bound = _situation_auc(scores, situations, positive, max_bins)
    _, sit = np.unique(situations, return_inverse=True)
    exact = exact_sweep(scores, sit.astype(np.int64), positive).auc
    if math.isnan(exact):
        assert math.isnan(auc)
    else:
        assert abs(auc - exact) <= bound + 1e-12
        if few and max_bins is None:
            assert bound == 0.0
