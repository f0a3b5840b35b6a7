"""The exactness contract (tests/exactness.py): its ulp distance by hand, and the kernel
against numpy computed with another CPU's ``exp``, simulated on any machine."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
from conftest import ROOT
from exactness import (
    FLOOR,
    KERNEL_VS_NUMPY_ULPS,
    assert_within_ulps,
    exp_off_by,
    kernel_ulps,
    max_ulps,
    near,
    numpy_exp_off_by,
    survival_ulps,
    ulp_distance,
)
from frames import mixed_frame
from hypothesis import given, settings
from hypothesis import strategies as st

from risk import MODELS, PredictionSettings, evaluate
from risk.registry import evaluate_numpy

pytestmark = pytest.mark.exactness
INF, NAN = math.inf, math.nan


def up(x: float, k: int = 1) -> float:
    for _ in range(k):
        x = math.nextafter(x, INF)
    return x


def test_ulp_distance_by_hand():
    a = np.array([1.0, 1.0, 0.0, -0.0, NAN, NAN, INF, INF, -INF, 1e-15, 2.0, -1.0, 0.1])
    b = np.array([up(1.0), up(1.0, 7), -0.0, 0.0, NAN, 1.0, INF, 1.7e308, INF, up(1e-15, 3),
                  math.nextafter(2.0, 0), up(-1.0), 0.1])  # fmt: skip
    got = ulp_distance(a, b)
    assert got.tolist() == [1, 7, 0, 0, 0, INF, 0, INF, INF, 3, 1, 1, 0]
    # Across zero: the floats between -x and x, both signs counted.
    tiny = 5e-324
    assert ulp_distance(np.array([-tiny]), np.array([tiny])).tolist() == [
        2 * tiny / np.spacing(FLOOR)
    ]
    # Symmetric.
    np.testing.assert_array_equal(ulp_distance(b, a), got)


def test_below_the_floor_differences_count_in_ulps_of_the_floor():
    """A subnormal and its neighbour are one float apart, but that is a relative change of
    up to 1: below 1e-300 the unit is the float spacing at 1e-300 instead."""
    assert ulp_distance(np.array([5e-324]), np.array([1e-323])).item() < 1e-7
    assert ulp_distance(np.array([0.0]), np.array([1e-310])).item() == pytest.approx(
        1e-310 / np.spacing(FLOOR)
    )
    assert ulp_distance(np.array([0.0]), np.array([1e-290])).item() > 1e9


def test_assert_within_ulps_names_what_differs():
    a = np.array([1.0, NAN, 3.0])
    assert_within_ulps(a, np.array([up(1.0, 2), NAN, 3.0]), 2)
    with pytest.raises(AssertionError, match=r"m: 1 values more than 2 ulps apart: \[0\] 1\.0"):
        assert_within_ulps(a, np.array([up(1.0, 3), NAN, 3.0]), 2, "m")
    with pytest.raises(AssertionError, match="inf ulps"):
        assert_within_ulps(a, np.array([1.0, 2.0, 3.0]), 100)  # NaN against a number
    with pytest.raises(AssertionError, match="shapes"):
        assert_within_ulps(a, a[:2], 1)


def test_near_finds_values_within_the_tolerance_of_a_threshold():
    t = 0.25
    v = np.array([t, up(t, 3), up(t, 4), math.nextafter(t, 0), NAN, 0.5])
    assert near(v, t, 3).tolist() == [True, True, False, True, False, False]
    assert not near(v, INF, 3).any()


def test_the_bounds():
    assert max(KERNEL_VS_NUMPY_ULPS.values()) == 6
    assert set(KERNEL_VS_NUMPY_ULPS) | {"survival"} == set(MODELS)
    assert survival_ulps(12.0, 0.4) == 70.0  # 8 + 2 (30 + 1)
    assert kernel_ulps("survival", 3.0, 0.4) == 25.0
    assert kernel_ulps("gaussian", 3.0, 0.4) == 6


def test_exp_off_by_moves_results_by_at_most_so_many_floats():
    rng = np.random.default_rng(0)
    x = np.r_[np.linspace(-800, 5, 5000), 0.0, -np.inf, np.inf]
    want = np.exp(x)
    got = exp_off_by(2, rng)(x)
    d = ulp_distance(got, want)
    assert d.max() <= 2 and (d > 0).mean() > 0.5
    assert got[-3] == 1.0 and got[-2] == 0.0 and got[-1] == INF  # exact results stay
    out = np.empty_like(x)
    assert exp_off_by(1, rng)(x, out=out) is out


SHORT = PredictionSettings(horizon_s=3.0, dt_s=0.25)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_kernel_within_the_contract_of_numpy_with_another_cpus_exp(seed):
    """numpy's exp on another CPU, simulated: every exp result of the numpy models moved
    by up to a float at random (numpy's AVX-512 exp is at most 1 apart from the C
    library's, measured; the contract allows two exps 2 apart, each within 1 ulp of the
    true value, so this stays inside it also where numpy's own exp is the AVX-512 one).
    The kernel's results stay within the contract on every machine, not only on one
    whose numpy takes another code path."""
    rng = np.random.default_rng(seed)
    frame = mixed_frame(rng)
    fast = evaluate(frame, prediction=SHORT)
    with numpy_exp_off_by(1, rng):
        slow = evaluate_numpy(frame, prediction=SHORT)
    for name in MODELS:
        assert_within_ulps(fast[name], slow[name], kernel_ulps(name, SHORT.horizon_s), name)


def test_the_simulated_exp_reaches_the_numpy_models():
    """(So that the test above compares against a moved exp, not numpy's own.)"""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_models import random_frame as lane_frame

    frame = lane_frame(40, np.random.default_rng(5))
    stochastic = ["gaussian", "survival"]
    plain = evaluate_numpy(frame, stochastic)
    with numpy_exp_off_by(2, np.random.default_rng(1)):
        moved = evaluate_numpy(frame, stochastic)
    assert all(max_ulps(plain[n], moved[n]) > 0 for n in stochastic)
