"""The one IDM law (replay.planning.idm_law): hand-computed values, properties, and the
two callers (the IDM planner, the reactive agents) unchanged bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from replay.planning import reactive
from replay.planning.idm import IdmSettings
from replay.planning.idm_law import (
    IdmLaw,
    desired_gap_m,
    free_road_acceleration,
    idm_acceleration,
)

# a0 = 1, b = 1 (so 2 sqrt(a0 b) = 2), T = 1 s, s0 = 2 m, delta = 4.
UNIT = IdmLaw(accel_mps2=1.0, decel_mps2=1.0, headway_s=1.0, min_gap_m=2.0, exponent=4.0)


@pytest.mark.parametrize(
    ("v", "v0", "gap", "v_lead", "expected"),
    [
        # free road: 1 - (10/20)^4 = 0.9375
        (10.0, 20.0, math.inf, 0.0, 0.9375),
        # same speed: s* = 2 + 10 = 12; 0.9375 - (12/20)^2 = 0.5775
        (10.0, 20.0, 20.0, 10.0, 0.5775),
        # closing on a standing car: s* = 2 + 10 + 10*10/2 = 62; 0.9375 - (62/30)^2
        (10.0, 20.0, 30.0, 0.0, 0.9375 - (62.0 / 30.0) ** 2),
        # standing, leader pulling away: s* = s0 = 2; 1 - (2/4)^2 = 0.75
        (0.0, 20.0, 4.0, 5.0, 0.75),
        # a much faster leader: v T + v dv / 2 = 10 - 150 < 0, so s* = s0 = 2;
        # 0.9375 - (2/10)^2 = 0.8975
        (10.0, 20.0, 10.0, 40.0, 0.8975),
        # at the desired speed, at the desired gap: 0 - 1 = -1
        (20.0, 20.0, 22.0, 20.0, -1.0),
    ],
)
def test_hand_computed(v: float, v0: float, gap: float, v_lead: float, expected: float) -> None:
    assert float(idm_acceleration(v, v0, gap, v_lead, UNIT)) == pytest.approx(expected, abs=1e-12)


def test_parts_by_hand() -> None:
    assert float(free_road_acceleration(10.0, 20.0, UNIT)) == pytest.approx(0.9375)
    assert float(desired_gap_m(10.0, 0.0, UNIT)) == pytest.approx(62.0)
    assert float(desired_gap_m(10.0, 40.0, UNIT)) == pytest.approx(2.0)
    assert UNIT.braking_scale_mps2 == pytest.approx(2.0)
    # zero gap: full braking (-inf), not a warning or NaN
    assert float(idm_acceleration(5.0, 10.0, 0.0, 0.0, UNIT)) == -math.inf


def test_infinite_gap_is_the_free_road_exactly() -> None:
    v = np.array([0.0, 3.0, 12.5, 30.0])
    free = free_road_acceleration(v, 15.0, UNIT)
    np.testing.assert_array_equal(idm_acceleration(v, 15.0, np.inf, 7.0, UNIT), free)


speeds = st.floats(0.0, 50.0)
positive = st.floats(0.5, 50.0)
gaps = st.floats(0.05, 300.0)
laws = st.builds(
    IdmLaw,
    accel_mps2=st.floats(0.3, 4.0),
    decel_mps2=st.floats(0.5, 8.0),
    headway_s=st.floats(0.5, 3.0),
    min_gap_m=st.floats(0.5, 5.0),
    exponent=st.sampled_from([2.0, 4.0, 10.0]),
)


@settings(max_examples=200, deadline=None)
@given(laws, speeds, positive, gaps, gaps, speeds, speeds)
def test_properties(
    law: IdmLaw, v: float, v0: float, gap1: float, gap2: float, lead1: float, lead2: float
) -> None:
    near, far = sorted((gap1, gap2))
    slow, fast = sorted((lead1, lead2))
    a = float(idm_acceleration(v, v0, near, slow, law))
    # never above the free road, which is never above a0
    assert a <= float(free_road_acceleration(v, v0, law)) <= law.accel_mps2
    # more room or a faster leader never asks for more braking
    assert float(idm_acceleration(v, v0, far, slow, law)) >= a
    assert float(idm_acceleration(v, v0, near, fast, law)) >= a
    # broadcasting equals the scalar evaluation (to rounding: numpy's array power may
    # take a vectorised path whose last bit differs from the scalar libm one)
    many = idm_acceleration(np.array([v, v]), v0, np.array([near, far]), slow, law)
    assert many[0] == pytest.approx(a, rel=1e-12, abs=1e-12)
    assert many[1] == pytest.approx(float(idm_acceleration(v, v0, far, slow, law)), rel=1e-12)


# ---------------------------------------------------------------------- the callers
def _reactive_before(
    v: np.ndarray, desired: np.ndarray, gap: np.ndarray, lead: np.ndarray,
    s: reactive.ReactiveSettings,
) -> np.ndarray:  # fmt: skip
    """reactive.idm_acceleration as it was written before the shared law (the oracle)."""
    v0 = np.maximum(desired, 0.1)
    a0, b = s.accel_mps2, s.decel_mps2
    free = a0 * (1.0 - (v / v0) ** s.exponent)
    s_star = s.min_gap_m + np.maximum(
        0.0, v * s.headway_s + v * (v - lead) / (2.0 * np.sqrt(a0 * b))
    )
    has_leader = np.isfinite(gap)
    gap_used = np.maximum(np.where(has_leader, gap, 1.0), s.least_gap_m)
    interaction = np.where(has_leader, a0 * (s_star / gap_used) ** 2, 0.0)
    return np.clip(free - interaction, -b, a0)


def _planner_before(v: float, v0: float, gap: np.ndarray, lead: np.ndarray) -> np.ndarray:
    """The IDM planner's per-step agent accelerations as written before the shared law."""
    p = IdmSettings()
    a_free = p.a0_mps2 * (1.0 - (v / v0) ** p.delta)
    sqrt_ab = 2.0 * math.sqrt(p.a0_mps2 * p.b_mps2)
    s_star = p.s0_m + np.maximum(0.0, v * p.headway_s + v * (v - lead) / sqrt_ab)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(a_free - p.a0_mps2 * (s_star / gap) ** 2)


def _random_cases(seed: int, n: int = 4000) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    v = rng.uniform(0.0, 40.0, n)
    desired = rng.uniform(-1.0, 40.0, n)
    gap = np.where(rng.random(n) < 0.2, np.inf, rng.uniform(-2.0, 150.0, n))
    lead = rng.uniform(-5.0, 45.0, n)
    return v, desired, gap, lead


def test_reactive_unchanged_bit_for_bit() -> None:
    v, desired, gap, lead = _random_cases(1)
    for s in (reactive.ReactiveSettings(), reactive.ReactiveSettings(exponent=2.0)):
        np.testing.assert_array_equal(
            reactive.idm_acceleration(v, desired, gap, lead, s),
            _reactive_before(v, desired, gap, lead, s),
        )


def test_planner_terms_unchanged_bit_for_bit() -> None:
    v, desired, gap, lead = _random_cases(2)
    gap = np.where(np.isinf(gap), np.nan, gap)  # the planner's "no constraint"
    law = IdmSettings().law
    for k in range(0, v.size, 97):  # the planner works on one ego speed per step
        vk = v[k]  # a numpy scalar, as the planner's v[k]
        v0 = max(float(desired[k]), 0.1)
        np.testing.assert_array_equal(
            idm_acceleration(vk, v0, gap, lead, law), _planner_before(vk, v0, gap, lead)
        )
        assert float(free_road_acceleration(vk, v0, law)) == float(
            IdmSettings().a0_mps2 * (1.0 - (vk / v0) ** IdmSettings().delta)
        )
