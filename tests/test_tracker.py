"""The trackers (replay/planning/tracking.py, replay/planning/lqr.py): the kinematic bicycle
by hand, the LQR's closed-form lateral response against PDM's matrix products, and the
``lqr`` tracker on straight, curved, offset and braking plans with stated errors.

Stated errors of ``lqr`` (measured; PDM-Closed's weights, 4.5 m car, 10 m/s, 5 s):

- straight constant-speed plan, starting on it: 0 (to rounding);
- circle of radius 100 m / 50 m, starting at the bicycle's steady steering angle: within
  0.2 m / 0.35 m and 0.03 rad / 0.05 rad of the plan (0.12 m / 0.23 m measured);
- the same circles starting with the wheels straight (a steering step): within 0.35 m /
  0.6 m and 0.05 rad / 0.09 rad (0.22 m / 0.46 m measured);
- 1 m to the side of a straight plan: within 0.25 m of it from 2 s on and 0.1 m from 6 s
  on (one overshoot of 0.21 m at 2.5 s);
- braking from 20 m/s at 4 m/s^2 to a stop: within 0.6 m of the plan (0.51 m measured).
  PDM's speed-only longitudinal LQR (``q_position=0``) runs 0.4 m/s above such a plan and
  comes to rest 4.5 m beyond it; the position term (``q_position``, our addition) removes that.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from replay.planning.errors import PlanningError
from replay.planning.lqr import (
    N_STATE,
    LqrTracker,
    StateIndex,
    TrackerSettings,
    TrackingProblem,
    _lateral_response,
    bicycle_step,
    centre_xy,
    curvature_moments,
    lqr_commands,
    rear_axle_xy,
    reference_from_centres,
    wheelbase_m,
)
from replay.planning.tracking import PerfectTracker, Tracker, VehicleState, make_tracker
from replay.planning.types import Plan

TIMES = np.arange(51) * 0.1
LENGTH_M = 4.5
WHEELBASE = float(wheelbase_m(LENGTH_M))


def straight_plan(speed=10.0, heading=0.0, start=(0.0, 0.0)) -> Plan:
    d = np.array([math.cos(heading), math.sin(heading)])
    xy = np.asarray(start)[None, :] + (speed * TIMES)[:, None] * d[None, :]
    return Plan(
        ok=True,
        times_s=TIMES,
        xy=xy,
        heading_rad=np.full(TIMES.size, heading),
        speed_mps=np.full(TIMES.size, speed),
        plan_ms=0.0,
    )


def circle_plan(radius: float, speed: float) -> Plan:
    """Box centres on a circle turning left from the origin, heading along it."""
    angle = speed * TIMES / radius
    xy = np.stack([radius * np.sin(angle), radius * (1.0 - np.cos(angle))], axis=1)
    return Plan(
        ok=True, times_s=TIMES, xy=xy, heading_rad=angle,
        speed_mps=np.full(TIMES.size, speed), plan_ms=0.0,
    )  # fmt: skip


def braking_plan(v0: float, decel: float) -> Plan:
    v = np.maximum(v0 - decel * TIMES, 0.0)
    x = np.r_[0.0, np.cumsum((v[1:] + v[:-1]) / 2.0 * 0.1)]
    return Plan(
        ok=True, times_s=TIMES, xy=np.stack([x, np.zeros_like(x)], 1),
        heading_rad=np.zeros_like(x), speed_mps=v, plan_ms=0.0,
    )  # fmt: skip


def errors(plan: Plan, start: VehicleState, durations) -> np.ndarray:
    """Rows (position error m, signed lateral error m, heading error rad) of lqr against
    the plan's own state at each duration."""
    lqr, perfect = LqrTracker(), PerfectTracker()
    out = []
    for d in durations:
        a, b = lqr.follow(start, plan, float(d)), perfect.follow(start, plan, float(d))
        dx, dy = a.xy - b.xy
        lateral = -dx * math.sin(b.heading_rad) + dy * math.cos(b.heading_rad)
        heading = (a.heading_rad - b.heading_rad + math.pi) % (2 * math.pi) - math.pi
        out.append((math.hypot(dx, dy), lateral, heading))
    return np.array(out)


# ---------------------------------------------------------------------- the bicycle
def test_bicycle_step_by_hand():
    """10 m/s along +x with the wheels at 0.1 rad: x moves 1 m, heading turns
    dt v tan(0.1) / L; a 2 m/s^2 command through the 0.2 s lag gives a third of it."""
    s = TrackerSettings()
    state = np.zeros((1, N_STATE))
    state[0, StateIndex.SPEED] = 10.0
    state[0, StateIndex.STEER] = 0.1
    out = bicycle_step(state, np.array([2.0]), np.array([0.0]), 0.1, np.array([2.7]), s)
    assert out[0, StateIndex.REAR_X] == pytest.approx(1.0)
    assert out[0, StateIndex.REAR_Y] == pytest.approx(0.0)
    assert out[0, StateIndex.HEADING] == pytest.approx(0.1 * 10.0 * math.tan(0.1) / 2.7)
    assert out[0, StateIndex.ACCEL] == pytest.approx(2.0 * 0.1 / 0.3)
    assert out[0, StateIndex.SPEED] == pytest.approx(10.0 + 0.1 * 2.0 / 3.0)
    assert out[0, StateIndex.STEER] == pytest.approx(0.1)


def test_bicycle_never_reverses_and_clips_its_commands():
    s = TrackerSettings()
    state = np.zeros((2, N_STATE))
    state[:, StateIndex.SPEED] = [0.3, 5.0]
    state[:, StateIndex.ACCEL] = [-8.0, 0.0]
    out = bicycle_step(state, np.array([-100.0, 100.0]), np.array([100.0, -100.0]), 0.1, 2.7, s)
    assert out[0, StateIndex.SPEED] == 0.0 and out[0, StateIndex.ACCEL] == pytest.approx(-3.0)
    assert out[1, StateIndex.ACCEL] == s.max_accel_mps2
    assert out[0, StateIndex.STEER] == pytest.approx(s.max_steer_rad)
    assert out[1, StateIndex.STEER] == pytest.approx(-s.max_steer_rad)


def test_rear_axle_and_centre_convert_both_ways():
    xy = np.array([[3.0, 4.0]])
    rear = rear_axle_xy(xy, np.array([math.pi / 2]), np.array([2.0]))
    np.testing.assert_allclose(rear, [[3.0, 3.0]])
    np.testing.assert_allclose(centre_xy(rear, np.array([math.pi / 2]), np.array([2.0])), xy)
    assert wheelbase_m(5.176) == pytest.approx(3.1056)  # a Pacifica: 3.089 m really


# ---------------------------------------------------------------------- the LQR
def _lateral_by_matrices(v, kappa, dt, wheelbase):
    """PDM's construction: the product of the n Euler step matrices (a plain loop)."""
    a, b, g = np.eye(3), np.zeros(3), np.zeros(3)
    for vi, ki in zip(v, kappa, strict=True):
        step = np.eye(3)
        step[0, 1] = vi * dt
        step[1, 2] = vi * dt / wheelbase
        a = step @ a
        b = step @ b + np.array([0.0, 0.0, dt])
        g = step @ g + np.array([0.0, -vi * ki * dt, 0.0])
    return a, b, g


@pytest.mark.parametrize("seed", range(6))
def test_lateral_response_matches_the_matrix_products(seed):
    rng = np.random.default_rng(seed)
    batch, n, length, dt = 5, 10, 30, 0.1
    v0 = rng.uniform(0.0, 30.0, batch)
    accel = rng.uniform(-6.0, 3.0, batch)
    wb = rng.uniform(1.0, 6.0, batch)
    kappa = rng.uniform(-0.2, 0.2, (batch, length))
    moments = curvature_moments(kappa, n)
    for k in (0, 7, length - 3):
        free, g = _lateral_response(v0, accel, moments[:, k], dt, wb, n)
        for b in range(batch):
            window = kappa[b, np.minimum(np.arange(k, k + n), length - 1)]
            a_m, b_m, g_m = _lateral_by_matrices(
                v0[b] + accel[b] * dt * np.arange(n), window, dt, wb[b]
            )
            np.testing.assert_allclose(
                free[b, :3], a_m[[0, 0, 1], [1, 2, 2]], rtol=1e-12, atol=1e-12
            )
            np.testing.assert_allclose(free[b, 3:], b_m[:2], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(g[b], g_m[:2], rtol=1e-12, atol=1e-12)
            # the rest of A is the identity, B2 = n dt, g2 = 0
            assert a_m[0, 0] == a_m[1, 1] == a_m[2, 2] == 1.0 and a_m[2, :2].tolist() == [0, 0]
            assert b_m[2] == pytest.approx(n * dt) and g_m[2] == 0.0


# ---------------------------------------------------------------------- the tracker
def test_make_tracker_gives_the_lqr_tracker():
    tracker = make_tracker("lqr")
    assert isinstance(tracker, LqrTracker) and isinstance(tracker, Tracker)
    assert tracker.name == "lqr"
    with pytest.raises(PlanningError, match="perfect, lqr"):
        make_tracker("pid")


@settings(max_examples=40, deadline=None)
@given(
    speed=st.floats(0.5, 35.0),
    heading=st.floats(-math.pi, math.pi),
    x=st.floats(-1e3, 1e3),
    y=st.floats(-1e3, 1e3),
    duration=st.floats(0.05, 6.0),
)
def test_starting_on_a_straight_constant_speed_plan_leaves_no_error(speed, heading, x, y, duration):
    plan = straight_plan(speed, heading, (x, y))
    start = VehicleState(xy=np.array([x, y]), heading_rad=heading, speed_mps=speed)
    got = LqrTracker().follow(start, plan, duration)
    want = PerfectTracker().follow(start, plan, duration)
    np.testing.assert_allclose(got.xy, want.xy, atol=1e-6)
    assert math.cos(got.heading_rad - heading) == pytest.approx(1.0, abs=1e-12)
    assert got.speed_mps == pytest.approx(speed, abs=1e-9)
    assert got.steer_rad == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    ("radius", "steady", "max_pos", "max_heading"),
    [
        (100.0, True, 0.2, 0.03),
        (50.0, True, 0.35, 0.05),
        (100.0, False, 0.35, 0.05),
        (50.0, False, 0.6, 0.09),
    ],
)
def test_follows_a_circle_within_the_stated_error(radius, steady, max_pos, max_heading):
    plan = circle_plan(radius, 10.0)
    steer = math.atan(WHEELBASE / radius) if steady else 0.0
    start = VehicleState(xy=plan.xy[0], heading_rad=0.0, speed_mps=10.0, steer_rad=steer)
    e = errors(plan, start, np.arange(0.5, 4.51, 0.5))
    assert e[:, 0].max() < max_pos
    assert np.abs(e[:, 2]).max() < max_heading
    # and it turns the right way: about the plan's heading change after 4.5 s
    end = LqrTracker().follow(start, plan, 4.5)
    assert end.heading_rad == pytest.approx(10.0 * 4.5 / radius, abs=max_heading)


def test_converges_from_a_lateral_offset():
    plan = straight_plan(10.0)
    start = VehicleState(xy=np.array([0.0, 1.0]), heading_rad=0.0, speed_mps=10.0)
    e = errors(plan, start, np.arange(0.5, 8.01, 0.5))
    lateral = np.abs(e[:, 1])
    assert lateral[0] > 0.9  # still near the start after 0.5 s: no jump
    assert lateral[3:].max() < 0.25  # from 2 s on
    assert lateral[11:].max() < 0.1  # from 6 s on


def test_respects_the_steering_and_acceleration_limits():
    s = TrackerSettings()
    tight = circle_plan(1.0, 3.0)  # needs more steering than the limit allows
    start = VehicleState(xy=tight.xy[0], heading_rad=0.0, speed_mps=3.0)
    steer = [LqrTracker().follow(start, tight, d).steer_rad for d in np.arange(0.1, 3.01, 0.1)]
    assert max(abs(x) for x in steer) <= s.max_steer_rad + 1e-12
    assert max(abs(x) for x in steer) == pytest.approx(s.max_steer_rad)  # it saturates
    hard = braking_plan(20.0, 10.0)  # 10 m/s^2 asked, 8 allowed
    start = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=20.0)
    accel = [LqrTracker().follow(start, hard, d).accel_mps2 for d in np.arange(0.1, 3.01, 0.1)]
    assert min(accel) >= -s.max_decel_mps2 - 1e-12
    assert min(accel) == pytest.approx(-s.max_decel_mps2)


def test_perfect_and_lqr_on_the_same_plans():
    """Equal on a constant-speed straight plan; on a braking plan within 0.6 m; PDM's
    speed-only longitudinal LQR lags the braking plan by metres."""
    start = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0)
    plan = straight_plan(10.0)
    a = LqrTracker().follow(start, plan, 3.0)
    b = PerfectTracker().follow(start, plan, 3.0)
    np.testing.assert_allclose(a.xy, b.xy, atol=1e-9)
    brake = braking_plan(20.0, 4.0)
    start = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=20.0)

    def gaps(tracker: LqrTracker) -> np.ndarray:
        out = []
        for d in np.arange(0.5, 6.01, 0.5):
            a = tracker.follow(start, brake, float(d))
            b = PerfectTracker().follow(start, brake, float(d))
            assert abs(a.xy[1]) < 1e-9
            out.append(a.xy[0] - b.xy[0])
        return np.array(out)

    ours = gaps(LqrTracker())
    assert np.abs(ours).max() < 0.6
    speed_only = gaps(LqrTracker(TrackerSettings(q_position=0.0)))
    assert speed_only.min() > 0.0 and speed_only[-1] > 3.0  # behind schedule, stops late


def test_past_the_plan_end_it_holds_the_last_speed_and_heading():
    plan = straight_plan(10.0)
    short = Plan(
        ok=True, times_s=plan.times_s[:11], xy=plan.xy[:11], heading_rad=plan.heading_rad[:11],
        speed_mps=plan.speed_mps[:11], plan_ms=0.0,
    )  # fmt: skip
    start = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0)
    end = LqrTracker().follow(start, short, 3.0)
    np.testing.assert_allclose(end.xy, [30.0, 0.0], atol=1e-9)
    assert end.speed_mps == pytest.approx(10.0)


def test_state_carries_over_between_calls():
    """Two calls of 0.5 s from the state the first ends in equal one of 1 s when the plan
    is shifted by 0.5 s (the tracker keeps no memory of its own)."""
    plan = circle_plan(50.0, 10.0)
    start = VehicleState(xy=plan.xy[0], heading_rad=0.0, speed_mps=10.0)
    one = LqrTracker().follow(start, plan, 1.0)
    half = LqrTracker().follow(start, plan, 0.5)
    shifted = Plan(
        ok=True, times_s=plan.times_s[:-5], xy=plan.xy[5:], heading_rad=plan.heading_rad[5:],
        speed_mps=plan.speed_mps[5:], plan_ms=0.0,
    )  # fmt: skip
    two = LqrTracker().follow(half, shifted, 0.5)
    np.testing.assert_allclose(two.xy, one.xy, atol=1e-9)
    assert two.steer_rad == pytest.approx(one.steer_rad, abs=1e-12)


# ---------------------------------------------------------------------- stopping
EMERGENCY_DECEL = 4.05  # PDM's emergency brake (m/s^2)


def brake_from(state: VehicleState, decel: float = EMERGENCY_DECEL) -> Plan:
    """A plan braking at ``decel`` from ``state`` (its pose, its speed) to rest, then
    standing: PDM's emergency brake as the closed loop re-plans it every 0.1 s."""
    t = np.arange(41) * 0.1
    v = np.maximum(state.speed_mps - decel * t, 0.0)
    s = np.r_[0.0, np.cumsum((v[1:] + v[:-1]) / 2.0 * 0.1)]
    ahead = np.array([math.cos(state.heading_rad), math.sin(state.heading_rad)])
    return Plan(
        ok=True, times_s=t, xy=state.xy[None, :] + s[:, None] * ahead[None, :],
        heading_rad=np.full(t.size, state.heading_rad), speed_mps=v, plan_ms=0.0,
    )  # fmt: skip


def stop_time_and_distance(v0: float, replan: bool) -> tuple[float, float, VehicleState]:
    """Time (s) and distance (m) until the lqr vehicle, from ``v0`` with no acceleration
    yet, is below nuPlan's stopped speed (0.05 m/s) on an emergency-brake plan followed
    in steps of 0.1 s: re-planned from the vehicle's state at every step (the closed
    loop), or the first plan throughout; and the state then."""
    start = VehicleState(xy=np.array([3.0, -2.0]), heading_rad=0.4, speed_mps=v0)
    first, state, tracker = brake_from(start), start, LqrTracker()
    for k in range(1, 60):
        plan = brake_from(state) if replan else first
        state = tracker.follow(state if replan else start, plan, 0.1 if replan else 0.1 * k)
        if state.speed_mps < 0.05:
            return 0.1 * k, float(np.hypot(*(state.xy - start.xy))), state
    raise AssertionError("never stopped")


@pytest.mark.parametrize("replan", [True, False])
@pytest.mark.parametrize("v0", [1.0, 3.2])
def test_an_emergency_brake_is_followed_to_rest_within_the_actuator_lag(v0, replan):
    """The plan stops in v0 / 4.05 s over v0^2 / 8.1 m; the vehicle, its acceleration
    lagging 0.2 s behind the command, is below 0.05 m/s within 0.3 s more (the lag and one
    re-planning step) and v0 * 0.3 m further. Measured: from 1 m/s 0.5 s, 0.31 m re-planned
    (0.4 s, 0.27 m on one plan); from 3.2 m/s 1.0 s, 1.95 m (0.8 s, 1.68 m). The tracker
    before the stop horizon (the look-ahead held at 1 s, a stop gain of 0.5 /s) took
    1.5 s, 0.65 m and 1.7 s, 2.39 m re-planned."""
    time_s, distance_m, _ = stop_time_and_distance(v0, replan)
    assert time_s <= v0 / EMERGENCY_DECEL + 0.3 + 1e-9
    assert distance_m <= v0 * v0 / (2.0 * EMERGENCY_DECEL) + 0.3 * v0


@pytest.mark.parametrize("v0", [1.0, 3.2])
def test_once_stopped_it_holds_still(v0):
    """Re-planned on after it is below 0.05 m/s, the vehicle is at rest (speed exactly 0)
    within 0.2 s and then stands for 2 s without moving (the former stop controller, from
    1 m/s, was still at 0.008 m/s 2 s later and crept on 37 mm)."""
    _, _, state = stop_time_and_distance(v0, replan=True)
    tracker = LqrTracker()
    for _ in range(2):
        state = tracker.follow(state, brake_from(state), 0.1)
    assert state.speed_mps == 0.0
    stopped_at = state.xy
    for _ in range(20):
        state = tracker.follow(state, brake_from(state), 0.1)
        assert state.speed_mps == 0.0
    np.testing.assert_array_equal(state.xy, stopped_at)


def test_a_slow_vehicle_on_a_standing_plan_stops_at_once():
    """At 0.19 m/s (below the stop controller's 0.2 m/s) behind a plan that stands, the
    vehicle is at rest within 0.3 s (the former proportional controller, gain 0.5 /s, was
    still above 0.05 m/s after 2.5 s)."""
    start = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=0.19)
    plan = braking_plan(0.0, 1.0)  # standing at the start
    assert LqrTracker().follow(start, plan, 0.3).speed_mps == 0.0


def test_a_stop_horizon_shorter_than_the_look_ahead_is_the_lqr_over_it():
    """The longitudinal command when the reference comes to rest m < n steps ahead is the
    one-step LQR over m steps (speed and position at the rest index, input weight
    r (m / n)^2), by hand: 1 m/s, the plan at rest from index 3 (v = 1, 0.595, 0.19, 0)."""
    s = TrackerSettings()
    plan = brake_from(VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=1.0))
    grid = np.arange(20) * 0.1
    xy = np.stack([np.interp(grid, plan.times_s, plan.xy[:, 0]), np.zeros(20)], 1)
    v = np.interp(grid, plan.times_s, plan.speed_mps)
    ref = reference_from_centres(xy[None], np.zeros((1, 20)), v[None], np.array([WHEELBASE]))
    problem = TrackingProblem.of(ref, np.array([WHEELBASE]), s)
    state = np.zeros((1, N_STATE))
    state[0, :2] = ref.rear_xy[0, 0]
    state[0, StateIndex.SPEED] = 1.0
    accel, _ = lqr_commands(state, problem, 0)
    m = 2  # v[2] = 0.19 <= stop_speed_mps: the reference is at rest (for the tracker) there
    assert v[2] <= s.stop_speed_mps < v[1]
    b_v, b_s = m * s.dt_s, s.dt_s**2 * m * (m - 1) / 2
    to_go = (xy[m, 0] - xy[0, 0]) - m * s.dt_s * 1.0
    num = s.q_speed * b_v * (v[m] - 1.0) + s.q_position * b_s * to_go
    den = s.q_speed * b_v**2 + s.q_position * b_s**2 + s.r_accel * (m / s.horizon_steps) ** 2
    assert accel[0] == pytest.approx(num / den, rel=1e-12)
    assert accel[0] < -3.5  # near the plan's 4.05 m/s^2 (-3.78; the 1 s look-ahead: -1.57)
