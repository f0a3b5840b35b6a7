"""``pdm`` (replay/planning/pdm.py): the PDM-Closed-style planner on the hand-made two-lane
road (tests/planner_scenes.py), the scorer on hand-computed cases, the vectorised box
contacts against a per-pair loop, the emergency brake, and the command line.

The generic planner tests (the stopped car, agents that change nothing, ``may_matter``'s
property test) run for ``pdm`` too, in tests/test_planning.py.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import planner_scenes as ps
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from replay.planning import AgentForecasts, EgoState, PlanRequest, compare_plans, lqr, plan_request
from replay.planning.pdm import (
    MultiMetric,
    PdmPlanner,
    PdmSettings,
    WeightedMetric,
    _centres,
    contacts,
)
from replay.planning.registry import PLANNERS, make_planner
from risk import Kind
from risk.hindsight import box_corners, boxes_overlap


def road_request(agents=ps.OTHERS, **changes) -> PlanRequest:
    req = plan_request(
        ps.road_frame(agents), ps.road_map(), target_speed_mps=ps.EGO_SPEED_MPS, horizon_s=5.0
    )
    return dataclasses.replace(req, **changes) if changes else req


def without(request: PlanRequest, agent_id: int) -> PlanRequest:
    return request.with_agents(request.agents.subset(request.agents.ids != agent_id))


def ego_hits(plan, request: PlanRequest, agent_id: int) -> bool:
    """Whether the plan's ego box overlaps the agent's forecast box at any plan time."""
    a = request.agents.subset(request.agents.ids == agent_id).on_times(plan.times_s)
    ego = request.ego
    return bool(
        boxes_overlap(
            plan.xy[:, 0], plan.xy[:, 1], plan.heading_rad, ego.length_m, ego.width_m,
            a.xy[0, :, 0], a.xy[0, :, 1], a.heading_rad[0], a.length_m[0], a.width_m[0],
        ).any()
    )  # fmt: skip


# ---------------------------------------------------------------------- the road
def test_registered_and_made_by_name():
    assert "pdm" in PLANNERS
    planner = make_planner("pdm")
    assert isinstance(planner, PdmPlanner) and planner.name == "pdm"


def test_stops_for_the_standing_car_and_does_not_hit_it():
    req = road_request()
    plan = PdmPlanner().plan(req)
    assert plan.ok and plan.reason == ""
    np.testing.assert_array_equal(plan.times_s, req.times_s)
    assert not ego_hits(plan, req, ps.STOPPED)
    assert plan.blocking_id == ps.STOPPED
    assert plan.speed_mps[-1] < 0.5 * ps.EGO_SPEED_MPS
    assert np.all(np.diff(plan.speed_mps) <= 1e-9)  # brakes, never speeds up
    # its front stays behind the standing car's rear, in its own lane
    assert (plan.xy[:, 0] + 2.25 < 40.0 - 2.25).all()
    assert np.abs(plan.xy[:, 1]).max() < 0.05 and plan.lane == 0
    assert plan.extras["emergency_brake"] == 0.0
    # long enough, it comes to a stop behind the car without touching it
    long = PdmPlanner().plan(road_request(horizon_s=12.0))
    assert long.stops and not ego_hits(long, road_request(horizon_s=12.0), ps.STOPPED)
    assert long.xy[-1, 0] + 2.25 < 40.0 - 2.25


def test_free_road_accelerates_to_the_target_speed_and_keeps_its_lane():
    slow = EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=4.0, length_m=4.5, width_m=1.8)
    req = road_request([], ego=slow)
    plan = PdmPlanner().plan(req)
    assert plan.ok and plan.blocking_id == -1 and plan.lane == 0
    assert plan.speed_mps[-1] > 0.95 * ps.EGO_SPEED_MPS
    assert plan.speed_mps.max() < ps.EGO_SPEED_MPS + 0.3
    assert np.all(np.diff(plan.speed_mps) >= -1e-9)
    assert np.abs(plan.xy[:, 1]).max() < 1e-9
    assert plan.extras["target_fraction"] == 1.0 and plan.extras["offset_m"] == 0.0
    # already at the target speed: it holds it, exactly on the lane centre
    cruise = PdmPlanner().plan(road_request([]))
    np.testing.assert_allclose(cruise.speed_mps, ps.EGO_SPEED_MPS, atol=1e-9)
    np.testing.assert_allclose(cruise.xy[:, 0], ps.EGO_SPEED_MPS * cruise.times_s, atol=1e-9)


@pytest.mark.parametrize("agent", [ps.ONCOMING, ps.BEHIND, ps.PARKED_OFF_ROAD])
def test_oncoming_behind_and_parked_off_road_change_nothing(agent):
    req = road_request()
    planner = PdmPlanner()
    with_it, without_it = planner.plan(req), planner.plan(without(req, agent))
    np.testing.assert_array_equal(with_it.xy, without_it.xy)
    assert with_it.blocking_id == without_it.blocking_id
    # alone on the road with the ego, too
    alone = road_request([agent])
    free = PdmPlanner().plan(road_request([]))
    assert compare_plans(free, PdmPlanner().plan(alone)).changed is False


def test_may_matter_keeps_the_standing_car_and_drops_far_agents():
    req = road_request()
    matters = dict(zip(req.agents.ids.tolist(), PdmPlanner().may_matter(req).tolist(), strict=True))
    assert matters[ps.STOPPED] and not matters[ps.ONCOMING] and not matters[ps.BEHIND]


def test_emergency_brake_when_a_collision_is_near_at_low_speed():
    """4 m/s, a standing car 2 m ahead (bumper to bumper): every IDM proposal, braking at
    IDM's 3 m/s^2, hits it within 2 s; the brake at 4.05 m/s^2 stops in 1.98 m. PDM as
    published (no braking proposals) brakes so; ours keeps its 8 m/s^2 braking proposal,
    which the tracker follows to rest short of the car."""
    frame = ps.road_frame([ps.STOPPED])
    frame_req = plan_request(frame, ps.road_map(), target_speed_mps=4.0)
    ego = EgoState(xy=np.array([40.0 - 4.5 - 2.0, 0.0]), heading_rad=0.0, speed_mps=4.0)
    req = dataclasses.replace(
        frame_req, ego=ego, reference=np.array([[ego.xy[0], 0.0], [200.0, 0.0]])
    )
    ours = PdmPlanner().plan(req)
    assert ours.extras["brake_proposal"] == 1.0 and ours.extras["emergency_brake"] == 0.0
    assert ours.stops and not ego_hits(ours, req, ps.STOPPED)
    plan = PdmPlanner(PdmSettings(brake_proposals_mps2=())).plan(req)
    assert plan.extras["emergency_brake"] == 1.0
    assert plan.blocking_id == ps.STOPPED
    assert plan.stops and not ego_hits(plan, req, ps.STOPPED)
    np.testing.assert_allclose(np.diff(plan.speed_mps)[:9], -0.405, atol=1e-9)
    # faster than 5 m/s PDM does not brake: it keeps the best proposal
    fast = PdmPlanner(PdmSettings(brake_proposals_mps2=())).plan(
        dataclasses.replace(req, ego=dataclasses.replace(ego, speed_mps=6.0))
    )
    assert fast.extras["emergency_brake"] == 0.0


# ---------------------------------------------------------------------- the scorer by hand
def straight_sim(speeds, ys=None, headings=None, n_t=51, dt=0.1, x0=0.0) -> np.ndarray:
    """Bicycle states (P, T, N_STATE) at constant speed along +x (or ``headings``),
    rear axle half a wheelbase behind centres starting at (x0, y)."""
    p = len(speeds)
    ys = np.zeros(p) if ys is None else np.asarray(ys, dtype=float)
    headings = np.zeros(p) if headings is None else np.asarray(headings, dtype=float)
    t = np.arange(n_t) * dt
    wb = float(lqr.wheelbase_m(4.5))
    sim = np.zeros((p, n_t, lqr.N_STATE))
    for i, (v, y, h) in enumerate(zip(speeds, ys, headings, strict=True)):
        centre = np.stack([x0 + v * t * math.cos(h), y + v * t * math.sin(h)], axis=1)
        sim[i, :, [lqr.StateIndex.REAR_X, lqr.StateIndex.REAR_Y]] = (
            centre - wb / 2 * np.array([math.cos(h), math.sin(h)])
        ).T
        sim[i, :, lqr.StateIndex.HEADING] = h
        sim[i, :, lqr.StateIndex.SPEED] = v
    return sim


def hand_request(agents: list[tuple] | None = None, *, lanes_left=0, lanes_right=0) -> PlanRequest:
    """A straight reference along +x; agents (x, y, heading, speed, kind) at constant
    velocity."""
    times = np.arange(51) * 0.1
    agents = agents or []
    xy = np.array(
        [
            [[x + v * math.cos(h) * t, y + v * math.sin(h) * t] for t in times]
            for x, y, h, v, _ in agents
        ]
    )
    forecasts = AgentForecasts(
        ids=np.arange(len(agents)) + 10,
        kinds=[k for *_, k in agents],
        length_m=np.full(len(agents), 4.5),
        width_m=np.full(len(agents), 1.8),
        times_s=times,
        xy=xy.reshape(len(agents), times.size, 2),
        heading_rad=np.array([[h] * times.size for _, _, h, _, _ in agents]).reshape(
            len(agents), times.size
        ),
    )
    return PlanRequest(
        ego=EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0),
        reference=np.array([[0.0, 0.0], [300.0, 0.0]]),
        target_speed_mps=10.0,
        agents=forecasts,
        lanes_left=lanes_left,
        lanes_right=lanes_right,
    )


def test_progress_ratio_and_the_weighted_mean_by_hand():
    # 10 m/s and 5 m/s straight along the lane: 50 m and 25 m of progress
    scores = PdmPlanner().score(hand_request(), straight_sim([10.0, 5.0]))
    np.testing.assert_allclose(scores.progress_m, [50.0, 25.0])
    np.testing.assert_allclose(scores.multi, 1.0)
    np.testing.assert_allclose(scores.weighted[WeightedMetric.PROGRESS], [1.0, 0.5])
    np.testing.assert_allclose(scores.weighted[WeightedMetric.TTC], 1.0)
    np.testing.assert_allclose(scores.weighted[WeightedMetric.COMFORT], 1.0)
    np.testing.assert_allclose(scores.total, [1.0, (5 * 0.5 + 5 * 1 + 2 * 1) / 12])
    assert np.isinf(scores.collision_step).all()


def test_a_collision_with_a_standing_car_scores_zero():
    # a car standing at x = 30 in the lane: the 10 m/s proposal's front (x + 2.25) meets
    # its rear (27.75) at x = 25.5, t = 2.55 s (step 26); the 5 m/s one ends at x = 25
    # (front 27.25) and never touches it, but its box moved ahead by 0.9 s does (TTC)
    req = hand_request([(30.0, 0.0, 0.0, 0.0, int(Kind.VEHICLE))])
    scores = PdmPlanner().score(req, straight_sim([10.0, 5.0]))
    assert scores.multi[MultiMetric.NO_AT_FAULT_COLLISION].tolist() == [0.0, 1.0]
    assert scores.total[0] == 0.0
    assert scores.collision_step[0] == 26 and scores.collision_row[0] == 0
    assert np.isinf(scores.collision_step[1])
    # the collision zeroes proposal 0's progress: proposal 1 has the best that counts
    np.testing.assert_allclose(scores.weighted[WeightedMetric.PROGRESS], [0.0, 1.0])
    # proposal 1's box moved ahead by up to 0.9 s (checked up to t = 4.1 s, the forecast
    # ending at 5 s) stays behind the car: front 2.25 + 5 t + 4.5 < 27.75 for t < 4.2 s
    assert scores.weighted[WeightedMetric.TTC, 1] == 1.0
    assert scores.total[1] == pytest.approx(1.0)


def test_time_to_collision_by_hand():
    """Braking from 10 m/s at 2 m/s^2 to a stop 0.5 m behind a standing car (front at
    2.25 + 10 t - t^2, the car's rear at 27.75): no collision, but the box moved ahead by
    0.9 s (by v(t) 0.9 = 9 - 1.8 t) reaches the car first at t = 3.6 s:
    11.25 + 8.2 t - t^2 = 27.81 >= 27.75 (27.70 at t = 3.5 s)."""
    sim = straight_sim([10.0])
    t = np.arange(51) * 0.1
    x = 10.0 * t - t * t
    wb = float(lqr.wheelbase_m(4.5))
    sim[0, :, lqr.StateIndex.REAR_X] = x - wb / 2
    sim[0, :, lqr.StateIndex.SPEED] = 10.0 - 2.0 * t
    sim[0, :, lqr.StateIndex.ACCEL] = -2.0
    req = hand_request([(30.0, 0.0, 0.0, 0.0, int(Kind.VEHICLE))])
    scores = PdmPlanner().score(req, sim)
    assert scores.multi[MultiMetric.NO_AT_FAULT_COLLISION, 0] == 1.0
    assert scores.weighted[WeightedMetric.TTC, 0] == 0.0
    assert scores.total[0] == pytest.approx((5 * 1.0 + 5 * 0.0 + 2 * 1.0) / 12)
    # the same braking with the car 1 m further on: the look-ahead never reaches it
    further = PdmPlanner().score(hand_request([(31.0, 0.0, 0.0, 0.0, int(Kind.VEHICLE))]), sim)
    assert further.weighted[WeightedMetric.TTC, 0] == 1.0


def test_a_static_object_halves_the_score_and_a_rear_end_is_not_at_fault():
    other = PdmPlanner().score(
        hand_request([(30.0, 0.0, 0.0, 0.0, int(Kind.OTHER))]), straight_sim([10.0])
    )
    assert other.multi[MultiMetric.NO_AT_FAULT_COLLISION, 0] == 0.5
    # a faster car from behind drives into the ego: not the ego's fault
    rear = PdmPlanner().score(
        hand_request([(-8.0, 0.0, 0.0, 20.0, int(Kind.VEHICLE))]), straight_sim([10.0])
    )
    assert rear.multi[MultiMetric.NO_AT_FAULT_COLLISION, 0] == 1.0
    assert np.isinf(rear.collision_step[0])


def test_a_proposal_off_the_drivable_area_scores_zero():
    # one lane: edges at +-1.75 m, tolerance 0.3 m. 1 m to the side: the corner at
    # 1.9 m is within it; 1.5 m: the corner at 2.4 m is not
    scores = PdmPlanner().score(
        hand_request(), straight_sim([10.0, 10.0, 10.0], ys=[0.0, 1.0, 1.5])
    )
    assert scores.multi[MultiMetric.DRIVABLE_AREA].tolist() == [1.0, 1.0, 0.0]
    assert scores.total[2] == 0.0
    # with a lane to the left the same proposal is on the road
    two = PdmPlanner().score(
        hand_request(lanes_left=1), straight_sim([10.0, 10.0, 10.0], ys=[0.0, 1.0, 1.5])
    )
    assert two.multi[MultiMetric.DRIVABLE_AREA].tolist() == [1.0, 1.0, 1.0]


def test_driving_against_the_reference_direction():
    # backwards along the lane: 1.5 m (ok), 5 m (0.5), 10 m (0)
    sim = straight_sim([0.3, 1.0, 2.0], headings=[math.pi] * 3, x0=20.0)
    req = dataclasses.replace(
        hand_request(), ego=EgoState(xy=np.array([20.0, 0.0]), heading_rad=math.pi, speed_mps=1.0)
    )
    scores = PdmPlanner().score(req, sim)
    assert scores.multi[MultiMetric.DRIVING_DIRECTION].tolist() == [1.0, 0.5, 0.0]


def test_uncomfortable_braking_loses_the_comfort_points():
    sim = straight_sim([10.0, 10.0])
    sim[1, 20:, lqr.StateIndex.ACCEL] = -6.0  # beyond nuPlan's -4.05 m/s^2
    scores = PdmPlanner().score(hand_request(), sim)
    assert scores.weighted[WeightedMetric.COMFORT].tolist() == [1.0, 0.0]


# ---------------------------------------------------------------------- contacts vs a loop
def _polygons_touch(a: np.ndarray, b: np.ndarray) -> bool:
    """The obvious oracle: two convex quadrilaterals (4, 2) touch when an edge of one
    crosses an edge of the other or a corner of one lies inside the other."""

    def cross2(u, v):
        return u[0] * v[1] - u[1] * v[0]

    def inside(p, poly):
        signs = [cross2(poly[(i + 1) % 4] - poly[i], p - poly[i]) for i in range(4)]
        return all(s >= -1e-12 for s in signs) or all(s <= 1e-12 for s in signs)

    def cross(p1, p2, q1, q2):
        d1 = cross2(p2 - p1, q1 - p1)
        d2 = cross2(p2 - p1, q2 - p1)
        d3 = cross2(q2 - q1, p1 - q1)
        d4 = cross2(q2 - q1, p2 - q1)
        return d1 * d2 <= 0 and d3 * d4 <= 0

    if any(inside(p, b) for p in a) or any(inside(p, a) for p in b):
        return True
    return any(
        cross(a[i], a[(i + 1) % 4], b[j], b[(j + 1) % 4]) for i in range(4) for j in range(4)
    )


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_contacts_match_a_per_pair_loop(seed):
    rng = np.random.default_rng(seed)
    n_p, n_t, n_k = 3, 8, 5
    look = np.array([0, 2, 4])
    req = PlanRequest(
        ego=EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=5.0, length_m=rng.uniform(2, 6), width_m=rng.uniform(1, 2.5)),
        reference=np.array([[0.0, 0.0], [50.0, 0.0]]),
        target_speed_mps=5.0,
        agents=AgentForecasts(
            ids=np.arange(n_k), kinds=np.zeros(n_k), length_m=rng.uniform(0.3, 12, n_k),
            width_m=rng.uniform(0.3, 3, n_k), times_s=np.arange(n_t) * 0.1,
            xy=rng.uniform(-8, 8, (n_k, n_t, 2)), heading_rad=rng.uniform(-np.pi, np.pi, (n_k, n_t)),
        ),
        horizon_s=0.7,
    )  # fmt: skip
    sim = np.zeros((n_p, n_t, lqr.N_STATE))
    sim[..., lqr.StateIndex.REAR_X] = rng.uniform(-6, 6, (n_p, n_t))
    sim[..., lqr.StateIndex.REAR_Y] = rng.uniform(-6, 6, (n_p, n_t))
    sim[..., lqr.StateIndex.HEADING] = rng.uniform(-np.pi, np.pi, (n_p, n_t))
    sim[..., lqr.StateIndex.SPEED] = rng.uniform(0, 15, (n_p, n_t))
    sim_xy = _centres(sim, float(lqr.wheelbase_m(req.ego.length_m)))
    c = contacts(req, req.agents, sim, sim_xy, look)
    got = set(
        zip(
            c.proposal.tolist(),
            c.step.tolist(),
            c.lookahead.tolist(),
            c.agent.tolist(),
            strict=True,
        )
    )
    want = set()
    a = req.agents
    for p in range(n_p):
        for t in range(n_t):
            h = sim[p, t, lqr.StateIndex.HEADING]
            shift = sim[p, t, lqr.StateIndex.SPEED] * 0.1
            for d, ahead in enumerate(look):
                if t + ahead >= n_t:
                    continue
                x = sim_xy[p, t, 0] + shift * ahead * math.cos(h)
                y = sim_xy[p, t, 1] + shift * ahead * math.sin(h)
                ego_box = box_corners(x, y, h, req.ego.length_m, req.ego.width_m)
                for k in range(n_k):
                    ta = t + ahead
                    box = box_corners(
                        a.xy[k, ta, 0],
                        a.xy[k, ta, 1],
                        a.heading_rad[k, ta],
                        a.length_m[k],
                        a.width_m[k],
                    )
                    if _polygons_touch(ego_box, box):
                        want.add((p, t, d, k))
    assert got == want


# ---------------------------------------------------------------------- settings, CLI
def test_fewer_proposals_by_settings():
    planner = PdmPlanner(
        PdmSettings(target_fractions=(1.0,), lateral_offsets_m=(0.0,), brake_proposals_mps2=())
    )
    plan = planner.plan(road_request())
    assert plan.extras["proposals"] == 1.0 and not ego_hits(plan, road_request(), ps.STOPPED)


def test_replay_plan_and_run_with_pdm(tmp_path):
    import polars as pl

    from replay.cli.app import main

    scene = ps.write_road_scene(tmp_path / "road.mcap")
    out = tmp_path / "out"
    result = CliRunner().invoke(
        main, ["plan", str(scene), "-o", str(out), "--planner", "pdm", "--filter", "nearest:1",
               "--every", "10", "--no-progress", "--workers", "1"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet")
    assert rows["plan_ok"].all()
    assert set(rows["planner"].to_list()) == {"pdm"}
    first = {r["filter"]: r for r in rows.filter(pl.col("frame") == 0).iter_rows(named=True)}
    assert first["none"]["blocking_id"] == ps.STOPPED
    assert first["nearest:1"]["changed"] is True  # the nearest is the car behind
    run = CliRunner().invoke(
        main, ["run", str(scene), "--planner", "pdm", "-o", str(tmp_path / "r.rrd")]
    )
    assert run.exit_code == 0, run.output
    assert (tmp_path / "r.rrd").stat().st_size > 0


def test_a_reference_without_direction_fails_with_its_reason():
    req = dataclasses.replace(
        hand_request([(30.0, 0.0, 0.0, 0.0, int(Kind.VEHICLE))]), reference=np.zeros((3, 2))
    )
    plan = PdmPlanner().plan(req)
    assert not plan.ok and plan.reason == "the reference path has fewer than two distinct points"
    assert PdmPlanner().may_matter(req).tolist() == [True]


@pytest.mark.parametrize("tracker", ["perfect", "lqr"])
def test_closed_loop_stops_behind_the_standing_car(tracker):
    """Re-planning every 0.1 s for 12 s and following each plan for 0.1 s (perfect or
    LQR tracker), the ego stops behind the standing car without touching it. (The plan
    must not carry the simulation's actuator lag: a plan that did braked a third as hard
    as asked at every re-plan and drove into the car.)"""
    from replay.planning.tracking import VehicleState, make_tracker

    base = road_request([ps.STOPPED])
    follow = make_tracker(tracker)
    planner = PdmPlanner()
    state = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=ps.EGO_SPEED_MPS)
    car = base.agents.xy[0, 0]
    for _ in range(120):
        ego = EgoState(
            xy=state.xy, heading_rad=state.heading_rad, speed_mps=state.speed_mps,
            accel_mps2=state.accel_mps2,
        )  # fmt: skip
        reference = np.array([[state.xy[0], 0.0], [state.xy[0] + 300.0, 0.0]])
        plan = planner.plan(dataclasses.replace(base, ego=ego, reference=reference))
        state = follow.follow(state, plan, 0.1)
        touching = boxes_overlap(
            state.xy[0], state.xy[1], np.asarray(state.heading_rad), np.asarray(4.5),
            np.asarray(1.8), car[0], car[1], np.asarray(0.0), np.asarray(4.5), np.asarray(1.8),
        )  # fmt: skip
        assert not touching
    assert state.speed_mps < 0.2
    gap = (car[0] - 2.25) - (state.xy[0] + 2.25)
    assert 0.5 < gap < 3.0  # IDM's 1 m jam gap, give or take the tracker
    assert abs(state.xy[1]) < 0.1
