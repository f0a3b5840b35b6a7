"""The compiled kernel (``risk.evaluate``) agrees with the plain-loop reference
(risk/reference.py) to 1e-9.

Relative agreement is checked on every finite value; values below 1e-300 (the Gaussian
overlap and survival risk of far agents, which are subnormal floats with few significant
bits) are compared with an absolute tolerance of 1e-300 instead. The reference orders its
operations differently (plain loops, the math module), so this side of the exactness
contract (tests/exactness.py) is a relative tolerance, not a few ulps: measured on 300
mixed frames, at most 24 ulps apart for the distance and time models and 10150 ulps
(2.2e-12) for the Gaussian, whose exp multiplies the exponent's rounding by its size
(benchmarks/ulp_table.py measures the kernel against numpy).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from frames import mixed_frame
from hypothesis import example, given, settings
from hypothesis import strategies as st
from oracle_ties import settle_rounding_touches, touch_rule_reference

from risk import MODELS, Frame, PredictionSettings, evaluate
from risk.reference import reference_evaluate
from risk.stochastic import CirclesParams, SurvivalParams
from risk.temporal import ClosestEncounterParams, Headway2DParams, HeadwayParams

pytestmark = pytest.mark.exactness


def assert_agree(frame: Frame, params=None, prediction=None) -> dict[str, np.ndarray]:
    fast = evaluate(frame, None, params, prediction=prediction)
    slow = reference_evaluate(frame, None, params, prediction=prediction)
    slow = settle_rounding_touches(fast, slow, frame, params, prediction)
    for name in MODELS:
        np.testing.assert_array_equal(np.isnan(fast[name]), np.isnan(slow[name]), err_msg=name)
        np.testing.assert_allclose(fast[name], slow[name], rtol=1e-9, atol=1e-300, err_msg=name)
    return fast


@settings(max_examples=120, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(235345)  # a path through the ego path's end point within rounding
def test_random_frames_agree(seed):
    assert_agree(mixed_frame(np.random.default_rng(seed)), prediction=PredictionSettings(3.0, 0.25))


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_random_frames_with_other_parameters_agree(seed):
    params = {
        "closest_encounter": ClosestEncounterParams(epsilon_m=0.5, encounter_time_max_s=1.3),
        "headway": HeadwayParams(tau_s=2.5, on_path_tolerance_m=3.0),
        "headway_2d": Headway2DParams(tau_s=0.7, on_path_tolerance_m=0.5, encounter_time_max_s=2.0),
        "circles": CirclesParams(n_circles=5, sigma_scale=1.0, epsilon_m=2.0),
        "survival": SurvivalParams(escape_time_s=1.1),
    }
    assert_agree(mixed_frame(np.random.default_rng(seed)), params, PredictionSettings(4.0, 0.5))


def test_default_prediction_settings_agree():
    """T = 12 s, dt = 0.1 s on a few frames (the reference is slow at 121 steps)."""
    rng = np.random.default_rng(2024)
    for _ in range(3):
        assert_agree(mixed_frame(rng))


def test_lane_like_frame_with_merges_and_shared_vertices():
    """Dense lane points (1.5 m), a merge that joins the ego lane on its exact vertices,
    a leader, an oncoming car and a crossing street: the touching and collinear cases."""
    x = np.arange(0.0, 61.0, 1.5)
    ego_lane = np.column_stack([x, np.zeros_like(x)])
    merge = np.vstack([[[12.0, -9.0], [13.5, -6.0], [15.0, -3.0]], ego_lane[10:]])
    leader = ego_lane[8:]
    oncoming = np.column_stack([x[::-1] + 2.0, np.full_like(x, 3.5)])
    cross = np.column_stack([np.full_like(x, 30.0), x - 20.0])
    f = Frame.from_arrays(
        np.array([ego_lane[0], merge[0], leader[0], oncoming[0], cross[0]]),
        np.array([0.0, math.atan2(3, 1.5), 0.0, math.pi, math.pi / 2]),
        np.array([8.0, 6.0, 5.0, 9.0, 4.0]),
        np.full(5, 4.5),
        np.full(5, 1.9),
        [ego_lane, merge, leader, oncoming, cross],
        ego=0,
    )
    r = assert_agree(f, prediction=PredictionSettings(6.0, 0.2))
    assert r["path_distance"][1] == 1.0  # the merge shares ego vertices
    assert r["headway_2d"][4] > r["headway"][4]  # the crossing street gets a 2D headway


@pytest.mark.parametrize("seed", [11, 12])
def test_reference_is_independent_of_frame_padding(seed):
    """Paths of very different lengths (heavy padding) agree too."""
    rng = np.random.default_rng(seed)
    long = np.column_stack([np.linspace(0, 90, 61), rng.normal(0, 0.3, 61)])
    f = Frame.from_arrays(
        np.array([[0.0, 0.0], [20.0, -10.0], [50.0, 1.0]]),
        np.array([0.0, 1.2, math.pi]),
        np.array([7.0, 3.0, 0.0]),
        np.array([4.0, 0.5, 4.0]),
        np.array([1.8, 0.5, 1.8]),
        [long, np.array([[20.0, -10.0]]), np.array([[50.0, 1.0], [10.0, 1.0]])],
        ego=0,
        kinds=["vehicle", "pedestrian", "vehicle"],
    )
    long[0] = (0.0, 0.0)
    assert_agree(f, prediction=PredictionSettings(5.0, 0.25))


@pytest.mark.realdata
def test_real_waymo_frames_agree(shared_data):
    """Real map-based paths (Waymo sample, converted by converters.waymo): the full frame
    has the right NaN pattern and a subset of agents agrees with the reference."""
    from converters.waymo import read_scenes

    scene = next(read_scenes(shared_data / "waymo" / "womd_637f20cafde22ff8.tfrecord"))
    for frame in (scene.frames[10], scene.frames[60]):
        full = evaluate(frame)
        for name in MODELS:
            np.testing.assert_array_equal(np.isnan(full[name]), ~frame.others, err_msg=name)
        d = np.hypot(*(frame.xy - frame.xy[frame.ego]).T)
        nearest = [int(i) for i in np.argsort(d) if frame.others[i]][:6]
        sub = frame.select([frame.ego, *nearest])
        r = assert_agree(sub)
        for name in MODELS:  # same agents, same values as in the full frame
            np.testing.assert_allclose(r[name][1:], full[name][nearest], rtol=1e-12, err_msg=name)


def test_a_touch_within_rounding_is_the_only_answer_taken_either_way():
    """Seed 235345 (found by hypothesis): agent 2's extended path passes through the ego
    path's end point to the last bit. The orientation signs say the two paths miss, their
    distance says they touch; the kernel follows the distance. The two verdicts differ on
    that agent's 2D headway alone, and every other value is compared exactly as before."""
    frame = mixed_frame(np.random.default_rng(235345))
    prediction = PredictionSettings(3.0, 0.25)
    fast = evaluate(frame, None, prediction=prediction)
    orientation = reference_evaluate(frame, None, prediction=prediction)
    touch = touch_rule_reference(frame, prediction=prediction)
    for name in MODELS:
        if name != "headway_2d":
            np.testing.assert_array_equal(orientation[name], touch[name], err_msg=name)
    differ = np.flatnonzero(
        ~np.isclose(orientation["headway_2d"], touch["headway_2d"], equal_nan=True)
    )
    assert differ.tolist() == [2]
    assert fast["path_distance"][2] == 1.0  # touching
    assert fast["headway_2d"][2] == pytest.approx(touch["headway_2d"][2], rel=1e-9)
    assert touch["headway_2d"][2] > orientation["headway_2d"][2]  # the crossing counts
    settled = settle_rounding_touches(fast, orientation, frame, prediction=prediction)
    assert settled["headway_2d"][2] == touch["headway_2d"][2]
    np.testing.assert_array_equal(
        np.delete(settled["headway_2d"], 2), np.delete(orientation["headway_2d"], 2)
    )
