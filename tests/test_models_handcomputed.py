"""Every model on tiny frames whose answers are worked out by hand (or in closed form)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from risk import Frame, PredictionSettings, evaluate
from risk.distance import CurrentDistanceParams
from risk.stochastic import CirclesParams, SurvivalParams
from risk.temporal import ClosestEncounterParams, Headway2DParams, HeadwayParams


def make(agents, ego=0, **kw):
    """agents: dicts with path (first point = position), speed, and optional heading,
    length, width, kind, valid."""
    paths = [a["path"] for a in agents]
    first = [np.asarray(p[0] if isinstance(p[0][0], (list, tuple)) else p, float) for p in paths]
    xy = np.array([np.atleast_2d(p)[0] for p in first])
    return Frame.from_arrays(
        xy,
        np.array([a.get("heading", 0.0) for a in agents]),
        np.array([a["speed"] for a in agents], dtype=float),
        np.array([a.get("length", 4.0) for a in agents]),
        np.array([a.get("width", 2.0) for a in agents]),
        [
            [np.asarray(c, float) for c in p]
            if isinstance(p[0][0], (list, tuple))
            else np.asarray(p, float)
            for p in paths
        ],
        ego=ego,
        kinds=[a.get("kind", "vehicle") for a in agents],
        valid=[a.get("valid", True) for a in agents],
        **kw,
    )


EGO_EAST = {"path": [[0, 0], [200, 0]], "speed": 10.0}


def risk(frame, model, params=None, prediction=None):
    out = evaluate(
        frame, [model], None if params is None else {model: params}, prediction=prediction
    )
    return out[model]


# ---------------------------------------------------------------------- distance models
def test_current_distance_3_4_5():
    f = make([{"path": [[0, 0]], "speed": 0}, {"path": [[3, 4]], "speed": 0}])
    r = risk(f, "current_distance")
    assert np.isnan(r[0])
    assert r[1] == pytest.approx(1 / 6)
    assert risk(f, "current_distance", CurrentDistanceParams(epsilon_m=2.0))[1] == pytest.approx(
        2 / 7
    )


def test_path_distance_parallel_crossing_and_extended():
    f = make(
        [
            {"path": [[0, 0], [100, 0]], "speed": 5.0},
            {"path": [[10, 3], [60, 3]], "speed": 0.0},  # parallel, 3 m away
            {"path": [[50, -5], [50, 5]], "speed": 0.0},  # crosses
            # 2 m long, heading down at 1 m/s: extended to 12 m, reaches the ego path
            {"path": [[0.5, 10], [0.5, 8]], "speed": 1.0, "heading": -math.pi / 2},
        ]
    )
    r = risk(f, "path_distance")
    assert r[1] == pytest.approx(0.25)
    assert r[2] == 1.0
    assert r[3] == 1.0


def test_trajectory_distance_cuts_at_v_times_t():
    # Ego reaches 24 m in 12 s; the agent 12 m up from (40, -30): the cut segments are
    # (0,0)-(24,0) and (40,-30)-(40,-18); the closest points are (24,0) and (40,-18).
    f = make(
        [
            {"path": [[0, 0], [100, 0]], "speed": 2.0},
            {"path": [[40, -30], [40, 30]], "speed": 1.0, "heading": math.pi / 2},
            {"path": [[5, 7], [5, 40]], "speed": 0.0},  # standing: a single point
        ]
    )
    r = risk(f, "trajectory_distance")
    assert r[1] == pytest.approx(1 / (1 + math.sqrt(16**2 + 18**2)))
    assert r[2] == pytest.approx(1 / (1 + 7))
    assert risk(f, "path_distance")[1] == 1.0  # the full paths cross


# ---------------------------------------------------------------------- time models
def test_closest_encounter_crossing_paths():
    # Relative position (20 - 10 s, -30 + 10 s): closest at s = 2.5 s, d = 5 sqrt(2).
    f = make([EGO_EAST, {"path": [[20, -30], [20, 100]], "speed": 10.0, "heading": math.pi / 2}])
    assert risk(f, "closest_encounter")[1] == pytest.approx(1 / (1 + 5 * math.sqrt(2)))


def test_closest_encounter_still_closing_at_the_horizon_is_not_counted():
    # Oncoming on the ego line from 300 m, closing at 15 m/s: after 12 s still 120 m apart.
    f = make([EGO_EAST, {"path": [[300, 0], [-100, 0]], "speed": 5.0, "heading": math.pi}])
    assert risk(f, "closest_encounter")[1] == 0.0
    later = ClosestEncounterParams(encounter_time_max_s=20.0)
    assert risk(f, "closest_encounter", later)[1] == pytest.approx(1 / 121)


def test_closest_encounter_at_constant_distance_is_counted():
    # Same speed on parallel paths: the distance never changes, so the encounter is at
    # s = 0. Rounding noise must not move it to the last step (which gives risk 0): with
    # these numbers the smallest computed distance is at s = T. (Found by hypothesis.)
    x0, v = 1.5093435605671424, 5.509343560567142
    f = make(
        [{"path": [[0, 0], [300, 0]], "speed": v}, {"path": [[x0, 2], [x0 + 300, 2]], "speed": v}]
    )
    want = 1 / (1 + math.hypot(x0, 2))
    assert risk(f, "closest_encounter", prediction=PredictionSettings(6.0, 0.2))[
        1
    ] == pytest.approx(want)


def test_headway_leader_follower_and_standing_ego():
    leader = {"path": [[30, 0.5], [230, 0.5]], "speed": 10.0}  # on the path, 30 m ahead
    behind = {"path": [[-20, 0], [180, 0]], "speed": 5.0}
    f = make([EGO_EAST, leader, behind])
    r = risk(f, "headway")
    assert r[1] == pytest.approx(1 / (1 + 3.0))  # TH = 30 m / 10 m/s = 3 s; R_E = 1/31
    assert r[2] == pytest.approx(1 / 21)  # behind: TH = inf, R_E at s = 0
    assert risk(f, "headway", HeadwayParams(tau_s=2.0))[1] == pytest.approx(2 / 5)
    standing = make([{"path": [[0, 0], [200, 0]], "speed": 0.0}, leader])
    d_now = math.hypot(30, 0.5)
    assert risk(standing, "headway")[1] == pytest.approx(1 / (1 + d_now))  # TH = inf
    # off the path (lateral 3 m > 1.75 m): no headway
    beside = make([EGO_EAST, {"path": [[30, 3], [230, 3]], "speed": 10.0}])
    assert risk(beside, "headway")[1] == pytest.approx(1 / (1 + math.hypot(30, 3)))


def test_headway_2d_crossing_agent():
    # Standing at (40, -20) on a path crossing the ego path at ego arc 40 after 20 m:
    # projected to ego arc 40 - 20 = 20 m, TH = 2 s, R = 1/3. R_E = 1/21 (s = 4 s).
    crossing = {"path": [[40, -20], [40, 20]], "speed": 0.0, "heading": math.pi / 2}
    far = {"path": [[40, -60], [40, 20]], "speed": 0.0, "heading": math.pi / 2}  # projects behind
    parallel = {"path": [[40, -20], [240, -20]], "speed": 0.0}  # never meets
    f = make([EGO_EAST, crossing, far, parallel])
    r = risk(f, "headway_2d")
    assert r[1] == pytest.approx(1 / 3)
    assert r[2] == pytest.approx(1 / 61)
    assert r[3] == pytest.approx(1 / 21)
    plain = risk(f, "headway")
    assert plain[1] == pytest.approx(1 / 21)
    assert risk(f, "headway_2d", Headway2DParams(tau_s=4.0))[1] == pytest.approx(4 / 6)


def test_headway_2d_equals_headway_on_the_ego_path():
    f = make([EGO_EAST, {"path": [[30, 0.5], [230, 0.5]], "speed": 10.0}])
    assert risk(f, "headway_2d")[1] == risk(f, "headway")[1] == pytest.approx(0.25)


# ---------------------------------------------------------------------- stochastic models
def test_circles_standing_agents():
    # ego radius 4/2 + 2 * 0.75 = 3.5; other radius 2/2 + 2 * 0.75 = 2.5
    point = {"path": [[0, 20], [0, 40]], "speed": 0.0, "length": 0.0}
    long = {"path": [[0, 20], [0, 40]], "speed": 0.0, "length": 6.0}  # circles at 18, 20, 22
    close = {"path": [[0, 5], [0, 40]], "speed": 0.0}
    f = make([{"path": [[0, 0], [10, 0]], "speed": 0.0}, point, long, close])
    r = risk(f, "circles")
    assert r[1] == pytest.approx(1 / 15)
    assert r[2] == pytest.approx(1 / 13)
    assert r[3] == 1.0  # overlapping circles: d_c clipped at 0
    assert risk(f, "circles", CirclesParams(n_circles=1))[2] == pytest.approx(1 / 15)
    assert risk(f, "circles", CirclesParams(sigma_scale=0.0))[1] == pytest.approx(1 / 18)


def gaussian_overlap(mu1, cov1, mu2, cov2):
    """Closed form of eq. 10 with numpy's general linear algebra (independent of the model)."""
    s = np.asarray(cov1) + np.asarray(cov2)
    d = np.asarray(mu2, float) - np.asarray(mu1, float)
    return np.linalg.det(2 * np.pi * s) ** -0.5 * np.exp(-0.5 * d @ np.linalg.solve(s, d))


def rot_cov(lon, lat, heading):
    c, s = math.cos(heading), math.sin(heading)
    r = np.array([[c, -s], [s, c]])
    return r @ np.diag([lon**2, lat**2]) @ r.T


def test_gaussian_overlap_closed_form():
    ego = {"path": [[0, 0], [10, 0]], "speed": 0.0}
    ped = {"path": [[3, 1], [3, 5]], "speed": 0.0, "kind": "pedestrian"}
    car45 = {"path": [[2, 2], [12, 12]], "speed": 0.0}
    f = make([ego, ped, car45])
    r = risk(f, "gaussian")
    ego_cov = rot_cov(0.75, 0.33, 0.0)
    assert r[1] == pytest.approx(
        gaussian_overlap([0, 0], ego_cov, [3, 1], rot_cov(0.1, 0.1, 0)), rel=1e-12
    )
    want = gaussian_overlap([0, 0], ego_cov, [2, 2], rot_cov(0.75, 0.33, math.pi / 4))
    assert r[2] == pytest.approx(want, rel=1e-12)


def test_gaussian_is_the_maximum_over_steps():
    # Crossing at the same time: at s = 2 s both are at (20, 0); ego heading x, agent
    # heading y, both vehicles at 10 m/s: sigma_lon = 0.75 + 0.125 * 20 = 3.25,
    # sigma_lat = min(0.33 + 2, 0.5) = 0.5; the sum is isotropic 3.25^2 + 0.5^2.
    f = make([EGO_EAST, {"path": [[20, -20], [20, 100]], "speed": 10.0, "heading": math.pi / 2}])
    var = 3.25**2 + 0.5**2
    assert risk(f, "gaussian")[1] == pytest.approx(1 / (2 * math.pi * var))


@pytest.mark.parametrize(("dt", "tau"), [(0.1, 0.4), (0.5, 0.4), (0.1, 2.0)])
def test_survival_constant_overlap_closed_form(dt, tau):
    # Both standing: P_o is the same p at every step, so S_k = q^k with
    # q = exp(-(p + dt/tau)) and R_S = p (1 - q^n) / (1 - q).
    f = make(
        [{"path": [[0, 0], [10, 0]], "speed": 0.0}, {"path": [[1.5, 0.5], [1.5, 9]], "speed": 0.0}]
    )
    pred = PredictionSettings(horizon_s=12.0, dt_s=dt)
    p = gaussian_overlap(
        [0, 0], rot_cov(0.75, 0.33, 0), [1.5, 0.5], rot_cov(0.75, 0.33, math.pi / 2)
    )
    n = pred.n_steps
    q = math.exp(-(p + dt / tau))
    want = p * (1 - q**n) / (1 - q)
    got = risk(f, "survival", SurvivalParams(escape_time_s=tau), prediction=pred)[1]
    assert got == pytest.approx(want, rel=1e-12)
    assert risk(f, "gaussian", prediction=pred)[1] == pytest.approx(p, rel=1e-12)


# ---------------------------------------------------------------------- candidates, validity
def test_riskiest_candidate_counts_for_agents_and_ego():
    crossing = [[50, -5], [50, 5]]
    parallel = [[50, -5], [150, -5]]
    f2 = make(
        [{"path": [[0, 0], [100, 0]], "speed": 5.0}, {"path": [parallel, crossing], "speed": 0.0}]
    )
    f_par = make([{"path": [[0, 0], [100, 0]], "speed": 5.0}, {"path": parallel, "speed": 0.0}])
    assert risk(f2, "path_distance")[1] == 1.0
    assert risk(f_par, "path_distance")[1] == pytest.approx(1 / 6)
    # the ego's candidates: the riskier one counts too
    ego2 = make(
        [
            {"path": [[[0, 0], [0, 100]], [[0, 0], [100, 0]]], "speed": 5.0},
            {"path": parallel, "speed": 0.0},
        ]
    )
    assert risk(ego2, "path_distance")[1] == pytest.approx(1 / 6)


def test_invalid_agents_get_nan_for_every_model():
    f = make(
        [
            EGO_EAST,
            {"path": [[5, 5]], "speed": 1.0, "valid": False},
            {"path": [[9, 9]], "speed": 0.0},
        ]
    )
    for name, r in evaluate(f).items():
        assert np.isnan(r[0]) and np.isnan(r[1]), name
        assert np.isfinite(r[2]), name
