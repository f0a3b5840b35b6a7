"""Issue 35's planner defects, each on a hand-made case that failed before its fix.

- the reference-end phantom: a constant-speed leader never brakes the IDM ego beyond its
  own IDM term (the reference is long enough, and beyond its ends an agent is off-path);
- the heading at t = 0: a forecast box starts with the recorded heading, not the
  direction of the path's join to the lane centre;
- a stopped ego yields to a crossing pedestrian (arrival timed on the free-road profile);
- the corridor: the ego's half width plus a margin (nuPlan's test), not half a lane;
- the reference: the lane centre line with the ego at its lateral offset (no kink);
- fiss-planner: a top speed from the scene, and a reason for every failure.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from replay.planning import AgentForecasts, EgoState, IdmPlanner, IdmSettings, PlanRequest
from replay.planning.idm import free_road_time_s
from replay.planning.inputs import forecasts_for, plan_request
from replay.planning.path_coords import path_coords
from risk import Frame, Lane, LaneMap

try:
    import fiss_planner  # noqa: F401

    HAS_FISS = True
except ImportError:
    HAS_FISS = False

needs_fiss = pytest.mark.skipif(
    not HAS_FISS, reason="fiss-planner is not installed (pip install 'riskreplay[planner]')"
)


def _frame(rows, paths, kinds=None) -> Frame:
    """Agents as (x, y, heading, speed, length, width); the first is the ego."""
    r = np.array(rows, dtype=float)
    return Frame.from_arrays(
        xy=r[:, :2],
        heading=r[:, 2],
        speed=r[:, 3],
        length=r[:, 4],
        width=r[:, 5],
        paths=[np.asarray(p, dtype=float) for p in paths],
        ego=0,
        ids=list(range(len(rows))),
        kinds=kinds or ["vehicle"] * len(rows),
    )


def _idm_oracle(s0, v_start, v0, leader_x0, leader_v, half_lengths, times, p: IdmSettings):
    """IDM by hand behind a leader at constant speed on a straight road (plain loop)."""
    s, v = [s0], [v_start]
    for k in range(times.size - 1):
        gap = leader_x0 + leader_v * times[k] - sum(half_lengths) - s[k]
        s_star = p.s0_m + max(
            0.0,
            v[k] * p.headway_s + v[k] * (v[k] - leader_v) / (2 * math.sqrt(p.a0_mps2 * p.b_mps2)),
        )
        a = p.a0_mps2 * (1 - (v[k] / v0) ** p.delta - (s_star / gap) ** 2)
        a = min(max(a, -p.max_decel_mps2), p.a0_mps2)
        dt = times[k + 1] - times[k]
        if v[k] + a * dt >= 0:
            s.append(s[k] + v[k] * dt + 0.5 * a * dt * dt)
            v.append(v[k] + a * dt)
        else:
            s.append(s[k] + v[k] ** 2 / (-2 * a))
            v.append(0.0)
    return np.array(s), np.array(v)


# ---------------------------------------------------------------------- the phantom
@pytest.mark.parametrize("leader_x", [30.0, 60.0, 90.0, 99.0])
def test_constant_speed_leader_near_the_old_reference_end_is_plain_idm(leader_x):
    """Ego 10 m/s, target 10 m/s, leader at 10 m/s. The old reference ended 100 m ahead
    (5 s x 10 m/s + 50 m): a leader at 90 m passed it after 1 s, its speed along the
    path fell to 0 and the ego braked for a phantom standing car. Now the plan is IDM
    behind the real leader, step for step."""
    frame = _frame(
        [(0, 0, 0, 10, 4.5, 1.8), (leader_x, 0, 0, 10, 4.5, 1.8)],
        [[(0, 0), (120, 0)], [(leader_x, 0), (leader_x + 60, 0)]],
    )
    req = plan_request(frame, LaneMap(), target_speed_mps=10.0)
    p = IdmSettings()
    plan = IdmPlanner(p).plan(req)
    s0 = float(plan.xy[0, 0])
    s, v = _idm_oracle(s0, 10.0, 10.0, leader_x, 10.0, (2.25, 2.25), plan.times_s, p)
    np.testing.assert_allclose(plan.speed_mps, v, atol=1e-9)
    np.testing.assert_allclose(plan.xy[:, 0], s, atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    leader_x=st.floats(20.0, 99.0),
    leader_v=st.floats(0.5, 25.0),
    ego_v=st.floats(0.0, 25.0),
)
def test_a_leader_passing_the_reference_end_never_brakes_beyond_its_idm_term(
    leader_x, leader_v, ego_v
):
    """A hand-made request whose reference ends 100 m ahead: wherever the constant-speed
    leader is, the ego's acceleration at every step is at least the IDM term of the real
    leader (beyond the end the leader is off-path, so the ego may only accelerate more)."""
    times = np.arange(51) * 0.1
    agents = AgentForecasts(
        ids=[1],
        kinds=[0],
        length_m=[4.5],
        width_m=[1.8],
        times_s=times,
        xy=np.stack([leader_x + leader_v * times, np.zeros_like(times)], 1)[None],
        heading_rad=np.zeros((1, times.size)),
    )
    req = PlanRequest(
        ego=EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=ego_v),
        reference=np.stack([np.arange(-10.0, 101.0), np.zeros(111)], 1),
        target_speed_mps=max(ego_v, 10.0),
        agents=agents,
    )
    p = IdmSettings()
    plan = IdmPlanner(p).plan(req)
    v0 = max(ego_v, 10.0)
    sqrt_ab = 2 * math.sqrt(p.a0_mps2 * p.b_mps2)
    for k in range(times.size - 1):
        v, s = plan.speed_mps[k], plan.xy[k, 0]
        gap = leader_x + leader_v * times[k] - 4.5 - s
        s_star = p.s0_m + max(0.0, v * p.headway_s + v * (v - leader_v) / sqrt_ab)
        own = p.a0_mps2 * (1 - (v / v0) ** p.delta - (s_star / gap) ** 2) if gap > 0 else -1e9
        own = max(own, -p.max_decel_mps2)
        if plan.speed_mps[k + 1] == 0.0:
            continue  # stopped within the step: the rate is not the acceleration
        got = (plan.speed_mps[k + 1] - v) / 0.1
        assert got >= min(own, p.a0_mps2) - 1e-9, (k, got, own)


def test_projections_beyond_the_reference_ends_are_off_path():
    ref = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    xy = np.array([[[-1.0, 0.5], [5.0, 1.0], [20.0, -2.0], [21.0, 0.0]]])
    agents = AgentForecasts(
        ids=[1], kinds=[0], length_m=[1.0], width_m=[1.0], times_s=np.arange(4.0),
        xy=xy, heading_rad=np.zeros((1, 4)),
    )  # fmt: skip
    c = path_coords(ref, agents)
    assert c.on_path.tolist() == [[False, True, True, False]]
    np.testing.assert_allclose(c.offset_m, [[0.5 * 0 + math.hypot(1, 0.5), 1.0, -2.0, 1.0]])


# ---------------------------------------------------------------------- heading at t = 0
def _truck_frame() -> Frame:
    """Ego at 25 m/s in the right lane (y = 0); a 15 m truck 30 m ahead in the left lane
    (centre y = 3.5), 0.8 m off its centre towards the ego, recorded heading 0.001 rad;
    its map path joins its lane centre 2 m ahead (a 0.38 rad segment)."""
    return _frame(
        [(0, 0, 0, 25, 4.5, 1.8), (30, 2.7, 0.001, 20, 15.0, 2.5)],
        [[(0, 0), (400, 0)], [(30, 2.7), (32, 3.5), (400, 3.5)]],
    )


def _two_lane_map() -> LaneMap:
    x = np.array([-100.0, 600.0])
    return LaneMap(
        lanes=(Lane(1, np.stack([x, [0.0, 0.0]], 1)), Lane(2, np.stack([x, [3.5, 3.5]], 1)))
    )


def test_forecast_starts_with_the_recorded_heading_and_turns_over_the_join():
    frame = _truck_frame()
    f = forecasts_for(frame, np.array([1]), np.arange(51) * 0.1)
    assert f.heading_rad[0, 0] == pytest.approx(0.001)
    # on the join (2.15 m at 20 m/s: the first 0.1 s) it stays near the recorded heading
    assert abs(f.heading_rad[0, 1]) < 0.01
    np.testing.assert_allclose(f.heading_rad[0, 2:], 0.0, atol=1e-12)  # the lane beyond


def test_a_truck_in_the_next_lane_is_no_leader():
    req = plan_request(_truck_frame(), _two_lane_map(), target_speed_mps=25.0)
    planner = IdmPlanner()
    plan = planner.plan(req)
    free = planner.plan(req.with_agents(AgentForecasts.empty(req.times_s)))
    np.testing.assert_array_equal(plan.speed_mps, free.speed_mps)
    assert plan.blocking_id == -1
    assert planner.may_matter(req).tolist() == [False]


# ---------------------------------------------------------------------- a stopped ego
def _pedestrian_request(ego_speed: float) -> PlanRequest:
    """A pedestrian crossing 8 m ahead of the ego, on the lane centre at t = 3 s."""
    walk = 1.5
    frame = _frame(
        [(0, 0, 0, ego_speed, 4.5, 1.8), (8.0, -walk * 3.0, math.pi / 2, walk, 0.5, 0.5)],
        [[(0, 0), (300, 0)], [(8.0, -4.5), (8.0, 50.0)]],
        kinds=["vehicle", "pedestrian"],
    )
    return plan_request(frame, LaneMap(), target_speed_mps=10.0)


def test_a_stopped_ego_yields_to_a_crossing_pedestrian():
    """Timed at its current speed (0) the ego never arrived, so it never yielded, drove
    off at IDM's free-road acceleration and reached the crossing with the pedestrian on
    it. Timed on the free-road profile it waits."""
    req = _pedestrian_request(0.0)
    p = IdmSettings()
    plan = IdmPlanner(p).plan(req)
    assert plan.blocking_id == 1
    # it yields from the first step: timed at speed 0 the pedestrian was ignored then,
    # and the ego moved off at the free-road acceleration a0
    assert plan.speed_mps[1] < p.a0_mps2 * 0.1 - 1e-3
    ped = req.agents.xy[0]
    # the pedestrian's box (0.5 m) in the ego's corridor (half width 0.9 m): |y| < 1.15
    in_lane = np.abs(ped[:, 1]) < 0.9 + 0.25
    ego_front = plan.xy[:, 0] + 2.25
    assert (ego_front[in_lane] < 8.0 - 0.25).all()


def test_free_road_time_matches_a_fine_simulation():
    p = IdmSettings()
    for v_start, dist in ((0.0, 8.0), (3.0, 30.0), (9.0, 100.0)):
        v, x, t, dt = v_start, 0.0, 0.0, 1e-4
        while x < dist:
            a = p.a0_mps2 * (1 - (v / 10.0) ** p.delta)
            x += v * dt + 0.5 * a * dt * dt
            v += a * dt
            t += dt
        got = float(free_road_time_s(np.array(dist), v_start, 10.0, p.a0_mps2, p.delta))
        assert got == pytest.approx(t, abs=2e-3)
    assert float(free_road_time_s(np.array(-1.0), 0.0, 10.0, 1.0, 4.0)) == 0.0
    assert float(free_road_time_s(np.array(30.0), 12.0, 10.0, 1.0, 4.0)) == pytest.approx(2.5)


# ---------------------------------------------------------------------- the corridor
def _side_car_request(offset_y: float) -> PlanRequest:
    """A slower car (5 m/s) 30 m ahead, ``offset_y`` to the left of the ego's lane centre."""
    frame = _frame(
        [(0, 0, 0, 10, 4.5, 1.8), (30.0, offset_y, 0.0, 5.0, 4.5, 1.8)],
        [[(0, 0), (300, 0)], [(30.0, offset_y), (300.0, offset_y)]],
    )
    return plan_request(frame, LaneMap(), target_speed_mps=10.0)


@pytest.mark.parametrize(
    ("offset_y", "leads"),
    [
        (2.6, False),  # in the next lane, drifted 0.9 m towards the ego: 0.8 m clear of its path
        (2.05, False),  # 0.25 m clear of the ego's path: beyond the 0.2 m margin
        (1.95, True),  # within the margin of the ego's path
        (0.5, True),  # in the ego's lane
    ],
)
def test_the_corridor_is_the_ego_path_buffered_by_its_half_width(offset_y, leads):
    """The old corridor (half a lane, 1.75 m, plus the box's 0.9 m) took the car at
    2.6 m, whose side never comes within 0.8 m of the ego's path, as a leader."""
    req = _side_car_request(offset_y)
    plan = IdmPlanner().plan(req)
    assert (plan.blocking_id == 1) is leads


def test_the_ego_path_starts_at_the_ego_and_returns_to_the_lane_centre():
    frame = _frame(
        [(0, 0.6, 0.05, 10, 4.5, 1.8)],
        [[(0, 0.6), (2, 0), (300, 0)]],  # a map path: the join to the lane centre y = 0
    )
    req = plan_request(frame, LaneMap(), target_speed_mps=10.0)
    # the reference is the lane centre (no kink at the ego), behind and ahead of it
    np.testing.assert_allclose(req.reference[:, 1], 0.0, atol=1e-12)
    assert req.reference[0, 0] < -4.5
    plan = IdmPlanner().plan(req)
    np.testing.assert_allclose(plan.xy[0], [0.0, 0.6], atol=1e-9)
    assert abs(plan.xy[-1, 1]) < 1e-9  # back on the centre after 30 m
    assert np.all(np.diff(plan.xy[:, 1]) <= 1e-12)  # monotone, no overshoot


# ---------------------------------------------------------------------- fiss-planner
@needs_fiss
def test_frenet_plans_at_motorway_speed_off_the_lane_centre():
    """35 m/s, 0.8 m off the lane centre, heading 0.02 rad: fiss-planner's default top
    speed (30 m/s) rejected every candidate, and the kinked reference did too."""
    from replay.planning.frenet import FrenetPlanner, top_speed_mps

    frame = _frame([(0, 0.8, 0.02, 35, 4.5, 1.8)], [[(0, 0.8), (2, 0), (1000, 0)]])
    req = plan_request(frame, _two_lane_map(), target_speed_mps=36.0)
    assert top_speed_mps(req) == 45.0  # 36 x 1.1 + 2 = 41.6, rounded up to 5 m/s
    plan = FrenetPlanner("fiss_plus").plan(req)
    assert plan.ok, plan.reason
    np.testing.assert_allclose(plan.xy[0], [0.0, 0.8], atol=0.05)


@needs_fiss
def test_frenet_failures_say_why():
    from replay.planning.frenet import failure_reason

    assert failure_reason({"speed": 125, "collision": 0}, 0) == (
        "no feasible path (no agents): speed 125"
    )
    assert failure_reason({"lat_accel": 3, "off_road": 5}, 4, False) == (
        "no feasible path (also without agents): off_road 5, lat_accel 3"
    )
    assert failure_reason({"collision": 10, "safety_distance": 2}, 4, True) == (
        "all candidates collide: collision 10, safety_distance 2"
    )
    assert failure_reason({"collision": 10, "accel": 2}, 4, True).startswith("blocked by agents")
    assert failure_reason({}, 0) == "no candidate generated"


@needs_fiss
def test_a_frenet_failure_names_the_rejections():
    """Boxed in: a car standing across the ego's only lane 5 m ahead at 20 m/s."""
    from replay.planning.frenet import FrenetPlanner

    frame = _frame(
        [(0, 0, 0, 20, 4.5, 1.8), (9.0, 0, math.pi / 2, 0, 4.5, 1.8)],
        [[(0, 0), (500, 0)], [(9.0, 0)]],
    )
    req = plan_request(frame, LaneMap(), target_speed_mps=20.0)
    plan = FrenetPlanner("fiss_plus").plan(req)
    assert not plan.ok
    assert plan.reason.split(":")[0] in {"all candidates collide", "blocked by agents"}
    assert any(word in plan.reason for word in ("collision", "safety_distance"))


@needs_fiss
def test_a_standing_ego_turned_in_its_lane_finds_a_plan():
    """0.6 m off its lane centre, turned 0.2 rad, standing: with the lane-centre
    reference every candidate was off the road until the ego's lane held the ego (the old
    reference started at the ego, offset 0); a 3.4 m wide bus did not fit a 3.5 m lane
    less fiss-planner's margins at all."""
    from replay.planning.frenet import FrenetPlanner

    planner = FrenetPlanner("fiss_plus")
    frame = _frame([(0, -0.6, 0.2, 0.03, 3.8, 1.8)], [[(0, -0.6), (2, 0), (300, 0)]])
    req = plan_request(frame, LaneMap(), target_speed_mps=0.07)
    assert planner.plan(req).ok, planner.plan(req).reason
    bus = _frame([(0, 0.17, 0.0, 0.2, 19.7, 3.4)], [[(0, 0.17), (2, 0), (300, 0)]])
    req = plan_request(bus, LaneMap(), target_speed_mps=4.2)
    assert planner.plan(req).ok, planner.plan(req).reason


@needs_fiss
def test_a_box_overlapping_the_ego_now_is_shrunk_until_clear():
    """A car beside the ego in the next lane whose recorded box comes within
    fiss-planner's lateral collision margin (0.3 m) of the ego's: every candidate started
    in collision and none was found. Its box is shrunk until it clears the ego's, by the
    largest of the scales tried; a car that does not overlap keeps its box."""
    from replay.planning.frenet import FrenetPlanner, box_scales

    frame = _frame(
        [(0, 0, 0, 8.0, 4.5, 1.8), (1.0, 2.0, 0, 8.0, 4.5, 1.8), (40.0, 3.5, 0, 8.0, 4.5, 1.8)],
        [[(0, 0), (300, 0)], [(1.0, 2.0), (3.0, 3.5), (300, 3.5)], [(40.0, 3.5), (300, 3.5)]],
    )
    req = plan_request(frame, _two_lane_map(), target_speed_mps=8.0)
    scale = box_scales(req, 0.5, 0.3)  # agents 1 and 2, in that order
    assert scale[1] == 1.0
    # across: the shrunk half width clears 2.0 - (0.9 + 0.3) = 0.8 m
    assert scale[0] * 0.9 <= 0.8 < (scale[0] + 0.1) * 0.9
    planner = FrenetPlanner("fiss_plus")
    plan = planner.plan(req)
    assert plan.ok, plan.reason
    assert plan.extras["shrunk_agents"] == 1.0
    unshrunk = planner.plan(req.with_agents(req.agents.subset(np.array([True, False]))))
    assert unshrunk.ok  # the one overlapping agent alone is shrunk as well


def _boxes_overlap_by_sampling(a_corners: np.ndarray, b_corners: np.ndarray) -> bool:
    """The obvious oracle: some point of one box lies in the other (a fine grid of each
    box's points tested against the other's half-planes)."""

    def inside(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
        edges = np.roll(corners, -1, axis=0) - corners
        rel = points[:, None, :] - corners[None]
        cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
        return (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)

    def grid(corners: np.ndarray) -> np.ndarray:
        u, v = np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41))
        o, e1, e2 = corners[0], corners[1] - corners[0], corners[3] - corners[0]
        return o + u.reshape(-1, 1) * e1 + v.reshape(-1, 1) * e2

    return bool(
        inside(grid(a_corners), b_corners).any() or inside(grid(b_corners), a_corners).any()
    )


@needs_fiss
@pytest.mark.parametrize("seed", range(4))
def test_overlapping_now_matches_a_sampling_oracle(seed):
    from replay.planning.frenet import overlapping_now

    rng = np.random.default_rng(seed)
    n = 60
    rows = [(0.0, 0.0, rng.uniform(-math.pi, math.pi), 5.0, 4.5, 1.8)]
    rows += [
        (rng.uniform(-7, 7), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi), 0.0,
         rng.uniform(0.5, 12.0), rng.uniform(0.5, 3.0))
        for _ in range(n)
    ]  # fmt: skip
    frame = _frame(rows, [[(0, 0), (1, 0)]] + [[(r[0], r[1])] for r in rows[1:]])
    req = plan_request(frame, LaneMap(), target_speed_mps=5.0)
    got = overlapping_now(req, 0.5, 0.3, np.ones(n))

    def corners(x, y, h, half_l, half_w):
        c, s = math.cos(h), math.sin(h)
        return np.array(
            [[x + c * u * half_l - s * v * half_w, y + s * u * half_l + c * v * half_w]
             for u, v in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        )  # fmt: skip

    ego = corners(0.0, 0.0, rows[0][2], 2.25 + 0.5, 0.9 + 0.3)
    a = req.agents
    want = [
        _boxes_overlap_by_sampling(
            ego, corners(*a.xy[k, 0], a.heading_rad[k, 0], a.length_m[k] / 2, a.width_m[k] / 2)
        )
        for k in range(n)
    ]
    assert 5 < sum(want) < n - 5  # both kinds, plenty of each
    # the grid can miss a sliver of overlap thinner than its spacing: allow those only
    disagree = np.flatnonzero(got != np.array(want))
    assert all(got[k] and not want[k] for k in disagree)
    assert len(disagree) <= 2


@needs_fiss
def test_a_failure_without_any_agent_to_blame_says_so():
    """25 m/s into a right-angle turn 20 m ahead: no candidate keeps within the lateral
    acceleration limit, with or without the car parked far off the road."""
    from replay.planning.frenet import FrenetPlanner

    frame = _frame(
        [(0, 0, 0, 25.0, 4.5, 1.8), (0.0, 200.0, 0, 0.0, 4.5, 1.8)],
        [[(0, 0), (20, 0), (20, -300)], [(0.0, 200.0)]],
    )
    req = plan_request(frame, LaneMap(), target_speed_mps=25.0)
    planner = FrenetPlanner("fiss_plus")
    plan = planner.plan(req)
    assert not plan.ok
    assert plan.reason.startswith("no feasible path (also without agents): ")
    alone = planner.plan(req.with_agents(AgentForecasts.empty(req.times_s)))
    assert alone.reason.startswith("no feasible path (no agents): ")
