"""replay.planning: the interface, inputs from a frame, plan comparison, the planners.

The hand-made two-lane road (tests/planner_scenes.py) has known answers: every planner
brakes or swerves for the car standing in the ego's lane, and the oncoming car far off, the
slower car behind and the car parked off the road change nothing.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import planner_scenes as ps
import pytest
from frames import random_frame
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from replay.planning import (
    PLANNERS,
    AgentForecasts,
    EgoState,
    IdmPlanner,
    IdmSettings,
    NoReferencePath,
    Plan,
    PlannerUnavailable,
    PlanRequest,
    UnknownPlanner,
    available_planners,
    compare_plans,
    forecasts_for,
    make_planner,
    plan_request,
)
from replay.planning.inputs import side_lanes, smooth_polyline
from risk import Frame, Lane, LaneMap, geometry
from risk.errors import RiskReplayError

try:
    import fiss_planner  # noqa: F401

    HAS_FISS = True
except ImportError:
    HAS_FISS = False

needs_fiss = pytest.mark.skipif(
    not HAS_FISS, reason="fiss-planner is not installed (pip install 'riskreplay[planner]')"
)
PLANNER_PARAMS = [
    pytest.param("idm"),
    pytest.param("fop", marks=needs_fiss),
    pytest.param("fiss", marks=needs_fiss),
    pytest.param("fiss_plus", marks=needs_fiss),
    pytest.param("pdm"),
]


def road_request(agents=ps.OTHERS) -> PlanRequest:
    return plan_request(
        ps.road_frame(agents), ps.road_map(), target_speed_mps=ps.EGO_SPEED_MPS, horizon_s=5.0
    )


def without(request: PlanRequest, agent_id: int) -> PlanRequest:
    return request.with_agents(request.agents.subset(request.agents.ids != agent_id))


def simple_plan(xy, *, t=None, stops=False, lane=0, ok=True) -> Plan:
    xy = np.asarray(xy, dtype=float)
    times = np.arange(len(xy)) * 0.5 if t is None else np.asarray(t, dtype=float)
    return Plan(
        ok=ok,
        times_s=times,
        xy=xy,
        heading_rad=np.zeros(len(xy)),
        speed_mps=np.ones(len(xy)),
        plan_ms=1.0,
        stops=stops,
        lane=lane,
    )


# ---------------------------------------------------------------------- compare_plans
def test_compare_identical_plans_is_unchanged():
    a = simple_plan([[0, 0], [1, 0], [2, 0]])
    change = compare_plans(a, a)
    assert change.changed is False and change.max_shift_m == 0.0 and change.why == ""


def test_compare_shift_against_the_tolerance():
    a = simple_plan([[0, 0], [1, 0], [2, 0]])
    # moved sideways by 0.3 m at the last time only, then by 0.6 m
    b = simple_plan([[0, 0], [1, 0], [2, 0.3]])
    c = simple_plan([[0, 0], [1, 0], [2, 0.6]])
    assert compare_plans(a, b).changed is False
    assert compare_plans(a, b).max_shift_m == pytest.approx(0.3)
    assert compare_plans(a, c).changed is True
    assert compare_plans(a, c).max_shift_m == pytest.approx(0.6)
    assert compare_plans(a, c, tolerance_m=1.0).changed is False


def test_compare_over_the_common_horizon_on_another_grid():
    # reference: x = t for t = 0..4 by 0.5; other: x = 1.5 t on 0..2 by 1 (shorter plan).
    ref = simple_plan(np.stack([np.arange(9) * 0.5, np.zeros(9)], 1))
    other = simple_plan([[0, 0], [1.5, 0], [3.0, 0]], t=[0, 1, 2])
    change = compare_plans(ref, other)
    # common times 0..2: the largest gap is at t = 2: 3.0 - 2.0 = 1.0 m
    assert change.max_shift_m == pytest.approx(1.0)
    assert change.changed is True


def test_compare_decisions_count_whatever_the_distance():
    a = simple_plan([[0, 0], [1, 0]])
    assert compare_plans(a, simple_plan([[0, 0], [1, 0]], stops=True)).why == "stop/go"
    assert compare_plans(a, simple_plan([[0, 0], [1, 0]], lane=1)).changed is True
    failed = Plan.failed("no feasible trajectory")
    assert compare_plans(a, failed).changed is True
    assert compare_plans(failed, a).changed is True
    both = compare_plans(failed, failed)
    assert both.changed is None and math.isnan(both.max_shift_m)


# ---------------------------------------------------------------------- types
def test_forecasts_subset_empty_and_resampling():
    times = np.array([0.0, 1.0, 2.0])
    a = AgentForecasts(
        ids=[5, 6],
        kinds=[0, 1],
        length_m=[4.0, 0.5],
        width_m=[2.0, 0.5],
        times_s=times,
        xy=[[[0, 0], [10, 0], [20, 0]], [[0, 5], [0, 6], [0, 7]]],
        heading_rad=[[0, 0, 0], [1, 1, 1]],
    )
    assert a.n == 2
    assert a.subset(np.array([False, True])).ids.tolist() == [6]
    assert a.subset(np.array([1, 0])).ids.tolist() == [6, 5]
    assert AgentForecasts.empty(times).n == 0
    r = a.on_times(np.array([0.5, 1.5, 3.0]))
    np.testing.assert_allclose(r.xy[0], [[5, 0], [15, 0], [20, 0]])
    assert a.on_times(times) is a
    with pytest.raises(ValueError, match="xy"):
        AgentForecasts(
            ids=[1], kinds=[0], length_m=[1], width_m=[1], times_s=times,
            xy=np.zeros((1, 2, 2)), heading_rad=np.zeros((1, 3)),
        )  # fmt: skip


# ---------------------------------------------------------------------- inputs
def test_plan_request_on_the_road():
    req = road_request()
    assert req.agents.ids.tolist() == list(ps.OTHERS)
    # the lane centre from REFERENCE_BEHIND_M + the ego's length behind the ego
    np.testing.assert_allclose(req.reference[0], [-14.5, 0.0])
    # long enough beyond the ego for its 10 m/s over 5 s, the margin and the fastest
    # other agent's travel (10 m/s over 5 s)
    length = geometry.cumulative_lengths(req.reference[None])[0, -1]
    assert length - 14.5 >= 50.0 + 50.0 + 50.0
    # the oncoming lane runs the other way: no usable side lane
    assert (req.lanes_left, req.lanes_right) == (0, 0)
    i = req.agents.ids.tolist().index(ps.ONCOMING)
    np.testing.assert_allclose(req.agents.xy[i, -1], [250.0, ps.LANE_WIDTH_M])
    np.testing.assert_allclose(req.agents.heading_rad[i], np.pi)
    j = req.agents.ids.tolist().index(ps.STOPPED)
    np.testing.assert_allclose(req.agents.xy[j], np.tile([40.0, 0.0], (51, 1)))


def test_side_lanes_counts_parallel_lanes_in_the_same_direction():
    ref = np.array([[0.0, 0.0], [200.0, 0.0]])
    x = np.array([-50.0, 300.0])

    def lane(i, y, forward=True):
        pts = np.stack([x if forward else x[::-1], np.full(2, y)], 1)
        return Lane(i, pts)

    two_left = LaneMap((lane(1, 0), lane(2, 3.5), lane(3, 7.0), lane(4, -3.4)))
    assert side_lanes(ref, two_left, lane_width_m=3.5, stretch_m=50) == (2, 1)
    oncoming = LaneMap((lane(1, 0), lane(2, 3.5, forward=False)))
    assert side_lanes(ref, oncoming, lane_width_m=3.5, stretch_m=50) == (0, 0)
    gap = LaneMap((lane(1, 0), lane(3, 7.0)))  # a lane two widths over, none between
    assert side_lanes(ref, gap, lane_width_m=3.5, stretch_m=50) == (0, 0)
    short = LaneMap((Lane(2, np.array([[150.0, 3.5], [200.0, 3.5]])),))  # only far ahead
    assert side_lanes(ref, short, lane_width_m=3.5, stretch_m=50) == (0, 0)
    assert side_lanes(ref, LaneMap(), lane_width_m=3.5, stretch_m=50) == (0, 0)


def test_smoothing_keeps_lines_and_ends_and_rounds_kinks():
    straight = smooth_polyline(np.array([[0.0, 0.0], [20.0, 0.0]]), spacing_m=1.0, half_window_m=4)
    np.testing.assert_allclose(straight, np.stack([np.arange(21.0), np.zeros(21)], 1), atol=1e-12)
    kinked = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])  # a right angle at (10, 0)
    out = smooth_polyline(kinked, spacing_m=1.0, half_window_m=4)
    np.testing.assert_array_equal(out[[0, -1]], kinked[[0, -1]])
    d = np.diff(out, axis=0)
    turn = np.abs(np.diff(np.unwrap(np.arctan2(d[:, 1], d[:, 0]))))
    # 90 degrees spread over the 9 m window: no turn above about 1/8 of it per metre
    assert turn.max() < math.pi / 2 / 6
    assert turn.sum() == pytest.approx(math.pi / 2)


def test_ego_without_a_path_is_a_clear_error():
    frame = Frame.from_arrays(
        xy=np.array([[0.0, 0.0], [10.0, 0.0]]),
        heading=np.zeros(2),
        speed=np.zeros(2),
        length=np.full(2, 4.5),
        width=np.full(2, 1.8),
        paths=[np.array([[0.0, 0.0]]), np.array([[10.0, 0.0], [20.0, 0.0]])],
        ego=0,
        ids=[7, 8],
    )
    with pytest.raises(NoReferencePath, match=r"ego 7 .* no path") as info:
        plan_request(frame, LaneMap(), target_speed_mps=10.0)
    assert isinstance(info.value, RiskReplayError)
    assert "\n" not in str(info.value)


def _forecast_oracle(frame: Frame, idx: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Plain loop: each agent's first path, extended straight, walked at constant speed."""
    out = np.empty((idx.size, times.size, 2))
    for n, i in enumerate(idx):
        path = frame.agent_paths(int(i))[0]
        speed = float(frame.speed[i])
        need = speed * times[-1] + 1.0
        seg = np.diff(path, axis=0)
        lengths = np.hypot(seg[:, 0], seg[:, 1])
        good = np.flatnonzero(lengths > 0)
        if good.size:
            direction = seg[good[-1]] / lengths[good[-1]]
        else:
            direction = np.array([math.cos(frame.heading[i]), math.sin(frame.heading[i])])
        total = lengths.sum()
        path = np.vstack([path, path[-1] + direction * max(need - total, 0.0)])
        cum = np.r_[0.0, np.cumsum(np.hypot(*np.diff(path, axis=0).T))]
        for k, t in enumerate(times):
            s = min(speed * t, cum[-1])
            out[n, k] = [np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])]
    return out


@pytest.mark.parametrize("seed", range(8))
def test_forecasts_match_a_plain_loop(seed):
    rng = np.random.default_rng(seed)
    frame = random_frame(rng)
    idx = np.flatnonzero(frame.others)
    times = np.arange(11) * 0.5
    got = forecasts_for(frame, idx, times)
    np.testing.assert_allclose(got.xy, _forecast_oracle(frame, idx, times), atol=1e-9)
    assert got.ids.tolist() == frame.ids[idx].tolist()


# ---------------------------------------------------------------------- IDM, by hand
def test_idm_first_step_matches_the_formula():
    """Ego at v = v0 = 10 m/s, a stopped car 40 m ahead (centres): one step by hand."""
    req = road_request([ps.STOPPED])
    p = IdmSettings()
    plan = IdmPlanner(p).plan(req)
    gap = 40.0 - 2.25 - 2.25  # bumper to bumper
    s_star = p.s0_m + 10.0 * p.headway_s + 10.0 * 10.0 / (2 * math.sqrt(p.a0_mps2 * p.b_mps2))
    accel = p.a0_mps2 * (1 - 1.0 - (s_star / gap) ** 2)
    assert plan.speed_mps[1] == pytest.approx(10.0 + accel * 0.1)
    assert plan.blocking_id == ps.STOPPED


def test_idm_free_road_keeps_the_target_speed_along_the_reference():
    req = road_request([])
    plan = IdmPlanner().plan(req)
    np.testing.assert_allclose(plan.speed_mps, 10.0)
    np.testing.assert_allclose(plan.xy[:, 0], 10.0 * plan.times_s, atol=1e-9)
    np.testing.assert_allclose(plan.xy[:, 1], 0.0, atol=1e-9)
    assert plan.blocking_id == -1 and not plan.stops


def _crossing_request(x_cross: float, t_cross: float) -> PlanRequest:
    """A pedestrian crossing the ego's lane at x_cross, on the centre line at t_cross."""
    speed = 1.5
    y0 = -speed * t_cross
    frame = Frame.from_arrays(
        xy=np.array([[0.0, 0.0], [x_cross, y0]]),
        heading=np.array([0.0, math.pi / 2]),
        speed=np.array([10.0, speed]),
        length=np.array([4.5, 0.5]),
        width=np.array([1.8, 0.5]),
        paths=[np.array([[0.0, 0.0], [300.0, 0.0]]), np.array([[x_cross, y0], [x_cross, 50.0]])],
        ego=0,
        ids=[0, 9],
        kinds=["vehicle", "pedestrian"],
    )
    return plan_request(frame, LaneMap(), target_speed_mps=10.0)


def test_idm_yields_to_a_crossing_agent_it_would_meet():
    # on the centre line at t = 3 s, 30 m ahead: the ego at 10 m/s would be there then
    req = _crossing_request(30.0, 3.0)
    plan = IdmPlanner().plan(req)
    assert plan.blocking_id == 9
    assert plan.speed_mps.min() < 6.0
    # and it never reaches the pedestrian while the pedestrian is in the lane
    assert IdmPlanner().may_matter(req).tolist() == [True]


def test_idm_ignores_a_crossing_agent_gone_long_before_the_ego_arrives():
    # 45 m ahead, in the lane from about t = -0.5 to 1.7 s; the ego arrives after 4 s
    req = _crossing_request(45.0, 0.6)
    plan = IdmPlanner().plan(req)
    free = IdmPlanner().plan(req.with_agents(AgentForecasts.empty(req.times_s)))
    assert compare_plans(free, plan).changed is False
    assert plan.blocking_id == -1


# ---------------------------------------------------------------------- the road scene
@pytest.fixture(scope="module")
def road() -> PlanRequest:
    return road_request()


@pytest.mark.parametrize("name", PLANNER_PARAMS)
def test_every_planner_brakes_or_swerves_for_the_stopped_car(name, road):
    planner = make_planner(name)
    plan = planner.plan(road)
    assert plan.ok, plan.reason
    swerves = plan.lane != 0 or np.abs(plan.xy[:, 1]).max() > 1.0
    brakes = plan.speed_mps.min() < ps.EGO_SPEED_MPS - 2.0
    assert brakes or swerves
    # no collision with it: the ego's front stays behind its rear while in its lane
    in_lane = np.abs(plan.xy[:, 1]) < 1.8
    assert (plan.xy[in_lane, 0] + 2.25 < 40.0 - 2.25).all()
    assert plan.blocking_id == ps.STOPPED
    # removing it changes the plan
    free = planner.plan(without(road, ps.STOPPED))
    assert compare_plans(plan, free).changed is True
    np.testing.assert_allclose(free.speed_mps, ps.EGO_SPEED_MPS, atol=0.05)
    assert planner.may_matter(road)[list(road.agents.ids).index(ps.STOPPED)]


@pytest.mark.parametrize("name", PLANNER_PARAMS)
@pytest.mark.parametrize("agent", [ps.ONCOMING, ps.BEHIND, ps.PARKED_OFF_ROAD])
def test_far_behind_and_off_road_agents_change_nothing(name, agent, road):
    planner = make_planner(name)
    change = compare_plans(planner.plan(road), planner.plan(without(road, agent)))
    assert change.changed is False, change.why


@pytest.mark.parametrize("name", PLANNER_PARAMS)
def test_plans_are_repeatable(name, road):
    planner = make_planner(name)
    a, b = planner.plan(road), planner.plan(road)
    np.testing.assert_array_equal(a.xy, b.xy)


# ---------------------------------------------------------------------- may_matter
_PLANNERS: dict[str, object] = {}


def _planner(name: str):
    if name not in _PLANNERS:
        _PLANNERS[name] = make_planner(name)
    return _PLANNERS[name]


def _with_extra_agent(request: PlanRequest, x, y, heading, speed, length, width) -> PlanRequest:
    times = request.times_s
    xy = np.stack([x + speed * math.cos(heading) * times, y + speed * math.sin(heading) * times], 1)
    extra = AgentForecasts(
        ids=[99],
        kinds=[0],
        length_m=[length],
        width_m=[width],
        times_s=times,
        xy=xy[None],
        heading_rad=np.full((1, times.size), heading),
    )
    a = request.agents
    both = AgentForecasts(
        ids=np.r_[a.ids, extra.ids],
        kinds=np.r_[a.kinds, extra.kinds],
        length_m=np.r_[a.length_m, extra.length_m],
        width_m=np.r_[a.width_m, extra.width_m],
        times_s=times,
        xy=np.concatenate([a.xy, extra.xy]),
        heading_rad=np.concatenate([a.heading_rad, extra.heading_rad]),
    )
    return request.with_agents(both)


@pytest.mark.parametrize("name", PLANNER_PARAMS)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(
    near=st.booleans(),
    u=st.floats(0.0, 1.0),
    v=st.floats(0.0, 1.0),
    heading=st.floats(-math.pi, math.pi),
    speed=st.floats(0.0, 25.0),
    length=st.floats(0.3, 12.0),
    width=st.floats(0.3, 3.0),
)
def test_an_agent_that_may_not_matter_never_changes_the_plan(
    name, near, u, v, heading, speed, length, width
):
    """Anywhere within 700 m of the road, or (``near``) in a band of 30 m either side of it
    where the planners' ranges end."""
    planner = _planner(name)
    base = road_request()
    if near:
        x, y = -100.0 + 400.0 * u, -30.0 + 60.0 * v
    else:
        radius, bearing = 700.0 * u, math.pi * (2.0 * v - 1.0)
        x, y = 50.0 + radius * math.cos(bearing), radius * math.sin(bearing)
    req = _with_extra_agent(base, x, y, heading, speed, length, width)
    matters = planner.may_matter(req)
    assert matters.shape == (req.agents.n,)
    assume(not matters[-1])
    with_it, without_it = planner.plan(req), planner.plan(base)
    # not merely within the tolerance: the same plan
    assert with_it.ok == without_it.ok
    np.testing.assert_array_equal(with_it.xy, without_it.xy)
    assert with_it.blocking_id == without_it.blocking_id


@pytest.mark.parametrize("name", PLANNER_PARAMS)
def test_far_agents_in_the_ego_lane_that_may_not_matter_change_nothing(name, road):
    """The likeliest way to be wrong: a leader far ahead in the ego's own lane (car
    following and speed policies look along the lane)."""
    planner = _planner(name)
    reference = planner.plan(road)
    checked = 0
    for x in (300.0, 450.0, 700.0, 1000.0):
        for speed, heading in ((0.0, 0.0), (3.0, 0.0), (10.0, math.pi)):
            req = _with_extra_agent(road, x, 0.0, heading, speed, 4.5, 1.8)
            if planner.may_matter(req)[-1]:
                continue
            checked += 1
            np.testing.assert_array_equal(planner.plan(req).xy, reference.xy)
    assert checked >= 3  # the far ones are skipped


@pytest.mark.parametrize("name", PLANNER_PARAMS)
def test_may_matter_skips_agents_far_away(name, road):
    planner = _planner(name)
    req = _with_extra_agent(road, 3000.0, 3000.0, 0.0, 0.0, 4.5, 1.8)
    assert not planner.may_matter(req)[-1]
    assert planner.may_matter(road.with_agents(AgentForecasts.empty(road.times_s))).shape == (0,)


# ---------------------------------------------------------------------- registry, errors
def test_registry_names_and_unknown_name():
    assert PLANNERS == ("idm", "fop", "fiss", "fiss_plus", "pdm")
    assert "idm" in available_planners()
    with pytest.raises(UnknownPlanner, match="idm, fop, fiss, fiss_plus, pdm"):
        make_planner("astar")


def test_missing_extra_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "fiss_planner", None)  # makes the import fail
    with pytest.raises(PlannerUnavailable) as info:
        make_planner("fop")
    message = str(info.value)
    assert "pip install 'riskreplay[planner]'" in message
    assert "\n" not in message
    assert isinstance(info.value, RiskReplayError)
    assert available_planners() == ("idm", "pdm")


# ---------------------------------------------------------------------- the scene file
def test_road_scene_written_as_mcap_reads_back_and_plans(tmp_path):
    from converters.scene.reader import read_scene

    path = ps.write_road_scene(tmp_path / "road.mcap")
    scene = read_scene(path)
    assert len(scene.frames) == 21 and scene.ego_id == ps.EGO
    assert len(scene.map.lanes) == 2
    req = plan_request(scene.frames[0], scene.map, target_speed_mps=10.0)
    assert req.agents.ids.tolist() == list(ps.OTHERS)
    plan = IdmPlanner().plan(req)
    assert plan.blocking_id == ps.STOPPED


def test_ego_state_checks_its_shape():
    with pytest.raises(ValueError, match="xy"):
        EgoState(xy=np.zeros(3), heading_rad=0.0, speed_mps=1.0)


def _side_lanes_by_loops(reference, lane_map, *, lane_width_m, stretch_m, max_lanes=4):
    """The obvious oracle of inputs.side_lanes: every sample, lane and segment in loops."""
    from replay.planning import inputs as pi

    cum = np.r_[0.0, np.cumsum(np.hypot(*np.diff(reference, axis=0).T))]
    samples = np.arange(0.0, min(stretch_m, cum[-1]) + 1e-9, pi.LANE_SAMPLE_M)
    present = np.zeros((samples.size, 2 * max_lanes + 1), dtype=bool)
    for si, s in enumerate(samples):
        j = min(int(np.searchsorted(cum, s, side="right")) - 1, len(reference) - 2)
        seg = reference[j + 1] - reference[j]
        tan = seg / np.hypot(*seg)
        frac = (s - cum[j]) / max(cum[j + 1] - cum[j], 1e-300)
        p = reference[j] + min(max(frac, 0.0), 1.0) * seg
        normal = np.array([-tan[1], tan[0]])
        for lane in lane_map.lanes:
            c = lane.centerline
            best = None
            for q in range(len(c) - 1):
                ab = c[q + 1] - c[q]
                l2 = ab @ ab
                if l2 <= 0:
                    continue
                t = min(max((p - c[q]) @ ab / l2, 0.0), 1.0)
                foot = c[q] + t * ab
                d2 = (p - foot) @ (p - foot)
                if best is None or d2 < best[0]:
                    best = (d2, foot, ab / np.sqrt(l2))
            if best is None:
                continue
            _, foot, unit = best
            lateral, along = (foot - p) @ normal, (foot - p) @ tan
            k = round(lateral / lane_width_m)
            if (
                unit @ tan >= math.cos(pi.LANE_ANGLE_RAD)
                and abs(lateral - k * lane_width_m) <= pi.LANE_OFFSET_TOLERANCE * lane_width_m
                and abs(along) <= 0.5 * pi.LANE_SAMPLE_M
                and k != 0
                and abs(k) <= max_lanes
            ):
                present[si, k + max_lanes] = True
    usable = present.mean(axis=0) >= pi.LANE_COVERAGE
    left = usable[max_lanes + 1 :]
    right = usable[:max_lanes][::-1]
    run = lambda f: int(np.argmin(f)) if not f.all() else int(f.size)  # noqa: E731
    return run(left), run(right)


@pytest.mark.parametrize("seed", range(12))
def test_side_lanes_match_the_loop_oracle(seed):
    """Random curved roads with lanes at whole and broken lane widths, both directions."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 200.0, 41)
    bend = rng.uniform(-0.004, 0.004)
    centre = np.stack([s, bend * s**2], axis=1)
    d = np.gradient(centre, axis=0)
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.hypot(*d.T)[:, None]
    lanes = []
    for i, offset in enumerate(rng.choice([-7.0, -3.5, -2.0, 3.5, 5.0, 7.0, 10.5], 4)):
        line = centre + (offset + rng.normal(0, 0.3)) * normal
        cut = rng.integers(0, 15)
        line = line[cut : cut + rng.integers(10, 41)]
        if rng.random() < 0.3:
            line = line[::-1]  # an oncoming lane
        if len(line) >= 2:
            lanes.append(Lane(i, line))
    lane_map = LaneMap(lanes=tuple(lanes))
    reference = centre[rng.integers(0, 5) :]
    from replay.planning.inputs import side_lanes

    got = side_lanes(reference, lane_map, lane_width_m=3.5, stretch_m=80.0)
    assert got == _side_lanes_by_loops(reference, lane_map, lane_width_m=3.5, stretch_m=80.0)


def test_coords_cache_serves_subsets_and_never_a_changed_forecast():
    from replay.planning.path_coords import CoordsCache, path_coords

    frame = ps.road_frame()
    request = plan_request(frame, ps.road_map(), target_speed_mps=10.0)
    cache = CoordsCache()
    full = cache.get(request.reference, request.agents)
    sub = request.agents.subset(np.array([2, 0]))
    got = cache.get(request.reference, sub)
    want = path_coords(request.reference, sub)
    assert np.array_equal(got.arc_m, want.arc_m) and np.array_equal(got.along, want.along)
    assert np.array_equal(full.arc_m[[2, 0]], got.arc_m)
    moved = AgentForecasts(
        ids=sub.ids,
        kinds=sub.kinds,
        length_m=sub.length_m,
        width_m=sub.width_m,
        times_s=sub.times_s,
        xy=sub.xy + 3.0,
        heading_rad=sub.heading_rad,
    )  # the same ids, moved: computed afresh
    assert np.array_equal(
        cache.get(request.reference, moved).arc_m, path_coords(request.reference, moved).arc_m
    )


def test_cold_drops_what_an_earlier_call_cached():
    """The study times the all-agents plan and each filter's plan on one request: after
    cold() a call finds nothing cached from the one before (else a filtered plan would
    reuse the all-agents plan's projections and look cheaper than it is)."""
    from replay.planning.idm import IdmPlanner
    from replay.planning.path_coords import CoordsCache
    from replay.planning.types import cold

    planner = IdmPlanner()
    planner._thinned = (np.zeros((2, 2)), np.zeros((2, 2)))
    stale = planner._coords
    assert cold(planner) is planner
    assert planner._thinned is None
    assert isinstance(planner._coords, CoordsCache) and planner._coords is not stale
