"""Agent paths: lane matching and forward routes (map), recorded futures (hindsight), and
the scene assembly shared by the recorded-data converters."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from converters.errors import ConversionError
from converters.hindsight_paths import Hindsight
from converters.lanegraph import LaneGraph, PathSettings, arc_length, simplify, straight_rows
from converters.tracks import Skipped, TrackTable, build_scene, integer_ids
from risk.frame import Kind, Lane, LaneMap

V, P, C, OT = int(Kind.VEHICLE), int(Kind.PEDESTRIAN), int(Kind.CYCLIST), int(Kind.OTHER)


def lanes(*specs: tuple) -> LaneMap:
    """``(id, points, successors[, kind])`` tuples as a LaneMap."""
    return LaneMap(
        tuple(
            Lane(
                id=s[0],
                centerline=np.array(s[1], float),
                successors=tuple(s[2]),
                kind=(s[3:] or ("vehicle",))[0],
            )
            for s in specs
        )
    )


STRAIGHT = lanes((1, [(0, 0), (100, 0)], ()))
# Lane 1 east to x=50, then 2 straight on or 3 turning left (a quarter circle of radius 20).
_ARC = [(50 + 20 * math.sin(a), 20 - 20 * math.cos(a)) for a in np.linspace(0, math.pi / 2, 30)]
FORK = lanes((1, [(0, 0), (25, 0), (50, 0)], (2, 3)), (2, [(50, 0), (150, 0)], ()), (3, _ARC, ()))


def rows_for(graph: LaneGraph, xy, heading, speed, kinds):
    xy = np.atleast_2d(np.asarray(xy, float))
    n = len(xy)
    return graph.map_rows(
        np.zeros(n, np.int64),
        np.arange(n),
        xy,
        np.asarray(heading, float).reshape(n),
        np.asarray(speed, float).reshape(n),
        np.asarray(kinds).reshape(n),
    )


def paths_of(rows, agent: int) -> list[np.ndarray]:
    return [rows.points[r, : rows.count[r]] for r in np.flatnonzero(rows.agent == agent)]


# ---------------------------------------------------------------------- map paths
SHORT = PathSettings(map_path_m=0.0)  # paths of exactly v * T + margin


def test_straight_lane_path_joins_the_centre_line_and_has_the_required_length():
    graph = LaneGraph(STRAIGHT, SHORT)  # T = 12 s, margin 10 m, join 2 m
    rows, unmatched = rows_for(graph, [(10, 0.5)], [0.0], [5.0], [V])
    assert not unmatched.any()
    (path,) = paths_of(rows, 0)
    # agent, centre line 2 m ahead of the projection (x = 10), end at 10 + 5 * 12 + 10.
    np.testing.assert_allclose(path, [(10, 0.5), (12, 0), (80, 0)])


def test_map_path_runs_to_the_end_of_the_lane_graph():
    # Defaults: the whole known path (the lane ends at x = 100), not just v * T + margin.
    (path,) = paths_of(rows_for(LaneGraph(STRAIGHT), [(10, 0.5)], [0.0], [5.0], [V])[0], 0)
    np.testing.assert_allclose(path, [(10, 0.5), (12, 0), (100, 0)])


def test_map_path_is_capped_at_map_path_m_but_never_shorter_than_v_t_plus_margin():
    long = lanes((1, [(0, 0), (1000, 0)], ()))
    graph = LaneGraph(long)  # map_path_m = 300
    rows, _ = rows_for(graph, [(10, 0), (10, 0)], [0.0, 0.0], [5.0, 30.0], [V, V])
    (slow,) = paths_of(rows, 0)
    (fast,) = paths_of(rows, 1)
    np.testing.assert_allclose(slow[-1], (10 + 300, 0))  # capped at 300 m
    np.testing.assert_allclose(fast[-1], (10 + 30 * 12 + 10, 0))  # v * T + margin = 370 m
    (mid,) = paths_of(rows_for(LaneGraph(long, PathSettings(map_path_m=120.0)),
                               [(10, 0)], [0.0], [5.0], [V])[0], 0)  # fmt: skip
    np.testing.assert_allclose(mid[-1], (130, 0))


def test_route_shorter_than_needed_continues_straight_past_a_dead_end():
    graph = LaneGraph(STRAIGHT)
    rows, _ = rows_for(graph, [(10, 0.0)], [0.0], [10.0], [V])
    (path,) = paths_of(rows, 0)
    np.testing.assert_allclose(path[-1], (10 + 10 * 12 + 10, 0))
    np.testing.assert_allclose(path[-2], (100, 0))  # the lane's own end stays a vertex


def test_fork_gives_one_candidate_per_branch_straightest_first():
    graph = LaneGraph(FORK, SHORT)
    rows, _ = rows_for(graph, [(10, 0)], [0.0], [5.0], [V])  # needs s = 10 + 70 = 80 m
    straight, left = paths_of(rows, 0)
    np.testing.assert_allclose(straight, [(10, 0), (12, 0), (50, 0), (80, 0)])
    assert left[-1][1] > 10  # turned left
    np.testing.assert_allclose(arc_length(left)[-1], 70.0, atol=1e-6)  # on the centre line
    # Whole paths: each branch to its end (the arc ends at (70, 20); it is 71.3 m from
    # the agent, longer than the 70 m needed, so it is not extended).
    whole, left = paths_of(rows_for(LaneGraph(FORK), [(10, 0)], [0.0], [5.0], [V])[0], 0)
    np.testing.assert_allclose(whole[-1], (150, 0))
    np.testing.assert_allclose(left[-1], (70, 20), atol=1e-9)
    one = LaneGraph(FORK, PathSettings(max_candidates=1, map_path_m=0.0))
    (only,) = paths_of(rows_for(one, [(10, 0)], [0.0], [5.0], [V])[0], 0)
    np.testing.assert_allclose(only, straight)


def test_agent_off_the_lanes_is_unmatched():
    graph = LaneGraph(STRAIGHT)
    rows, unmatched = rows_for(graph, [(10, 2.5), (10, 1.9)], [0.0, 0.0], [5.0, 5.0], [V, V])
    assert unmatched.tolist() == [True, False]
    assert set(rows.agent.tolist()) == {1}


def test_wrong_way_and_crossing_headings_are_not_matched():
    graph = LaneGraph(STRAIGHT)
    headings = [math.pi, math.radians(50), math.radians(40), -math.radians(40)]
    _, unmatched = rows_for(graph, [(10, 0)] * 4, headings, [5.0] * 4, [V] * 4)
    assert unmatched.tolist() == [True, True, False, False]


def test_lane_kinds_decide_who_may_use_a_lane():
    bike = lanes((1, [(0, 0), (100, 0)], (), "bike"))
    graph = LaneGraph(bike)
    _, unmatched = rows_for(graph, [(10, 0)] * 4, [0.0] * 4, [3.0] * 4, [V, C, P, OT])
    assert unmatched.tolist() == [True, False, True, True]
    graph = LaneGraph(STRAIGHT)
    _, unmatched = rows_for(graph, [(10, 0)] * 4, [0.0] * 4, [3.0] * 4, [V, C, P, OT])
    assert unmatched.tolist() == [False, False, True, True]


def test_overlapping_lanes_give_candidates_in_order_of_fit():
    # Two lanes from the same start (an intersection): 1 east, 2 slightly to the north-east.
    m = lanes((1, [(0, 0), (100, 0)], ()), (2, [(0, 0), (100, 20)], ()))
    graph = LaneGraph(m)
    rows, _ = rows_for(graph, [(5, 0.2)], [0.0], [1.0], [V])
    first, second = paths_of(rows, 0)
    assert first[-1][1] == pytest.approx(0.0)  # lane 1 fits better (distance, heading)
    assert second[-1][1] > 1.0


def test_agent_at_a_lane_joint_gets_no_duplicate_route():
    m = lanes((1, [(0, 0), (50, 0)], (2,)), (2, [(50, 0), (150, 0)], ()))
    graph = LaneGraph(m, SHORT)
    rows, _ = rows_for(graph, [(49.9, 0.1), (50.5, 0)], [0.0, 0.0], [5.0, 5.0], [V, V])
    assert len(paths_of(rows, 0)) == 1 and len(paths_of(rows, 1)) == 1
    np.testing.assert_allclose(paths_of(rows, 0)[0][-1], (49.9 + 70, 0))


def test_merging_lanes_do_not_duplicate_their_common_successor():
    # 1 and 2 both lead into 3; an agent just past the merge point projects onto the end
    # of 1 and of 2, and onto 3: a single path.
    m = lanes(
        (1, [(0, -3), (50, 0)], (3,)), (2, [(0, 3), (50, 0)], (3,)), (3, [(50, 0), (150, 0)], ())
    )
    graph = LaneGraph(m)
    rows, _ = rows_for(graph, [(50.3, 0)], [0.0], [2.0], [V])
    assert len(paths_of(rows, 0)) == 1


def test_lane_loops_terminate():
    m = lanes((1, [(0, 0), (10, 0)], (2,)), (2, [(10, 0), (0, 0.1)], (1,)))
    graph = LaneGraph(m)
    rows, _unmatched = rows_for(graph, [(5, 0)], [0.0], [30.0], [V])
    (path,) = paths_of(rows, 0)
    assert arc_length(path)[-1] >= 30 * 12 + 10 - 2.0


def test_lanes_without_a_direction_are_ignored():
    m = lanes((1, [(5, 5), (5, 5)], ()), (2, [(3, 3)], ()))
    assert LaneGraph(m).n_lanes == 0


def test_settings_are_validated():
    with pytest.raises(ValueError, match="max_candidates"):
        PathSettings(max_candidates=0)
    with pytest.raises(ValueError, match="horizon_s"):
        PathSettings(horizon_s=float("nan"))


def _brute_force(lane_pts: list[np.ndarray], xy: np.ndarray, heading: np.ndarray, s: PathSettings):
    """Reference matcher: per agent and lane, a plain loop over segments."""
    found = set()
    for q, (p, h) in enumerate(zip(xy, heading, strict=True)):
        for li, line in enumerate(lane_pts):
            best = (np.inf, 0.0)
            for a, b in itertools.pairwise(line):
                d = b - a
                t = min(max(np.dot(p - a, d) / np.dot(d, d), 0.0), 1.0)
                dist = float(np.hypot(*(p - a - t * d)))
                if dist < best[0]:
                    best = (dist, math.atan2(d[1], d[0]))
            dh = abs((h - best[1] + math.pi) % (2 * math.pi) - math.pi)
            if best[0] <= s.max_lateral_m and dh <= s.max_heading_rad:
                found.add((q, li))
    return found


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_vectorised_matching_equals_a_plain_loop(seed):
    rng = np.random.default_rng(seed)
    pts = [np.cumsum(rng.normal(0, 4, size=(rng.integers(2, 6), 2)), axis=0) for _ in range(6)]
    m = LaneMap(tuple(Lane(id=i, centerline=p) for i, p in enumerate(pts)))
    s = PathSettings(simplify_m=0.0)
    graph = LaneGraph(m, s)
    keep = [
        i
        for i, p in enumerate(pts)
        if len(p) >= 2 and np.all(np.hypot(*np.diff(p, axis=0).T) > 1e-6)
    ]
    xy = rng.uniform(-15, 15, size=(40, 2))
    heading = rng.uniform(-math.pi, math.pi, size=40)
    got = graph.match(xy, heading, np.zeros(40, np.int8))
    expected = _brute_force([pts[i] for i in keep], xy, heading, s)
    assert {(int(q), int(lane)) for q, lane in zip(got.query, got.lane, strict=True)} == expected


@settings(max_examples=40, deadline=None)
@given(
    speed=st.floats(0.0, 30.0),
    start=st.floats(0.0, 44.0),  # the join point stays on the first lane
    offset=st.floats(-1.5, 1.5),
    join=st.floats(0.0, 5.0),
)
def test_map_path_follows_the_centre_line_for_exactly_the_needed_length(speed, start, offset, join):
    s = PathSettings(join_m=join, map_path_m=0.0)
    graph = LaneGraph(FORK, s)
    rows, unmatched = rows_for(graph, [(start, offset)], [0.0], [speed], [V])
    assert not unmatched.any()
    need = speed * s.horizon_s + s.margin_m
    for path in paths_of(rows, 0):
        np.testing.assert_allclose(path[0], (start, offset))
        # A straight blend to the centre line `join` ahead, then need - join along it.
        j = min(join, need)
        total = math.hypot(j, offset) + need - j
        assert arc_length(path)[-1] == pytest.approx(total, abs=1e-6)
        assert np.all(np.hypot(*np.diff(path, axis=0).T) > 0)  # no repeated points


# ---------------------------------------------------------------------- polylines
@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), tol=st.floats(0.01, 2.0))
def test_simplify_keeps_ends_and_stays_within_tolerance(seed, tol):
    rng = np.random.default_rng(seed)
    pts = np.cumsum(rng.normal(0, 1, size=(int(rng.integers(2, 60)), 2)), axis=0)
    keep = simplify(pts, tol)
    assert keep[0] == 0 and keep[-1] == len(pts) - 1
    kept = pts[keep]
    # Every dropped point lies within tol of the simplified segment that spans it.
    for a, b in itertools.pairwise(keep):
        seg_a, seg_b = pts[a], pts[b]
        d = seg_b - seg_a
        for p in pts[a + 1 : b]:
            t = 0.0 if not d.any() else min(max(np.dot(p - seg_a, d) / np.dot(d, d), 0.0), 1.0)
            assert np.hypot(*(p - seg_a - t * d)) <= tol + 1e-9
    assert len(kept) <= len(pts)


def test_simplify_drops_collinear_points():
    pts = np.stack([np.linspace(0, 10, 21), np.zeros(21)], axis=1)
    assert simplify(pts, 0.01).tolist() == [0, 20]


def test_straight_rows():
    rows = straight_rows(
        np.array([0, 0]), np.array([0, 1]), np.array([(1.0, 1.0), (0.0, 0.0)]),
        np.array([math.pi / 2, 0.0]), np.array([3.0, 0.0]),
    )  # fmt: skip
    np.testing.assert_allclose(rows.points[0], [(1, 1), (1, 4)], atol=1e-12)
    assert rows.count.tolist() == [2, 1]


# ---------------------------------------------------------------------- hindsight
def _line_track(n_steps=10):
    xy = np.zeros((n_steps, 1, 2))
    xy[:, 0, 0] = np.arange(n_steps, dtype=float)  # 1 m per step along +x
    return xy, np.zeros((n_steps, 1)), np.ones((n_steps, 1), bool)


def test_hindsight_is_the_recorded_future_then_straight():
    xy, heading, valid = _line_track()
    h = Hindsight(xy, heading, valid, PathSettings(horizon_s=2.0, margin_m=1.0))
    rows = h.rows(np.array([3]), np.array([0]), np.array([0]), xy[3], np.array([1.0]))
    # collinear record collapses to its end (9, 0); 6 m recorded < 2 * 1 + 1 = 3? no: 6 >= 3
    np.testing.assert_allclose(rows.points[0, : rows.count[0]], [(3, 0), (9, 0)])
    rows = h.rows(np.array([3]), np.array([0]), np.array([0]), xy[3], np.array([5.0]))
    # needs 5 * 2 + 1 = 11 m: 6 m recorded, 5 m straight on along the last heading
    np.testing.assert_allclose(rows.points[0, : rows.count[0]], [(3, 0), (9, 0), (14, 0)])


def test_hindsight_at_the_last_state_and_across_gaps():
    xy, heading, valid = _line_track()
    heading[:] = math.pi / 2
    valid[5:8] = False
    xy[8:, 0] = [(8, 3), (9, 6)]  # after the gap it turned north
    h = Hindsight(xy, heading, valid, PathSettings(horizon_s=1.0, margin_m=0.0, simplify_m=0.0))
    rows = h.rows(
        np.array([9, 2]), np.array([0, 1]), np.array([0, 0]), xy[[9, 2], 0], np.array([2.0, 0.0])
    )
    np.testing.assert_allclose(rows.points[0, : rows.count[0]], [(9, 6), (9, 8)])
    first = rows.points[1, : rows.count[1]]
    np.testing.assert_allclose(first, [(2, 0), (3, 0), (4, 0), (8, 3), (9, 6)])


def test_hindsight_removes_the_jitter_of_a_standing_agent():
    rng = np.random.default_rng(0)
    xy = rng.normal(0, 0.01, size=(50, 1, 2))
    h = Hindsight(xy, np.zeros((50, 1)), np.ones((50, 1), bool), PathSettings())
    rows = h.rows(np.array([0]), np.array([0]), np.array([0]), xy[0], np.array([0.0]))
    assert rows.count[0] <= 3


# ---------------------------------------------------------------------- scenes
def _table(valid: np.ndarray, kinds=(V, V, P)) -> TrackTable:
    n_steps, n = valid.shape
    xy = np.zeros((n_steps, n, 2))
    xy[:, :, 0] = np.arange(n_steps)[:, None] * 1.0 + np.arange(n)[None, :] * 10.0
    xy[:, 2, 1] = 5.0
    return TrackTable(
        ids=np.array([7, 8, 9][:n]),
        kinds=np.array(kinds[:n], np.int8),
        t_s=np.arange(n_steps) * 0.1,
        xy=xy,
        heading=np.zeros((n_steps, n)),
        speed=np.full((n_steps, n), 10.0),
        length=np.full((n_steps, n), 4.0),
        width=np.full((n_steps, n), 2.0),
        valid=valid,
    )


@pytest.mark.parametrize("mode", ["map", "hindsight"])
def test_build_scene_keeps_every_track_and_every_step(mode):
    valid = np.ones((5, 3), bool)
    valid[0, 0] = False  # the ego is missing at step 0
    valid[2, 1] = False  # another agent vanishes for one step
    table = _table(valid)
    scene = build_scene(
        table, 0, STRAIGHT, paths=mode, settings=PathSettings(), frame_period_s=0.1,
        metadata={"dataset": "test"}, labels={"x": (8,)},
    )  # fmt: skip
    assert len(scene.frames) == 5 and scene.ego_id == 7
    assert scene.metadata["steps_without_ego"] == "1"
    # Step 0 has no ego: it is kept, seen from the first valid agent.
    assert scene.frames[0].ego_id == 8 and not scene.frames[0].valid[0]
    assert scene.metadata["paths"] == mode
    assert scene.labels == {"x": (8,)}
    f = scene.frames[2]  # step 2
    assert f.t == pytest.approx(0.2)
    assert f.ids.tolist() == [7, 8, 9] and f.valid.tolist() == [True, False, True]
    assert f.ego_id == 7
    ped = f.agent_paths(2)
    assert len(ped) == 1 and ped[0][0].tolist() == [22.0, 5.0]
    if mode == "map":  # a pedestrian walks straight even on a lane
        np.testing.assert_allclose(ped[0], [(22, 5), (22 + 130, 5)])


def test_build_scene_stops_at_or_drops_bad_values_and_rejects_a_missing_ego():
    valid = np.ones((3, 3), bool)
    table = _table(valid)
    table.xy[1, 1] = np.nan
    args = (table, 0, LaneMap())
    kwargs = dict(paths="map", settings=PathSettings(), frame_period_s=0.1, metadata={})
    with pytest.raises(ConversionError, match=r"x\.csv: track \d+ at t=.* position is not"):
        build_scene(*args, **kwargs, source="x.csv")  # the default: stop, naming the record
    skipped = Skipped()
    scene = build_scene(*args, **kwargs, source="x.csv", skip_bad=True, skipped=skipped)
    assert scene.metadata["invalid_states_dropped"] == "1"
    assert scene.metadata["bad_states_dropped"] == "1"
    assert len(skipped) == 1 and "dropped 1 state(s)" in skipped.what[0]
    assert not scene.frames[1].valid[1]
    with pytest.raises(ConversionError, match=r"ego .*valid at no time step"):
        build_scene(
            _table(np.zeros((3, 3), bool)), 0, LaneMap(), paths="map",
            settings=PathSettings(), frame_period_s=0.1, metadata={}, source="x.csv",
        )  # fmt: skip


def test_integer_ids_keep_numbers_and_number_the_rest_after_them():
    ids, renamed = integer_ids(["12", "AV", "3", "P1"])
    assert ids.tolist() == [12, 13, 3, 14]
    assert renamed == {"AV": 13, "P1": 14}
    assert integer_ids(["a", "b"])[0].tolist() == [0, 1]


def test_cutting_in_chunks_changes_nothing(monkeypatch):
    import converters.lanegraph as lg

    xy = [(5 + 7 * i, 0.3 * (i % 3)) for i in range(7)]
    args = (xy, [0.0] * 7, [float(i) for i in range(7)], [V] * 7)
    whole, _ = rows_for(LaneGraph(FORK), *args)
    monkeypatch.setattr(lg, "_CUT_CHUNK", 2)
    chunked, _ = rows_for(LaneGraph(FORK), *args)
    assert chunked.agent.tolist() == whole.agent.tolist()
    for a in range(7):
        for p, q in zip(paths_of(chunked, a), paths_of(whole, a), strict=True):
            np.testing.assert_array_equal(p, q)
