"""The synthetic intersection: geometry, situation sampling, IDM motion, determinism."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from converters.errors import ConversionError
from converters.intersection import (
    TURNS,
    IntersectionSettings,
    build_intersection,
    forward_paths,
    lane_at,
    pose,
)
from converters.synthetic import (
    IdmSettings,
    SyntheticSettings,
    Traffic,
    boxes_overlap,
    generate_scene,
    generate_situation,
    idm_accel,
    route_gaps,
    spawn,
    step,
)

WORLD = build_intersection()
H = IntersectionSettings().box_half_m  # 2 * 3.5 + 6 = 13 m


# ---------------------------------------------------------------------- geometry


def test_box_and_lane_layout():
    assert H == 13.0
    lanes = WORLD.lane_map.lanes
    roles = WORLD.lane_role
    # 4 arms x 2 lanes in and out, plus per arm 2 straight + 1 left + 1 right connectors.
    assert roles.count("incoming") == 8 and roles.count("outgoing") == 8
    assert roles.count("connector") == 16
    east_in = [lane for lane, r in zip(lanes, roles, strict=True) if r == "incoming"][:2]
    # East arm, westbound, right-hand traffic: inner lane at y = 1.75, outer at y = 5.25.
    np.testing.assert_allclose(east_in[0].centerline, [[163.0, 1.75], [13.0, 1.75]])
    np.testing.assert_allclose(east_in[1].centerline, [[163.0, 5.25], [13.0, 5.25]])
    by_id = WORLD.lane_map.by_id()
    for lane in lanes:
        for succ in lane.successors:  # successors start where the lane ends
            np.testing.assert_allclose(by_id[succ].centerline[0], lane.centerline[-1])


def test_route_lengths_and_turn_radii():
    r = WORLD.routes
    arm, w, corner = 150.0, 3.5, 6.0
    straight = r.turn == TURNS.index("straight")
    np.testing.assert_allclose(r.length_m[straight], 2 * arm + 2 * H)
    # Quarter circles: left radius h + w/2 = 14.75 m, right radius corner + w/2 = 7.75 m,
    # sampled as chords every 3 degrees (30 chords): length = 2 R sin(1.5 deg) * 30.
    chord = 2 * np.sin(np.radians(1.5)) * 30
    np.testing.assert_allclose(r.length_m[r.turn == 1], 2 * arm + (H + w / 2) * chord)
    np.testing.assert_allclose(r.length_m[r.turn == 2], 2 * arm + (corner + w / 2) * chord)


@pytest.mark.parametrize("turn", [1, 2])
def test_turn_arcs_are_circles_tangent_to_their_lanes(turn):
    r = WORLD.routes
    k = int(np.flatnonzero(r.turn == turn)[0])  # from the east arm, westbound
    line = r.vertices[k, : r.n_vertices[k]]
    in_box = line[(np.abs(line) <= H + 1e-9).all(axis=1)]
    centre = np.array([H, -H]) if turn == 1 else np.array([H, H])
    radius = H + 1.75 if turn == 1 else 6.0 + 1.75
    np.testing.assert_allclose(np.linalg.norm(in_box - centre, axis=1), radius)
    heading = np.unwrap(np.arctan2(*np.diff(line, axis=0).T[::-1]))
    assert np.degrees(np.abs(np.diff(heading))).max() <= 3.0 + 1e-9  # smooth: <= arc step
    assert np.isclose(heading[-1] - heading[0], np.pi / 2 if turn == 1 else -np.pi / 2)


@pytest.mark.parametrize("n_lanes", [1, 3])
def test_other_lane_counts(n_lanes):
    world = build_intersection(IntersectionSettings(lanes_per_direction=n_lanes))
    per_arm = n_lanes + 2
    assert world.lane_role.count("connector") == 4 * per_arm
    assert world.lane_role.count("incoming") == 4 * n_lanes
    for lane in range(world.n_lanes):
        assert world.routes_through(lane).size >= 1


def test_pose_and_forward_path_on_a_straight_route():
    r = WORLD.routes
    k = int(np.flatnonzero(r.turn == 0)[0])  # east arm inner lane, straight on to the west
    s = np.array([0.0, 150.0, 160.0])
    xy, heading = pose(r, np.full(3, k), s)
    np.testing.assert_allclose(xy, [[163.0, 1.75], [13.0, 1.75], [3.0, 1.75]])
    np.testing.assert_allclose(np.cos(heading), -1.0)
    paths, points = forward_paths(r, np.full(3, k), s, xy)
    # The position, then the route vertices strictly ahead (box edges at x = 13, -13).
    assert list(points) == [4, 3, 3]
    np.testing.assert_allclose(paths[2, :3], [[3.0, 1.75], [-13.0, 1.75], [-163.0, 1.75]])
    np.testing.assert_allclose(paths[2, 3], [-163.0, 1.75])  # padding repeats the end
    lane, into = lane_at(r, np.full(3, k), s)
    assert [WORLD.lane_role[i] for i in lane] == ["incoming", "connector", "connector"]
    np.testing.assert_allclose(into, [0.0, 0.0, 10.0])


@settings(max_examples=40, deadline=None)
@given(route=st.integers(0, 15), frac=st.floats(0.0, 0.999))
def test_forward_path_starts_at_the_agent_and_ends_at_the_route_end(route, frac):
    r = WORLD.routes
    s = np.array([frac * r.length_m[route]])
    xy, _ = pose(r, np.array([route]), s)
    paths, points = forward_paths(r, np.array([route]), s, xy)
    path = paths[0, : points[0]]
    np.testing.assert_allclose(path[0], xy[0])
    np.testing.assert_allclose(path[-1], r.vertices[route, r.n_vertices[route] - 1])
    remaining = np.linalg.norm(np.diff(path, axis=0), axis=1).sum()
    assert remaining == pytest.approx(r.length_m[route] - s[0], abs=1e-6)


# ---------------------------------------------------------------------- overlap test


def overlap_all(xy, heading, length, width, margin):
    return boxes_overlap(xy, heading, length, width, xy, heading, length, width, margin)


def test_boxes_overlap_hand_cases():
    xy = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 2.5], [3.0, 2.5]])
    heading = np.array([0.0, 0.0, 0.0, np.pi / 4])
    length = np.full(4, 4.5)
    width = np.full(4, 2.0)
    over = overlap_all(xy, heading, length, width, 0.0)
    assert over[0, 1] and over[1, 0]  # 4 m apart along x with 4.5 m bodies
    assert not over[0, 2]  # 2.5 m apart sideways with 2 m widths: 0.5 m clear
    assert overlap_all(xy, heading, length, width, 0.6)[0, 2]  # ... less than 0.6 m
    # The 45-degree box at (3, 2.5): its lowest corner (3 - 3.25/sqrt2 + ..., ) is
    # (3 - 2.25 c + c, 2.5 - 2.25 c - c) with c = 1/sqrt2 = (2.12, 0.20): inside box 0.
    assert over[0, 3]
    # Moved by (0.5, 0.5), its own long axis separates them: |(3.5, 3) . d| = 4.60 >
    # 2.25 + (2.25 + 1) c = 4.55.
    moved = xy + np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.5, 0.5]])
    assert not overlap_all(moved, heading, length, width, 0.0)[0, 3]
    assert overlap_all(moved, heading, length, width, 0.1)[0, 3]


def points_inside(xy, heading, length, width, pts):
    """Independent check: which of ``pts (K, 2)`` lie inside the rectangle."""
    d = np.array([np.cos(heading), np.sin(heading)])
    rel = pts - xy
    return (np.abs(rel @ d) < length / 2) & (np.abs(rel @ np.array([-d[1], d[0]])) < width / 2)


@settings(max_examples=60, deadline=None)
@given(
    dx=st.floats(-8, 8),
    dy=st.floats(-8, 8),
    h1=st.floats(-np.pi, np.pi),
    h2=st.floats(-np.pi, np.pi),
    dims=st.tuples(st.floats(1, 6), st.floats(0.5, 2.5), st.floats(1, 6), st.floats(0.5, 2.5)),
)
def test_boxes_overlap_agrees_with_point_sampling(dx, dy, h1, h2, dims):
    """A sampled point of one body inside the other implies overlap (independent check),
    and the test is symmetric."""
    l1, w1, l2, w2 = dims
    xy = np.array([[0.0, 0.0], [dx, dy]])
    heading, length, width = np.array([h1, h2]), np.array([l1, l2]), np.array([w1, w2])
    over = overlap_all(xy, heading, length, width, 0.0)
    assert over[0, 1] == over[1, 0]
    u = np.linspace(-0.49, 0.49, 15)
    d = np.array([np.cos(h1), np.sin(h1)])
    grid = (u[:, None, None] * l1 * d + u[None, :, None] * w1 * np.array([-d[1], d[0]])).reshape(
        -1, 2
    )
    if points_inside(xy[1], h2, l2, w2, grid).any():
        assert over[0, 1]


# ---------------------------------------------------------------------- situations


@pytest.mark.parametrize("seed", range(6))
def test_situation_follows_the_paper_ranges(seed):
    scene = generate_situation(SyntheticSettings(), seed)
    (frame,) = scene.frames
    assert 30 <= frame.n_agents <= 100
    assert frame.ego == 0 and frame.ego_id == 0
    assert frame.valid.all()
    assert ((frame.speed >= 0) & (frame.speed <= 25)).all()
    assert scene.metadata["seed"] == str(seed)
    assert scene.metadata["converter"] == "synthetic-intersection"
    # The ego is on an incoming lane, 10-60 m before the box, driving towards it.
    x, y = frame.xy[0]
    along, across = (abs(x), abs(y)) if abs(x) > abs(y) else (abs(y), abs(x))
    assert 10.0 - 1e-9 <= along - H <= 60.0 + 1e-9
    assert across < 7.0
    assert np.dot([np.cos(frame.heading[0]), np.sin(frame.heading[0])], frame.xy[0]) < 0


def test_situation_bodies_do_not_overlap():
    frame = generate_situation(SyntheticSettings(n_agents=100), 11).frames[0]
    # Sample each body on a grid and test the points against every other body.
    u = np.linspace(-0.5, 0.5, 7)
    for i in range(frame.n_agents):
        d = np.array([np.cos(frame.heading[i]), np.sin(frame.heading[i])])
        nrm = np.array([-d[1], d[0]])
        grid = (
            frame.xy[i]
            + u[:, None, None] * frame.length[i] * d
            + u[None, :, None] * frame.width[i] * nrm
        ).reshape(-1, 2)
        for j in range(i + 1, frame.n_agents):
            hit = points_inside(
                frame.xy[j], frame.heading[j], frame.length[j], frame.width[j], grid
            )
            assert not hit.any(), (i, j)


def test_gaps_on_a_lane_respect_the_minimum():
    s = SyntheticSettings(n_agents=100)
    for seed in range(5):
        traffic = spawn(WORLD, s, np.random.default_rng(seed))
        lane, into = lane_at(WORLD.routes, traffic.route, traffic.s_m)
        for k in np.unique(lane):
            i = np.flatnonzero(lane == k)
            i = i[np.argsort(into[i])]
            gaps = np.diff(into[i]) - 0.5 * (traffic.length_m[i][1:] + traffic.length_m[i][:-1])
            assert (gaps >= 5.0 - 1e-9).all()


def test_exact_agent_count_and_determinism():
    s = SyntheticSettings(n_agents=42)
    a = generate_situation(s, 5).frames[0]
    b = generate_situation(s, 5).frames[0]
    c = generate_situation(s, 6).frames[0]
    assert a.n_agents == 42
    for name in ("xy", "heading", "speed", "length", "paths", "path_points"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.xy, c.xy)


def test_too_many_agents_is_a_clear_error():
    with pytest.raises(ConversionError, match="do not fit"):
        generate_situation(SyntheticSettings(n_agents=2000), 0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"agents_range": (50, 30)}, "agents range"),
        ({"n_agents": 0}, "must be >= 1"),
        ({"gap_range_m": (0.0, 10.0)}, "minimum gap"),
        ({"speed_range_mps": (-1.0, 5.0)}, "speed_range_mps"),
        ({"duration_s": 0.0}, "duration"),
        ({"ego_distance_range_m": (10.0, 400.0)}, "ego must start"),
    ],
)
def test_settings_are_validated(kwargs, match):
    with pytest.raises(ConversionError, match=match):
        SyntheticSettings(**kwargs)


def test_intersection_settings_are_validated():
    with pytest.raises(ConversionError, match="lanes per direction"):
        IntersectionSettings(lanes_per_direction=0)
    with pytest.raises(ConversionError, match="arm_length_m"):
        IntersectionSettings(arm_length_m=-5.0)


# ---------------------------------------------------------------------- IDM


def test_idm_hand_values():
    p = IdmSettings()  # a = 1.5, b = 2, s0 = 2, T = 1.5, delta = 4
    v = np.array([0.0, 10.0, 20.0, 10.0, 10.0])
    v0 = np.full(5, 20.0)
    gap = np.array([np.inf, np.inf, np.inf, 17.0, 0.5])
    dv = np.zeros(5)
    a = idm_accel(v, v0, gap, dv, p)
    # free road: a (1 - (v/v0)^4); at the equilibrium-like gap s0 + vT = 17 m the
    # interaction term is exactly 1; at 0.5 m the braking is capped at 9 m/s^2.
    np.testing.assert_allclose(a, [1.5, 1.5 * (1 - 0.0625), 0.0, 1.5 * (0.9375 - 1.0), -9.0])
    # approaching (dv > 0) brakes harder than following at the same speed
    closing = idm_accel(v[3:4], v0[:1], gap[3:4], np.array([5.0]), p)
    assert closing[0] < a[3]


def two_on_a_lane(gap_m: float, v_follower: float, v_leader: float) -> Traffic:
    k = int(np.flatnonzero(WORLD.routes.turn == 0)[0])
    s_leader = 100.0
    return Traffic(
        route=np.array([k, k]),
        s_m=np.array([s_leader - 4.5 - gap_m, s_leader]),
        speed_mps=np.array([v_follower, v_leader]),
        desired_mps=np.array([20.0, 0.0]),  # the leader wants to stand still
        length_m=np.array([4.5, 4.5]),
        width_m=np.array([1.8, 1.8]),
        active=np.array([True, True]),
    )


def test_follower_stops_behind_a_stopped_leader():
    traffic = two_on_a_lane(gap_m=60.0, v_follower=15.0, v_leader=0.0)
    leader, gap = route_gaps(WORLD, traffic)
    assert list(leader) == [1, -1]
    assert gap[0] == pytest.approx(60.0)
    gaps = []
    for _ in range(300):
        traffic = step(WORLD, traffic, IdmSettings(), 0.1)
        gaps.append(route_gaps(WORLD, traffic)[1][0])
    assert traffic.speed_mps[0] == pytest.approx(0.0, abs=0.05)
    assert min(gaps) > 0.0
    assert gaps[-1] == pytest.approx(IdmSettings().jam_gap_m, abs=0.5)


def test_follower_never_passes_through_a_leader():
    # Far too fast and far too close: IDM's capped braking cannot avoid contact.
    traffic = two_on_a_lane(gap_m=1.0, v_follower=25.0, v_leader=0.0)
    for _ in range(30):
        traffic = step(WORLD, traffic, IdmSettings(), 0.1)
        assert route_gaps(WORLD, traffic)[1][0] >= -1e-9


def test_agents_leave_at_the_route_end():
    traffic = two_on_a_lane(gap_m=30.0, v_follower=20.0, v_leader=20.0)
    k = traffic.route[0]
    traffic = dataclasses.replace(
        traffic, s_m=np.array([10.0, WORLD.routes.length_m[k] - 1.0]), desired_mps=np.full(2, 20.0)
    )
    traffic = step(WORLD, traffic, IdmSettings(), 0.1)
    assert list(traffic.active) == [True, False]
    assert traffic.speed_mps[1] == 0.0


# ---------------------------------------------------------------------- scenes


def test_scene_defaults_and_motion():
    scene = generate_scene(SyntheticSettings(n_agents=60), 3)
    assert scene.frame_period_s == 0.1
    assert len(scene.frames) == 100
    times = np.array([f.t for f in scene.frames])
    np.testing.assert_allclose(times, np.arange(100) * 0.1)
    valid = np.stack([f.valid for f in scene.frames])
    assert valid[:, 0].all()  # the ego stays
    assert (valid[:-1] >= valid[1:]).all()  # agents only ever leave
    for f in scene.frames:
        v = f.valid
        assert (f.speed[v] >= 0).all()
        # every valid agent's path starts where the agent is
        np.testing.assert_allclose(f.paths[v, 0], f.xy[v])
    # agents move forward along their path: displacement matches speed on average
    f0, f1 = scene.frames[0], scene.frames[1]
    both = f0.valid & f1.valid
    moved = np.linalg.norm(f1.xy[both] - f0.xy[both], axis=1)
    expected = 0.5 * (f0.speed[both] + f1.speed[both]) * 0.1
    np.testing.assert_allclose(moved, expected, atol=0.05)


def test_scene_ends_when_the_ego_leaves():
    s = SyntheticSettings(
        n_agents=5,
        intersection=IntersectionSettings(arm_length_m=30.0),
        ego_distance_range_m=(10.0, 20.0),
        speed_range_mps=(20.0, 25.0),
        desired_speed_range_mps=(20.0, 25.0),
        duration_s=10.0,
    )
    scene = generate_scene(s, 0)
    assert 1 < len(scene.frames) < 100
    assert all(f.valid[0] for f in scene.frames)


def test_settings_travel_in_metadata():
    scene = generate_situation(SyntheticSettings(n_agents=31), 9)
    assert '"n_agents": 31' in scene.metadata["settings"]
    assert scene.metadata["n_agents"] == "31"
