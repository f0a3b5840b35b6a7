"""Property tests (hypothesis) for the invariants of the model spec (docs/models.md)."""

from __future__ import annotations

import math

import numpy as np
from frames import random_frame, wander
from hypothesis import given, settings
from hypothesis import strategies as st
from roc_oracle import roc_curve

from risk import (
    BASELINE_MODEL,
    BASELINE_THRESHOLD,
    MODELS,
    Frame,
    FrameContext,
    PredictionSettings,
    baseline_mask,
    evaluate,
)
from risk.distance import current_distances, path_distances, trajectory_distances
from risk.metrics import confusion_counts, threshold_for_tpr
from risk.stochastic import overlap_rows, survival_function
from risk.temporal import closest_encounter_distances

# A shorter horizon keeps the examples fast; the invariants do not depend on it.
FAST = PredictionSettings(horizon_s=6.0, dt_s=0.2)
seeds = st.integers(0, 2**32 - 1)


def transformed(f: Frame, theta: float, shift: np.ndarray) -> Frame:
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    paths = [[p @ rot.T + shift for p in f.agent_paths(i)] for i in range(f.n_agents)]
    return Frame.from_arrays(
        f.xy @ rot.T + shift,
        f.heading + theta,
        f.speed,
        f.length,
        f.width,
        paths,
        ego=f.ego,
        kinds=f.kinds,
    )


# ---------------------------------------------------------------------- distances
@settings(max_examples=150, deadline=None)
@given(seeds)
def test_distance_ordering(seed):
    """d_path <= d_traj <= d_E <= d_current (same extended paths and horizon)."""
    ctx = FrameContext(random_frame(np.random.default_rng(seed)), FAST)
    others = ctx.frame.others
    d_path = path_distances(ctx)[others]
    d_traj = trajectory_distances(ctx)[others]
    d_e = closest_encounter_distances(ctx)[others]
    d_now = current_distances(ctx)[others]
    tol = 1e-9
    assert np.all(d_path <= d_traj + tol)
    assert np.all(d_traj <= d_e + tol)
    assert np.all(d_e <= d_now + tol)


@settings(max_examples=120, deadline=None)
@given(seeds)
def test_ranges(seed):
    f = random_frame(np.random.default_rng(seed))
    r = evaluate(f, prediction=FAST)
    o = f.others
    for name in ("current_distance", "path_distance", "trajectory_distance", "circles"):
        assert np.all((r[name][o] > 0) & (r[name][o] <= 1)), name
    for name in ("closest_encounter", "headway", "headway_2d"):
        assert np.all((r[name][o] >= 0) & (r[name][o] <= 1)), name
    assert np.all(r["gaussian"][o] >= 0)
    assert np.all(r["survival"][o] >= 0)
    ctx = FrameContext(f, FAST)
    p_o = overlap_rows(ctx, int(ctx.ego_rows[0]))
    assert np.all(p_o >= 0)
    s = survival_function(p_o, FAST.dt_s, 0.4)
    assert np.all(s[:, 0] == 1.0)
    assert np.all(np.diff(s, axis=1) <= 0)


# ---------------------------------------------------------------------- symmetry, invariance
SYMMETRIC = (
    "current_distance",
    "path_distance",
    "trajectory_distance",
    "closest_encounter",
    "gaussian",
    "survival",
)


@settings(max_examples=120, deadline=None)
@given(seeds)
def test_symmetry_swapping_ego_and_agent(seed):
    f = random_frame(np.random.default_rng(seed), bodies=False)
    j = f.n_agents - 1
    a = evaluate(f, prediction=FAST)
    b = evaluate(f.with_ego(j), prediction=FAST)
    # circles are symmetric only for point bodies (the ego is one circle of half its
    # length, the other k circles of half its width); these frames have point bodies.
    for name in (*SYMMETRIC, "circles"):
        np.testing.assert_allclose(a[name][j], b[name][0], rtol=1e-9, atol=1e-300, err_msg=name)


@settings(max_examples=120, deadline=None)
@given(seeds, st.floats(-math.pi, math.pi), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3))
def test_rotation_and_translation_invariance(seed, theta, dx, dy):
    f = random_frame(np.random.default_rng(seed))
    a = evaluate(f, prediction=FAST)
    b = evaluate(transformed(f, theta, np.array([dx, dy])), prediction=FAST)
    for name in MODELS:
        np.testing.assert_allclose(a[name], b[name], rtol=1e-6, atol=1e-300, err_msg=name)


# ---------------------------------------------------------------------- monotonicity
@settings(max_examples=120, deadline=None)
@given(
    st.floats(2.0, 20.0),
    st.floats(0.01, 10.0),
    st.floats(-60.0, 60.0),
    st.floats(0.0, 20.0),
    st.floats(0.0, 20.0),
)
def test_moving_an_agent_away_lowers_risk(y0, dy, x0, v_ego, v_other):
    """An agent driving past the ego on a line y = y0: moving the line away lowers R_E,
    R_G and R_S (and the circle risk), because every predicted distance grows and both
    covariances are axis-aligned. (y0 >= 2 m keeps every overlap below 0.01 per step,
    where survival risk grows with every overlap.)"""

    def risks(y):
        f = Frame.from_arrays(
            np.array([[0.0, 0.0], [x0, y]]),
            np.zeros(2),
            np.array([v_ego, v_other]),
            np.array([4.5, 4.5]),
            np.array([1.8, 1.8]),
            [np.array([[0.0, 0.0], [300.0, 0.0]]), np.array([[x0, y], [x0 + 300.0, y]])],
            ego=0,
        )
        return evaluate(
            f, ["closest_encounter", "gaussian", "survival", "circles"], prediction=FAST
        )

    near, far = risks(y0), risks(y0 + dy)
    for name in near:
        assert far[name][1] <= near[name][1] * (1 + 1e-12), name


def test_moving_a_crossing_agent_away_strictly_lowers_risk():
    r = [
        evaluate(
            Frame.from_arrays(
                np.array([[0.0, 0.0], [30.0, -y]]),
                np.array([0.0, math.pi / 2]),
                np.array([10.0, 10.0]),
                np.full(2, 4.5),
                np.full(2, 1.8),
                [np.array([[0.0, 0.0], [200.0, 0.0]]), np.array([[30.0, -y], [30.0, 200.0]])],
                ego=0,
            )
        )
        for y in (30.0, 35.0, 45.0)
    ]
    for name in ("closest_encounter", "gaussian", "survival"):
        values = [x[name][1] for x in r]
        assert values[0] > values[1] > values[2] > 0, (name, values)


# ---------------------------------------------------------------------- thresholds, baseline
@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.one_of(st.floats(0, 1), st.just(math.nan)), min_size=1, max_size=30),
    st.integers(0, 2**32 - 1),
)
def test_raising_the_threshold_never_grows_the_kept_set(scores, seed):
    s = np.array(scores)
    b = np.random.default_rng(seed).random(s.size) < 0.5
    t = np.sort(np.r_[np.unique(s[~np.isnan(s)]), 0.0, 0.5, 1.1])
    c = confusion_counts(s, b, t)
    kept = c.tp + c.fp
    assert np.all(np.diff(kept) <= 0)
    assert np.all(np.diff(c.tp) <= 0) and np.all(np.diff(c.fp) <= 0)
    n_agents = int((~np.isnan(s)).sum())
    assert np.all(c.tp + c.fp + c.fn + c.tn == n_agents)


@settings(max_examples=15, deadline=None)
@given(st.lists(seeds, min_size=1, max_size=4))
def test_the_baseline_has_tpr_one_and_fpr_zero_against_itself(frame_seeds):
    scores, masks = [], []
    for seed in frame_seeds:
        f = random_frame(np.random.default_rng(seed), n=8)
        r = evaluate(f, [BASELINE_MODEL])[BASELINE_MODEL]
        scores.append(r)
        masks.append(baseline_mask(r))
    res = roc_curve(scores, masks, thresholds=np.array([1e-30, BASELINE_THRESHOLD, 1e-20]))
    has_pos = ~np.isnan(res.tpr[:, 1])
    assert np.all(res.tpr[has_pos, 1] == 1.0)
    has_neg = ~np.isnan(res.fpr[:, 1])
    assert np.all(res.fpr[has_neg, 1] == 0.0)
    if has_pos.any():
        assert threshold_for_tpr(res, 1.0) >= BASELINE_THRESHOLD


# ---------------------------------------------------------------------- 2D headway
@settings(max_examples=50, deadline=None)
@given(seeds, st.floats(0.0, 1.0), st.floats(-1.7, 1.7), st.floats(0.0, 20.0), st.floats(0.0, 20.0))
def test_headway_2d_equals_headway_on_the_ego_path(seed, where, lateral, v_ego, v_other):
    rng = np.random.default_rng(seed)
    ego_path = wander(rng, [0.0, 0.0], 0.0, max_points=10)
    if len(ego_path) < 2:
        ego_path = np.array([[0.0, 0.0], [50.0, 0.0]])
    seg = np.diff(ego_path, axis=0)
    cum = np.r_[0.0, np.cumsum(np.hypot(*seg.T))]
    s = where * cum[-1]
    j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(seg) - 1)
    u = seg[j] / np.hypot(*seg[j])
    on_path = ego_path[j] + (s - cum[j]) * u + lateral * np.array([-u[1], u[0]])
    other_path = wander(rng, on_path, rng.uniform(-math.pi, math.pi))
    f = Frame.from_arrays(
        np.array([[0.0, 0.0], on_path]),
        np.array([0.0, 0.0]),
        np.array([v_ego, v_other]),
        np.full(2, 4.0),
        np.full(2, 1.8),
        [ego_path, other_path],
        ego=0,
    )
    r = evaluate(f, ["headway", "headway_2d"], prediction=FAST)
    assert r["headway"][1] == r["headway_2d"][1]
