"""Calibration with a guarantee (risk.calibration.calibrate_with_guarantee): the
order-statistic rule against brute force, refusal of small samples, and properties."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk.calibration import (
    CalibrationError,
    allowed_unit_drops,
    binomial_cdf,
    calibrate_with_guarantee,
    unit_minimum,
    units_needed,
)


def exact_cdf(k: int, n: int, p: Fraction) -> Fraction:
    return sum((math.comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(k + 1)), Fraction(0))


def test_binomial_cdf_against_exact_fractions():
    for n, k, p in [(10, 0, "1/10"), (50, 3, "1/20"), (299, 0, "1/100"), (30, 30, "1/2")]:
        assert binomial_cdf(k, n, float(Fraction(p))) == pytest.approx(
            float(exact_cdf(k, n, Fraction(p))), rel=1e-12
        )


def test_units_needed_is_about_300_for_one_percent_at_95():
    assert units_needed(0.01, 0.95) == 299
    assert allowed_unit_drops(299, 0.01, 0.95) == 0
    assert allowed_unit_drops(298, 0.01, 0.95) == -1
    assert units_needed(0.1, 0.9) == 22


def test_rule_against_a_brute_force_order_statistic():
    # a hand-made table: 8 units (scenes), agent-frames with one stage's scores
    units = np.array([0, 0, 1, 1, 1, 2, 3, 4, 5, 6, 7, 7, 8])
    important = np.array([1, 0, 1, 1, 0, 1, 1, 1, 0, 1, 1, 1, 0], dtype=bool)
    scores = np.array([0.5, 0.01, 0.3, 0.9, 0.02, 0.7, 0.2, 0.8, 0.05, 0.6, 0.4, 0.35, 0.1])
    # unit minima over important agents: 0 .5, 1 .3, 2 .7, 3 .2, 4 .8, 6 .6, 7 .35
    assert unit_minimum(scores, important, units).tolist() == [0.5, 0.3, 0.7, 0.2, 0.8, 0.6, 0.35]
    miss, conf = 0.5, 0.8
    n = 7
    # brute force: the largest k with P(Bin(n, A) <= k) <= 1 - C, exactly
    k = max(j for j in range(-1, n) if j < 0 or exact_cdf(j, n, Fraction(1, 2)) <= Fraction(1, 5))
    assert k == allowed_unit_drops(n, miss, conf) == 1
    cal = calibrate_with_guarantee(
        scores[None, :], important, units, models=["m"], miss_rate=miss, confidence=conf
    )
    # brute force: the highest threshold among the observed values dropping <= k units
    candidates = sorted(set(scores.tolist()))
    best = max(
        t for t in candidates if (np.array([0.5, 0.3, 0.7, 0.2, 0.8, 0.6, 0.35]) < t).sum() <= k
    )
    assert best == 0.3
    assert (
        cal.stages[0].threshold == pytest.approx(best, rel=1e-8) and cal.stages[0].threshold < best
    )
    assert cal.stages[0].units_dropped == 1 and cal.units == 7 and cal.positives == 9
    assert "0.5" in cal.statement() and cal.guarantee()["unit"] == "scene"


def test_a_sample_too_small_is_refused_saying_how_many_are_needed():
    units = np.arange(100)
    with pytest.raises(CalibrationError, match=r"needs at least 299 scenes .* has 100"):
        calibrate_with_guarantee(
            np.ones((1, 100)),
            np.ones(100, bool),
            units,
            models=["m"],
            miss_rate=0.01,
            confidence=0.95,
        )


def test_stages_share_the_budget():
    rng = np.random.default_rng(1)
    units = np.repeat(np.arange(200), 3)
    scores = rng.random((2, units.size))
    cal = calibrate_with_guarantee(
        scores, np.ones(units.size, bool), units, models=["a", "b"], miss_rate=0.1, confidence=0.9
    )
    assert cal.stage_miss_rate == pytest.approx(0.05) and cal.stage_confidence == pytest.approx(
        0.95
    )
    k = allowed_unit_drops(200, 0.05, 0.95)
    assert all(s.drops_allowed == k and s.units_dropped <= k for s in cal.stages)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_units=st.integers(25, 120),
    miss=st.sampled_from([0.05, 0.1, 0.2]),
    conf=st.sampled_from([0.8, 0.9, 0.95]),
    stages=st.integers(1, 3),
)
def test_chosen_thresholds_drop_at_most_the_allowed_units(seed, n_units, miss, conf, stages):
    rng = np.random.default_rng(seed)
    per = rng.integers(1, 5, n_units)
    units = np.repeat(np.arange(n_units), per)
    important = rng.random(units.size) < 0.5
    important[np.r_[0, np.cumsum(per)[:-1]]] = True  # every unit has a positive
    scores = rng.exponential(1.0, (stages, units.size))
    scores[:, rng.random(units.size) < 0.05] = np.inf  # kept by the corridor
    scores[:, rng.random(units.size) < 0.02] = -np.inf  # dropped by the bound
    try:
        cal = calibrate_with_guarantee(
            scores, important, units, models=[f"m{s}" for s in range(stages)],
            miss_rate=miss, confidence=conf,
        )  # fmt: skip
    except CalibrationError as exc:
        k = allowed_unit_drops(n_units, miss / stages, 1 - (1 - conf) / stages)
        forced = np.unique(units[important & np.isneginf(scores[0])]).size
        assert n_units < units_needed(miss / stages, 1 - (1 - conf) / stages) or forced > k, exc
        return
    k = allowed_unit_drops(n_units, miss / stages, 1 - (1 - conf) / stages)
    for s, stage in enumerate(cal.stages):
        dropped_units = np.unique(units[important & (scores[s] < stage.threshold)])
        assert dropped_units.size <= k
        assert stage.threshold >= 0
    # the whole cascade drops at most stages * k units
    kept = np.all(scores >= np.array([st_.threshold for st_ in cal.stages])[:, None], axis=0)
    assert np.unique(units[important & ~kept]).size <= stages * k
