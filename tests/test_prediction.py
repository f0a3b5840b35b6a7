"""Prediction settings, the uncertainty model and the shared per-frame context."""

from __future__ import annotations

import math

import numpy as np
import pytest

from risk import Frame, FrameContext, KindUncertainty, PredictionSettings, RiskError
from risk.prediction import covariances, uncertainty_sigmas


def frame(speeds, paths, headings=None, kinds=None, ego=0):
    n = len(paths)
    xy = np.array([np.asarray(p, dtype=float)[0] for p in paths])
    return Frame.from_arrays(
        xy,
        np.zeros(n) if headings is None else np.asarray(headings, dtype=float),
        np.asarray(speeds, dtype=float),
        np.full(n, 4.0),
        np.full(n, 2.0),
        [np.asarray(p, dtype=float) for p in paths],
        ego=ego,
        kinds=kinds,
    )


# ---------------------------------------------------------------------- settings
def test_default_settings_and_steps():
    s = PredictionSettings()
    assert (s.horizon_s, s.dt_s, s.n_steps) == (12.0, 0.1, 121)
    steps = s.steps_s
    assert steps[0] == 0.0 and steps[-1] == 12.0
    np.testing.assert_allclose(np.diff(steps), 0.1)


@pytest.mark.parametrize(
    ("horizon", "dt"), [(12.0, 0.7), (0.0, 0.1), (-1.0, 0.1), (12.0, 0.0), (math.nan, 0.1)]
)
def test_bad_settings_are_rejected(horizon, dt):
    with pytest.raises(RiskError):
        PredictionSettings(horizon_s=horizon, dt_s=dt)


ROW = {
    "sigma0_lon_m": 0.5,
    "sigma0_lat_m": 0.3,
    "growth_lon": 0.1,
    "growth_lat": 0.1,
    "sigma_max_lon_m": 1.0,
    "sigma_max_lat_m": 1.0,
}


def test_bad_uncertainty_is_rejected():
    with pytest.raises(RiskError, match="sigma0"):
        KindUncertainty(**{**ROW, "sigma0_lon_m": 0.0})
    with pytest.raises(RiskError):
        KindUncertainty(**{**ROW, "growth_lon": -0.1})
    with pytest.raises(RiskError):
        KindUncertainty(**{**ROW, "time_growth_lat_mps": -0.1})
    with pytest.raises(TypeError):  # keywords only: six floats in a row are easy to swap
        KindUncertainty(0.5, 0.3, 0.1, 0.1, 1.0, 1.0)  # type: ignore[misc]


def test_settings_dict_has_the_spec_table():
    d = PredictionSettings().to_dict()
    assert d["uncertainty"]["vehicle"]["sigma0_lon_m"] == 0.75
    assert d["uncertainty"]["pedestrian"]["sigma_max_lat_m"] == 1.5
    assert d["uncertainty"]["cyclist"]["growth_lon"] == 0.125
    assert d["uncertainty"]["other"] == d["uncertainty"]["vehicle"]  # our choice


# ---------------------------------------------------------------------- uncertainty
def test_sigmas_grow_with_distance_travelled_and_are_capped():
    steps = np.array([0.0, 1.0, 4.0, 100.0])
    lon, lat = uncertainty_sigmas(
        np.array([0, 1]), np.array([10.0, 1.0]), steps, PredictionSettings().uncertainty
    )
    # vehicle at 10 m/s: 0.75 + 0.125 * 10 s; lat 0.33 + 0.1 * 10 s, capped at 0.5
    np.testing.assert_allclose(lon[0], [0.75, 2.0, 5.0, 5.0])
    np.testing.assert_allclose(lat[0], [0.33, 0.5, 0.5, 0.5])
    # pedestrian at 1 m/s: 0.1 + 0.03 s, capped 0.4 (lon) and 1.5 (lat)
    np.testing.assert_allclose(lon[1], [0.1, 0.13, 0.22, 0.4])
    np.testing.assert_allclose(lat[1], [0.1, 0.13, 0.22, 1.5])


def test_covariance_rotates_with_heading():
    xx, xy, yy = covariances(np.array(2.0), np.array(1.0), np.array(0.0), np.array(1.0))
    assert (float(xx), float(yy)) == pytest.approx((1.0, 4.0))  # heading +y: lon along y
    assert float(xy) == pytest.approx(0.0, abs=1e-15)
    c = s = math.sqrt(0.5)
    xx, xy, yy = covariances(np.array(2.0), np.array(1.0), np.array(c), np.array(s))
    assert (float(xx), float(xy), float(yy)) == pytest.approx((2.5, 1.5, 2.5))


# ---------------------------------------------------------------------- prediction
def test_constant_speed_along_path_with_extension():
    # An L-shaped path of 20 m; at 5 m/s over 12 s the agent needs 60 m: the last
    # segment (heading +y) is extended by 40 m.
    f = frame([5.0, 0.0], [[[0, 0], [10, 0], [10, 10]], [[50, 50]]])
    ctx = FrameContext(f)
    xy = ctx.traj_xy
    np.testing.assert_allclose(xy[0, 10], [5.0, 0.0], atol=1e-12)  # s = 1 s
    np.testing.assert_allclose(xy[0, 30], [10.0, 5.0], atol=1e-12)  # s = 3 s: round the bend
    np.testing.assert_allclose(xy[0, -1], [10.0, 50.0], atol=1e-9)  # s = 12 s, extended
    np.testing.assert_allclose(ctx.traj_dir[0, 10], [1.0, 0.0])
    np.testing.assert_allclose(ctx.traj_dir[0, -1], [0.0, 1.0], atol=1e-12)
    # standing agent stays put
    np.testing.assert_allclose(xy[1], np.tile([50.0, 50.0], (121, 1)))


def test_single_point_path_runs_along_heading():
    f = frame([2.0, 0.0], [[[1, 1]], [[9, 9]]], headings=[math.pi / 2, 0.0])
    xy = FrameContext(f).traj_xy
    np.testing.assert_allclose(xy[0, -1], [1.0, 25.0], atol=1e-9)


def test_cut_paths_end_at_the_dynamic_horizon():
    f = frame([2.0, 0.0], [[[0, 0], [100, 0]], [[5, 5], [5, 50]]])
    ctx = FrameContext(f)
    cut = ctx.cut_paths
    np.testing.assert_allclose(cut[0, -1], [24.0, 0.0])  # 2 m/s * 12 s
    np.testing.assert_allclose(cut[1], [[5, 5]] * cut.shape[1])  # v = 0: one point
    # the last predicted point is exactly the cut end
    np.testing.assert_array_equal(ctx.traj_xy[0, -1], cut[0, -1])


def test_covariances_follow_kind_and_path_heading():
    f = frame([0.0, 0.0], [[[0, 0], [0, 10]], [[5, 5], [6, 5]]], kinds=["pedestrian", "vehicle"])
    xx, xy, yy = FrameContext(f).cov
    # pedestrian heading +y: isotropic 0.1 m
    np.testing.assert_allclose([xx[0, 0], yy[0, 0]], [0.01, 0.01])
    # vehicle heading +x standing: lon 0.75 along x, lat 0.33 along y
    np.testing.assert_allclose([xx[1, 0], xy[1, 0], yy[1, 0]], [0.5625, 0.0, 0.1089], atol=1e-15)


def test_context_computes_shared_work_once():
    f = frame([5.0, 3.0], [[[0, 0], [100, 0]], [[10, -10], [10, 50]]])
    ctx = FrameContext(f)
    assert ctx.traj_x is ctx.traj_x
    calls = []
    assert ctx.memo("k", lambda: calls.append(1) or 42) == 42
    assert ctx.memo("k", lambda: calls.append(1) or 43) == 42
    assert calls == [1]
