"""ROC metrics: confusion counts, the threshold sweep, undefined cases, AUC."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from roc_oracle import roc_curve

from risk import RiskError
from risk.metrics import confusion_counts, exact_sweep, threshold_for_tpr

NAN = math.nan


def test_confusion_counts_by_hand():
    scores = np.array([NAN, 0.9, 0.5, 0.5, 0.1, 0.7])
    base = np.array([True, True, False, True, False, False])  # the NaN entry is ignored
    c = confusion_counts(scores, base, np.array([0.0, 0.5, 0.6, 1.0]))
    # positives 0.9, 0.5; negatives 0.5, 0.1, 0.7; keep score >= t
    assert list(c.tp) == [2, 2, 1, 0]
    assert list(c.fn) == [0, 0, 1, 2]
    assert list(c.fp) == [3, 2, 1, 0]
    assert list(c.tn) == [0, 1, 2, 3]
    assert c.tp.dtype == np.int64


def test_roc_curve_by_hand():
    scores = [np.array([NAN, 0.9, 0.5, 0.1]), np.array([0.3, NAN, 0.8, 0.6])]
    base = [np.array([False, True, False, False]), np.array([False, False, True, False])]
    r = roc_curve(scores, base)
    np.testing.assert_array_equal(r.thresholds, [0.1, 0.3, 0.5, 0.6, 0.8, 0.9])  # observed values
    # situation 0: one positive (0.9); negatives 0.5, 0.1
    np.testing.assert_allclose(r.tpr[0], [1, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(r.fpr[0], [1, 0.5, 0.5, 0, 0, 0])
    # situation 1: positive 0.8; negatives 0.3, 0.6
    np.testing.assert_allclose(r.tpr[1], [1, 1, 1, 1, 1, 0])
    np.testing.assert_allclose(r.fpr[1], [1, 1, 0.5, 0.5, 0, 0])
    np.testing.assert_allclose(r.mean_tpr, [1, 1, 1, 1, 1, 0.5])
    np.testing.assert_allclose(r.std_tpr, [0, 0, 0, 0, 0, 0.5])
    np.testing.assert_array_equal(r.kept[0], [3, 2, 2, 1, 1, 1])
    assert r.auc == pytest.approx(1.0)  # every positive outranks every negative
    assert (r.n_situations, r.n_no_positive, r.n_no_negative) == (2, 0, 0)
    assert threshold_for_tpr(r, 1.0) == 0.8
    assert threshold_for_tpr(r, 0.5) == 0.9


def test_undefined_situations_are_counted_not_averaged_as_zero():
    scores = [np.array([0.9, 0.2]), np.array([0.4, 0.3]), np.array([0.6, 0.5])]
    base = [np.array([True, False]), np.array([False, False]), np.array([True, True])]
    r = roc_curve(scores, base, thresholds=np.array([0.45]))
    assert (r.n_no_positive, r.n_no_negative) == (1, 1)
    assert np.isnan(r.tpr[1, 0]) and np.isnan(r.fpr[2, 0])
    assert r.mean_tpr[0] == pytest.approx(1.0)  # (1 + 1) / 2, not (1 + 0 + 1) / 3
    assert r.mean_fpr[0] == pytest.approx(0.0)  # situation 1 keeps no negative at 0.45


def test_auc_of_reversed_and_random_rankings():
    base = [np.array([True, True, False, False])]
    assert roc_curve([np.array([0.1, 0.2, 0.8, 0.9])], base).auc == pytest.approx(0.0)
    assert roc_curve([np.array([0.5, 0.5, 0.5, 0.5])], base).auc == pytest.approx(0.5)
    rng = np.random.default_rng(0)
    s = [rng.random(200) for _ in range(20)]
    b = [rng.random(200) < 0.3 for _ in range(20)]
    assert roc_curve(s, b).auc == pytest.approx(0.5, abs=0.03)


def test_auc_is_nan_when_no_situation_has_positives():
    r = roc_curve([np.array([0.2, 0.4])], [np.array([False, False])])
    assert math.isnan(r.auc) and np.isnan(r.mean_tpr).all() and np.isnan(r.std_tpr).all()
    with pytest.raises(RiskError, match="undefined"):
        threshold_for_tpr(r, 1.0)


def test_threshold_for_tpr_errors():
    r = roc_curve([np.array([0.9, 0.2])], [np.array([True, False])], thresholds=np.array([0.95]))
    with pytest.raises(RiskError, match="no threshold reaches"):
        threshold_for_tpr(r, 1.0)
    with pytest.raises(RiskError, match=r"\[0, 1\]"):
        threshold_for_tpr(r, 1.5)


def test_exact_sweep_by_hand():
    """The by-hand case above, through the product's sweep (agent-frames of both
    situations in one array)."""
    scores = np.array([NAN, 0.9, 0.5, 0.1, 0.3, NAN, 0.8, 0.6])
    situation = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    base = np.array([False, True, False, False, False, False, True, False])
    sw = exact_sweep(scores, situation, base)
    np.testing.assert_array_equal(sw.thresholds, [0.1, 0.3, 0.5, 0.6, 0.8, 0.9])
    np.testing.assert_allclose(sw.mean_tpr, [1, 1, 1, 1, 1, 0.5])
    np.testing.assert_allclose(sw.mean_fpr, [1, 0.75, 0.5, 0.25, 0, 0])
    np.testing.assert_allclose(sw.std_tpr, [0, 0, 0, 0, 0, 0.5])
    np.testing.assert_allclose(sw.mean_kept, [3, 2.5, 2, 1.5, 1, 0.5])
    assert sw.auc == pytest.approx(1.0)
    assert (sw.n_situations, sw.n_no_positive, sw.n_no_negative) == (2, 0, 0)
    assert threshold_for_tpr(sw, 1.0) == 0.8
    assert threshold_for_tpr(sw, 0.5) == 0.9


def test_exact_sweep_bad_inputs():
    with pytest.raises(RiskError, match="shape"):
        exact_sweep(np.array([0.1, 0.2]), np.array([0]), np.array([True, False]))
    with pytest.raises(RiskError, match="boolean"):
        exact_sweep(np.array([0.1]), np.array([0]), np.array([1]))
    with pytest.raises(RiskError, match="every score is NaN"):
        exact_sweep(np.array([NAN]), np.array([0]), np.array([False]))


def test_bad_inputs():
    with pytest.raises(RiskError, match="one of each"):
        roc_curve([np.array([0.1])], [])
    with pytest.raises(RiskError, match="no situations"):
        roc_curve([], [])
    with pytest.raises(RiskError, match="shape"):
        roc_curve([np.array([0.1, 0.2])], [np.array([True])])
    with pytest.raises(RiskError, match="boolean"):
        roc_curve([np.array([0.1])], [np.array([1])])
    with pytest.raises(RiskError, match="no scores"):
        roc_curve([np.array([NAN])], [np.array([False])])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1), st.booleans()), min_size=1, max_size=40))
def test_exact_sweep_matches_a_direct_count(rows):
    s = np.array([r[0] for r in rows])
    b = np.array([r[1] for r in rows])
    r = roc_curve([s], [b])
    for k, t in enumerate(r.thresholds):
        keep = s >= t
        if b.any():
            assert r.tpr[0, k] == pytest.approx((keep & b).sum() / b.sum())
        if (~b).any():
            assert r.fpr[0, k] == pytest.approx((keep & ~b).sum() / (~b).sum())
    # the lowest threshold keeps everything
    assert r.kept[0, 0] == s.size


def test_one_auc_for_single_curves_and_rows():
    """Hand-computed: the curve (0, 0) -> (0, 0.5) -> (0.5, 1) -> (1, 1) has area 0.875."""
    from risk.metrics import trapezoid_auc, trapezoid_auc_rows

    fpr, tpr = np.array([0.0, 0.5]), np.array([0.5, 1.0])
    assert trapezoid_auc(fpr, tpr) == 0.875
    rows = trapezoid_auc_rows(
        np.array([[0.0, 0.5], [1.0, 1.0]]), np.array([[0.5, 1.0], [1.0, 1.0]])
    )
    assert rows.tolist() == [0.875, 0.5]  # the second: the chance diagonal
    assert np.isnan(trapezoid_auc(np.array([np.nan]), np.array([0.5])))
    assert np.isnan(trapezoid_auc(np.zeros(0), np.zeros(0)))


def test_the_sweep_and_the_pooled_evaluation_share_one_sort():
    """One situation: the mean sweep is the pooled curve (same thresholds, rates, AUC)."""
    from risk.evaluation import pooled_roc

    rng = np.random.default_rng(3)
    scores = np.round(rng.random(200), 2)  # ties
    positive = rng.random(200) < 0.3
    sweep = exact_sweep(scores, np.zeros(200, dtype=np.int64), positive)
    pooled = pooled_roc(scores, positive)
    assert np.array_equal(sweep.thresholds, pooled.thresholds)
    assert np.allclose(sweep.mean_tpr, pooled.tpr) and np.allclose(sweep.mean_fpr, pooled.fpr)
    assert sweep.auc == pytest.approx(pooled.auc, abs=1e-12)


@pytest.mark.exactness
@pytest.mark.parametrize("exp_ulps", [0, 1])
def test_roc_points_of_kernel_and_numpy_risks_agree_except_ties(exp_ulps):
    """Across code paths: the sweep of the kernel's risks and of the numpy modules'
    (with numpy's own exp, or one moved by up to a float: another CPU's, simulated) over
    20 frames. Thresholds within the contract's ulps and every ROC point (TPR, FPR, agents
    kept, AUC) exactly the same, after leaving out by name the agent-frames whose place
    may differ: a score within the tolerance of another (tests/exactness.py,
    score_ties) or a survival risk within it of the baseline threshold."""
    from exactness import FLOOR, kernel_ulps, near, numpy_exp_off_by, score_ties, ulp_distance
    from frames import scattered_frame

    from risk import BASELINE_THRESHOLD, evaluate
    from risk.registry import evaluate_numpy

    frames = [scattered_frame(seed) for seed in range(20)]
    rng = np.random.default_rng(exp_ulps)
    fast = [evaluate(f) for f in frames]
    with numpy_exp_off_by(exp_ulps, rng):
        slow = [evaluate_numpy(f) for f in frames]
    situation = np.concatenate([np.full(f.n_agents, i) for i, f in enumerate(frames)])
    surv_k, surv_n = (np.concatenate([r["survival"] for r in side]) for side in (fast, slow))
    tol_s = kernel_ulps("survival")
    for model in ("path_distance", "trajectory_distance", "circles", "gaussian"):
        k, n = (np.concatenate([r[model] for r in side]) for side in (fast, slow))
        ties = score_ties(k, n, kernel_ulps(model)) | near(surv_k, BASELINE_THRESHOLD, tol_s)
        agents = int((~np.isnan(k)).sum())
        # Scores below the contract's floor (1e-300: Gaussians of far agents, subnormal or
        # 0) are all within its tolerance of each other: one block of ties, left out.
        above = ties & (k >= FLOOR)
        assert above.sum() <= agents // 20, f"{model}: {above.sum()} of {agents} agent-frames tie"
        a = exact_sweep(np.where(ties, NAN, k), situation, surv_k >= BASELINE_THRESHOLD)
        b = exact_sweep(np.where(ties, NAN, n), situation, surv_n >= BASELINE_THRESHOLD)
        assert a.thresholds.size == b.thresholds.size > agents // 3, model
        assert ulp_distance(a.thresholds, b.thresholds).max() <= kernel_ulps(model), model
        for name in ("mean_tpr", "mean_fpr", "std_tpr", "mean_kept"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=model)
        assert (a.auc, a.n_no_positive, a.n_no_negative) == (
            b.auc,
            b.n_no_positive,
            b.n_no_negative,
        )
