"""Calibration maths: hand-computed thresholds and the properties the cascade relies on."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from risk.calibration import (
    THRESHOLD_MARGIN,
    CalibrationError,
    calibrate_thresholds,
    cascade_keep,
    highest_threshold,
    tier_thresholds_for_counts,
)

MODELS2 = ("path_distance", "gaussian")


def test_highest_threshold_hand_computed():
    r = np.array([0.5, 0.2, 0.9, 0.2])
    assert highest_threshold(r, 0) == pytest.approx(0.2 * (1 - THRESHOLD_MARGIN), rel=0)
    # Two may go: the two 0.2's; the next risk is 0.5.
    assert highest_threshold(r, 2) == pytest.approx(0.5 * (1 - THRESHOLD_MARGIN), rel=0)
    # One may go, but the two 0.2's tie: the threshold stays at 0.2, dropping none.
    assert highest_threshold(r, 1) == pytest.approx(0.2 * (1 - THRESHOLD_MARGIN), rel=0)
    assert highest_threshold(r, 4) == math.inf
    assert highest_threshold(np.array([0.0, 1.0]), 0) == 0.0


def test_calibrate_hand_computed():
    # Six agent-frames in two frames. Baseline: a, b, e.
    #               a    b    c    d    e    f
    risks = np.array(
        [
            [0.8, 0.3, 0.1, 0.5, 0.4, 0.05],  # stage 0
            [2.0, 1.0, 9.0, 0.1, 5.0, 9.0],  # stage 1
        ]
    )
    base = np.array([1, 1, 0, 0, 1, 0], dtype=bool)
    frames = np.array([0, 0, 0, 1, 1, 1])
    cal = calibrate_thresholds(risks, base, frames, models=MODELS2, max_fn_rate=0.0)
    # Stage 0: min baseline risk 0.3 -> keeps a, b, d, e; removes c, f.
    # Stage 1 on a, b, d, e: min baseline risk 1.0 -> keeps a, b, e; removes d.
    assert cal.thresholds == pytest.approx((0.3, 1.0), rel=1e-8)
    s0, s1 = cal.stages
    assert (s0.agents_in, s0.removed, s0.false_negatives) == (6, 2, 0)
    assert (s1.agents_in, s1.removed, s1.false_negatives) == (4, 1, 0)
    assert s0.mean_removed_per_frame == 1.0 and s1.mean_removed_per_frame == 0.5
    assert s0.removed_share == pytest.approx(2 / 6) and s1.removed_share == pytest.approx(1 / 4)
    assert cal.frames == 2 and cal.baseline_agents == 3 and cal.total_fn_share == 0.0

    # R = 1/3: each stage may drop floor(1/3 * 3) = 1 baseline agent-frame.
    cal = calibrate_thresholds(risks, base, frames, models=MODELS2, max_fn_rate=1 / 3)
    # Stage 0 drops b (0.3): threshold 0.4 keeps a, d, e. Stage 1 on a, d, e: baseline
    # risks 2.0 (a), 5.0 (e); dropping a gives threshold 5.0, keeping e only.
    assert cal.thresholds == pytest.approx((0.4, 5.0), rel=1e-8)
    assert [s.false_negatives for s in cal.stages] == [1, 1]
    assert cal.total_fn_share == pytest.approx(2 / 3)


def test_calibrate_rejects_unusable_input():
    with pytest.raises(CalibrationError, match="no baseline-important agent"):
        calibrate_thresholds(
            np.ones((2, 3)), np.zeros(3, bool), np.zeros(3), models=MODELS2, max_fn_rate=0
        )
    with pytest.raises(CalibrationError, match="shape"):
        calibrate_thresholds(np.ones((3, 3)), np.ones(3, bool), np.zeros(3), models=MODELS2)
    with pytest.raises(CalibrationError, match="max_fn_rate"):
        calibrate_thresholds(
            np.ones((2, 3)), np.ones(3, bool), np.zeros(3), models=MODELS2, max_fn_rate=1.5
        )


def test_nan_risks_are_never_kept():
    keep = cascade_keep(np.array([[np.nan, 0.5], [1.0, 1.0]]), [0.0, 0.0])
    np.testing.assert_array_equal(keep, [[False, True], [False, True]])


# ---------------------------------------------------------------------- properties
@st.composite
def calibration_data(draw):
    """Random risks of 2-3 stages on agent-frames of a few frames, with quantised values
    so that ties happen."""
    n_stages = draw(st.integers(1, 3))
    n = draw(st.integers(1, 40))
    values = st.sampled_from([0.0, 0.01, 0.1, 0.2, 0.25, 0.5, 0.9, 1.0, 3.0])
    risks = draw(hnp.arrays(np.float64, (n_stages, n), elements=values))
    base = draw(hnp.arrays(bool, n))
    base[draw(st.integers(0, n - 1))] = True  # at least one baseline agent
    frames = draw(hnp.arrays(np.int64, n, elements=st.integers(0, 4)))
    return risks, base, frames


@settings(max_examples=150, deadline=None)
@given(data=calibration_data())
def test_zero_fn_rate_drops_no_baseline_agent(data):
    risks, base, frames = data
    models = tuple(f"m{s}" for s in range(risks.shape[0]))
    cal = calibrate_thresholds(risks, base, frames, models=models, max_fn_rate=0.0)
    kept = cascade_keep(risks, cal.thresholds)
    assert kept[-1][base].all()
    assert all(s.false_negatives == 0 for s in cal.stages)
    # Highest: raising any one threshold to the next distinct value would drop a baseline
    # agent (or the threshold is already unbounded).
    for s, t in enumerate(cal.thresholds):
        reaching = kept[s - 1] if s else np.ones_like(base)
        r = risks[s][reaching & base]
        assert t == math.inf or np.any(r < t * (1 + 2 * THRESHOLD_MARGIN) + 1e-300)


@settings(max_examples=150, deadline=None)
@given(data=calibration_data(), rates=st.lists(st.floats(0, 1), min_size=2, max_size=2))
def test_raising_the_fn_rate_never_lowers_a_threshold(data, rates):
    risks, base, frames = data
    models = tuple(f"m{s}" for s in range(risks.shape[0]))
    low, high = sorted(rates)
    t_low = calibrate_thresholds(risks, base, frames, models=models, max_fn_rate=low)
    t_high = calibrate_thresholds(risks, base, frames, models=models, max_fn_rate=high)
    assert all(h >= lo for h, lo in zip(t_high.thresholds, t_low.thresholds, strict=True))


@settings(max_examples=100, deadline=None)
@given(data=calibration_data(), rate=st.floats(0, 1))
def test_each_stage_keeps_to_its_fn_budget(data, rate):
    risks, base, frames = data
    models = tuple(f"m{s}" for s in range(risks.shape[0]))
    cal = calibrate_thresholds(risks, base, frames, models=models, max_fn_rate=rate)
    budget = math.floor(rate * base.sum() + 1e-9)
    kept = cascade_keep(risks, cal.thresholds)
    reaching = np.ones_like(base)
    for s, stage in enumerate(cal.stages):
        dropped = reaching & ~kept[s]
        assert stage.false_negatives == (dropped & base).sum() <= budget
        assert stage.removed == dropped.sum()
        reaching = kept[s]


# ---------------------------------------------------------------------- tiers
def test_tier_thresholds_hand_computed():
    #                  frame 0          frame 1     frame 2
    survival = np.array([0.9, 0.1, 0.5, 0.7, 0.2, 0.05])
    frames = np.array([0, 0, 0, 1, 1, 2])
    # c = 1: the largest per frame 0.9, 0.7, 0.05 -> median 0.7.
    # c = 2: the 2nd largest 0.5, 0.2 and (only one survivor) 0.05 -> median 0.2.
    # c = 5: the smallest per frame 0.1, 0.2, 0.05 -> median 0.1.
    assert tier_thresholds_for_counts(survival, frames, [1, 2, 5]) == (0.7, 0.2, 0.1)
    with pytest.raises(CalibrationError):
        tier_thresholds_for_counts(np.array([]), np.array([]), [1])
