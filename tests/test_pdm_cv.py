"""PDM's second forecast hypothesis (``PdmSettings.constant_velocity_s``): every agent is
scored against its map-path forecast and against a constant-velocity forecast (straight
on at its current speed and heading, PDM-Closed's own forecast); a proposal collides at
fault when it does so under either.

Issue 35's 400-ego closed loop: 9 of PDM's 21 at-fault runs came from agents that did not
drive where their one map path said (crossing or oncoming turners, late cut-ins).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import planner_scenes as ps
from test_pdm import hand_request, road_request

from replay.planning import AgentForecasts, EgoState
from replay.planning.pdm import PdmPlanner, PdmSettings, _Hypotheses
from replay.planning.tracking import VehicleState, make_tracker
from risk import Kind
from risk.hindsight import boxes_overlap

#: A car 25 m ahead, 8 m to the right, pointing across the ego's lane (+y) at 4 m/s. Its
#: map path turns right at once into a lane parallel to the ego's (+x at y = -8): that
#: forecast never comes near the ego. Straight on it is in the ego's lane (|y| <= 0.9 m
#: plus its half length) from 1.2 s to 2.8 s, where the ego's front at 10 m/s reaches
#: its near side (x = 24.1 m) at 2.2 s.
START = np.array([25.0, -8.0])
SPEED = 4.0


def _turner(start: np.ndarray = START, *, speed_known: bool = True) -> AgentForecasts:
    """The car's map-path forecast: recorded heading +y now, then along +x."""
    times = np.arange(51) * 0.1
    xy = start[None, :] + np.outer(SPEED * times, [1.0, 0.0])
    heading = np.where(times > 0.0, 0.0, math.pi / 2)
    return AgentForecasts(
        ids=np.array([7]), kinds=np.array([int(Kind.VEHICLE)]), length_m=np.array([4.5]),
        width_m=np.array([1.8]), times_s=times, xy=xy[None], heading_rad=heading[None],
        speed_mps=np.array([SPEED]) if speed_known else None,
    )  # fmt: skip


def _truth_hits(xy: np.ndarray, heading: np.ndarray, times: np.ndarray, start=START) -> bool:
    """Whether the ego's boxes overlap the car where it really drives (straight on)."""
    ax = np.full(times.size, start[0])
    ay = start[1] + SPEED * times
    return bool(
        boxes_overlap(
            xy[:, 0], xy[:, 1], heading, np.asarray(4.5), np.asarray(1.8),
            ax, ay, np.full(times.size, math.pi / 2), np.asarray(4.5), np.asarray(1.8),
        ).any()
    )  # fmt: skip


def test_the_constant_velocity_twin_is_straight_on_at_the_current_speed():
    scored = _Hypotheses.of(_turner(), PdmSettings())
    assert scored.agents.n == 2 and list(scored.owner) == [0, 0]
    assert list(scored.agents.ids) == [7, 7]
    t = scored.agents.times_s
    np.testing.assert_allclose(scored.agents.xy[1, :, 0], 25.0)
    np.testing.assert_allclose(scored.agents.xy[1, :, 1], -8.0 + SPEED * t, atol=1e-12)
    np.testing.assert_allclose(scored.agents.heading_rad[1], math.pi / 2)
    assert list(scored.last_step) == [50, 50]
    # without the request's speed, the forecast's own (4 m/s along its path) is taken
    derived = _Hypotheses.of(_turner(speed_known=False), PdmSettings())
    np.testing.assert_allclose(derived.agents.xy[1], scored.agents.xy[1], atol=1e-9)
    # a 2 s window: checked up to step 20; 0 s: no twin
    assert list(_Hypotheses.of(_turner(), PdmSettings(constant_velocity_s=2.0)).last_step) == [
        50,
        20,
    ]
    assert _Hypotheses.of(_turner(), PdmSettings(constant_velocity_s=0.0)).agents.n == 1


def test_a_crossing_car_the_map_path_misses_is_avoided():
    req = hand_request()
    req = dataclasses.replace(req, agents=_turner())
    plan = PdmPlanner().plan(req)
    assert not _truth_hits(plan.xy, plan.heading_rad, plan.times_s)
    assert plan.extras["target_fraction"] < 1.0 and plan.extras["score"] > 0.0
    # with the map path alone (PDM's scorer on our forecasts) it drives on and hits it
    old = PdmPlanner(PdmSettings(constant_velocity_s=0.0)).plan(req)
    assert old.extras["target_fraction"] == 1.0
    assert _truth_hits(old.xy, old.heading_rad, old.times_s)
    # the same without the request's current speed (derived from the forecast)
    derived = PdmPlanner().plan(dataclasses.replace(req, agents=_turner(speed_known=False)))
    assert not _truth_hits(derived.xy, derived.heading_rad, derived.times_s)


def test_closed_loop_with_the_lqr_tracker_does_not_hit_the_crossing_car():
    """Re-planning every 0.1 s while the car drives straight across and its map path keeps
    saying it turns away: the ego never touches it; with the map path alone it does."""
    follow = make_tracker("lqr")
    base = hand_request()

    def drive(planner: PdmPlanner) -> bool:
        state = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0)
        for k in range(50):
            now = START + np.array([0.0, SPEED * k * 0.1])
            ego = EgoState(
                xy=state.xy, heading_rad=state.heading_rad, speed_mps=state.speed_mps,
                accel_mps2=state.accel_mps2,
            )  # fmt: skip
            req = dataclasses.replace(base, ego=ego, agents=_turner(now))
            state = follow.follow(state, planner.plan(req), 0.1)
            if _truth_hits(state.xy[None], np.asarray([state.heading_rad]), np.zeros(1), start=now):
                return True
        return False

    assert not drive(PdmPlanner())
    assert drive(PdmPlanner(PdmSettings(constant_velocity_s=0.0)))


def test_nothing_changes_where_the_forecasts_agree():
    """Agents that drive straight on along their headings (the twin is their forecast),
    standing agents, and the two-lane road: the plan is the same bit for bit."""
    new, old = PdmPlanner(), PdmPlanner(PdmSettings(constant_velocity_s=0.0))
    straight = [
        (40.0, 0.0, 0.0, 0.0, int(Kind.VEHICLE)),  # standing in the lane
        (10.0, 3.5, 0.0, 12.0, int(Kind.VEHICLE)),  # overtaking in the next lane
        (80.0, -3.5, math.pi, 9.0, int(Kind.VEHICLE)),  # oncoming
        (30.0, -6.0, math.pi / 2, 1.0, int(Kind.PEDESTRIAN)),  # crossing, as forecast
    ]
    for req in (hand_request(straight), road_request(), road_request(horizon_s=8.0)):
        assert _Hypotheses.of(req.agents.on_times(req.times_s), PdmSettings()).agents.n == (
            req.agents.n
        )
        a, b = new.plan(req), old.plan(req)
        for field in ("xy", "heading_rad", "speed_mps"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        assert a.extras == b.extras and a.blocking_id == b.blocking_id


def test_a_twin_far_from_every_proposal_changes_nothing():
    """A car turning far from the ego: it has a twin, which touches no proposal."""
    far = _turner(np.array([25.0, -60.0]))
    req = dataclasses.replace(hand_request(), agents=far)
    assert _Hypotheses.of(far, PdmSettings()).agents.n == 2
    a = PdmPlanner().plan(req)
    b = PdmPlanner(PdmSettings(constant_velocity_s=0.0)).plan(req)
    np.testing.assert_array_equal(a.xy, b.xy)
    np.testing.assert_array_equal(a.speed_mps, b.speed_mps)
    assert not PdmPlanner().may_matter(req).any()


def test_may_matter_reads_the_twin():
    """The crossing car matters through its twin alone (its map path is far from every
    proposal), and removing it changes the plan."""
    req = dataclasses.replace(hand_request(), agents=_turner())
    assert PdmPlanner().may_matter(req).all()
    assert not PdmPlanner(PdmSettings(constant_velocity_s=0.0)).may_matter(req).any()
    assert ps.EGO_SPEED_MPS > 0  # the road module is the shared one


def test_a_constant_velocity_row_that_no_proposal_escapes_is_left_out():
    """A car 3 m ahead and 4 m to the right pointing across the ego's lane at 10 m/s: straight
    on it crosses the ego's front within 0.3 s, whatever the ego does (even the 8 m/s^2
    brake is still moving); its map path turns away along +x. That row cannot tell the
    proposals apart, so it is left out: the plan is the map-path one, bit for bit. Kept,
    it zeroes every proposal."""
    times = np.arange(51) * 0.1
    start = np.array([3.0, -4.0])
    forecast = AgentForecasts(
        ids=np.array([9]), kinds=np.array([int(Kind.VEHICLE)]), length_m=np.array([4.5]),
        width_m=np.array([1.8]), times_s=times,
        xy=(start[None, :] + np.outer(10.0 * times, [1.0, 0.0]))[None],
        heading_rad=np.where(times > 0.0, 0.0, math.pi / 2)[None], speed_mps=np.array([10.0]),
    )  # fmt: skip
    req = dataclasses.replace(hand_request(), agents=forecast)
    plan = PdmPlanner().plan(req)
    path_only = PdmPlanner(PdmSettings(constant_velocity_s=0.0)).plan(req)
    np.testing.assert_array_equal(plan.xy, path_only.xy)
    np.testing.assert_array_equal(plan.speed_mps, path_only.speed_mps)
    assert plan.extras == path_only.extras and plan.extras["score"] > 0.0
    kept = PdmPlanner(PdmSettings(drop_unavoidable_twins=False)).plan(req)
    assert kept.extras["score"] == 0.0
