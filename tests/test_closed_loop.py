"""The closed loop: reactive agents, collision classes and fault, the metrics, the CLI.

Hand-made cases with known answers, the vectorised reactive model against a slow
per-agent oracle, and ``replay plan --closed-loop`` through click's CliRunner.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from replay.analysis.planner_eval import metrics
from replay.analysis.planner_eval.closed_loop import ClosedLoopSettings, run_ego
from replay.analysis.planner_eval.open_loop import PlanSettings
from replay.cli.app import main
from replay.planning import reactive
from risk import Frame, Scene
from risk.hindsight import box_corners, boxes_overlap
from tests.planner_scenes import road_map

# ---------------------------------------------------------------------- a scene
EGO, STOPPED, FOLLOWER = 0, 1, 5


def _follower_scene(duration_s: float = 10.0) -> Scene:
    """The two-lane road: the ego at 10 m/s, a car standing 40 m ahead in its lane, and a
    follower 15 m behind the ego at 10 m/s that, as logged, drives on at 10 m/s (the
    recorded ego drove through the standing car: the planner's ego stops for it)."""
    frames = []
    for t in np.round(np.arange(0.0, duration_s + 1e-9, 0.1), 6):
        x = np.array([10.0 * t, 40.0, -15.0 + 10.0 * t])
        frames.append(
            Frame.from_arrays(
                xy=np.stack([x, np.zeros(3)], axis=1),
                heading=np.zeros(3),
                speed=np.array([10.0, 0.0, 10.0]),
                length=np.full(3, 4.5),
                width=np.full(3, 1.8),
                paths=[np.array([[xi, 0.0], [600.0, 0.0]]) for xi in x],
                ego=0,
                ids=[EGO, STOPPED, FOLLOWER],
                t=float(t),
            )
        )
    return Scene(
        map=road_map(),
        frames=tuple(frames),
        frame_period_s=0.1,
        metadata={"dataset": "hand-made", "scenario_id": "follower", "converter": "tests"},
        ego_id=EGO,
    )


@pytest.fixture(scope="module")
def follower_scene(tmp_path_factory) -> pathlib.Path:
    from converters.scene.writer import write_scene

    folder = tmp_path_factory.mktemp("cl") / "hand-made"
    folder.mkdir()
    return write_scene(folder / "follower.mcap", _follower_scene())


def _run(path: pathlib.Path, agents: str) -> dict:
    settings = ClosedLoopSettings(plan=PlanSettings(filters=()), agents=agents, tracker="perfect")
    (row,) = run_ego(path, EGO, settings)
    return row


def test_a_reactive_follower_brakes_for_the_stopping_ego(follower_scene):
    row = _run(follower_scene, "reactive")
    assert row["collisions"] == 0 and row["at_fault_collisions"] == 0
    assert row["min_gap_m"] > 0.5
    assert row["progress_m"] > 15.0  # it drove towards the standing car, and stopped
    assert row["agents"] == "reactive" and row["tracker"] == "perfect"


def test_a_log_follower_rear_ends_the_stopping_ego_and_that_is_not_its_fault(follower_scene):
    row = _run(follower_scene, "log")
    assert row["collisions"] == 1  # the follower, once; never the standing car
    assert row["rear_end_collisions"] + row["stopped_ego_collisions"] == 1
    assert row["at_fault_collisions"] == 0
    assert row["score"] > 0.0  # no at-fault factor of 0


# ---------------------------------------------------------------------- collision classes
def _ego(speed: float, *, x: float = 0.0, heading: float = 0.0) -> metrics.EgoHistory:
    return metrics.EgoHistory(
        times_s=np.array([0.0]), xy=np.array([[x, 0.0]]), heading_rad=np.array([heading]),
        speed_mps=np.array([speed]), length_m=4.5, width_m=1.8,
    )  # fmt: skip


def _one(x: float, y: float, speed: float, heading: float = 0.0, kind: int = 0):
    return metrics.OthersHistory(
        ids=np.array([7]), kinds=np.array([kind], np.int8), xy=np.array([[[x, y]]]),
        heading_rad=np.array([[heading]]), speed_mps=np.array([[speed]]),
        length_m=np.array([[4.5]]), width_m=np.array([[1.8]]), valid=np.array([[True]]),
    )  # fmt: skip


# ego: centre (0, 0), heading +x, 4.5 x 1.8: front edge x = 2.25, rear axle x = -1.27
CASES = [
    # (ego speed, track x, y, speed, in lane) -> class, at fault
    ((0.0, 4.0, 0.0, 5.0, True), metrics.CollisionType.STOPPED_EGO, False),  # hit while standing
    ((5.0, 4.0, 0.0, 0.0, True), metrics.CollisionType.STOPPED_TRACK, True),  # into a standing car
    ((5.0, 4.0, 0.0, 3.0, True), metrics.CollisionType.ACTIVE_FRONT, True),  # into a slower one
    ((5.0, -4.0, 0.0, 8.0, True), metrics.CollisionType.ACTIVE_REAR, False),  # hit from behind
    ((5.0, -0.5, 1.7, 5.0, True), metrics.CollisionType.ACTIVE_LATERAL, False),  # side, in lane
    ((5.0, -0.5, 1.7, 5.0, False), metrics.CollisionType.ACTIVE_LATERAL, True),  # changing lanes
]


def _twice(ego: metrics.EgoHistory, track: metrics.OthersHistory):
    """Two steps: the track 100 m away, then where it is (a first overlap after the start
    and after the track's own first step, either of which is never at fault)."""
    e = metrics.EgoHistory(
        times_s=np.array([0.0, 0.1]), xy=np.repeat(ego.xy, 2, 0),
        heading_rad=np.repeat(ego.heading_rad, 2), speed_mps=np.repeat(ego.speed_mps, 2),
        length_m=ego.length_m, width_m=ego.width_m,
    )  # fmt: skip
    rep = {f.name: np.repeat(getattr(track, f.name), 2, 0) for f in dataclasses.fields(track)}
    rep["ids"], rep["kinds"] = track.ids, track.kinds
    rep["xy"] = rep["xy"] + np.array([[[100.0, 0.0]], [[0.0, 0.0]]])
    return e, metrics.OthersHistory(**rep)


@pytest.mark.parametrize(("case", "kind", "fault"), CASES)
def test_collision_classes_by_hand(case, kind, fault):
    ego_speed, x, y, speed, lane = case
    ego, track = _twice(_ego(ego_speed), _one(x, y, speed))
    out = metrics.classify_collisions(ego, track, np.array([lane, lane]))
    assert out.first_step.tolist() == [1]
    assert out.kind.tolist() == [int(kind)]
    assert out.at_fault.tolist() == [fault]
    # the same overlap at the very start (in the recording itself) is never at fault
    start = metrics.classify_collisions(_ego(ego_speed), _one(x, y, speed), np.array([lane]))
    assert start.kind.tolist() == [int(kind)] and start.at_fault.tolist() == [False]


def test_a_track_counts_once_at_its_first_overlap():
    # three steps: apart, overlapping (the ego moving into a standing car), overlapping
    ego = metrics.EgoHistory(
        times_s=np.array([0.0, 0.1, 0.2]), xy=np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0]]),
        heading_rad=np.zeros(3), speed_mps=np.array([5.0, 5.0, 0.0]), length_m=4.5,
        width_m=1.8,
    )  # fmt: skip
    track = metrics.OthersHistory(
        ids=np.array([3]), kinds=np.array([0], np.int8), xy=np.full((3, 1, 2), [5.5, 0.0]),
        heading_rad=np.zeros((3, 1)), speed_mps=np.zeros((3, 1)),
        length_m=np.full((3, 1), 4.5), width_m=np.full((3, 1), 1.8), valid=np.ones((3, 1), bool),
    )  # fmt: skip
    out = metrics.classify_collisions(ego, track, np.ones(3, bool))
    assert out.overlap[:, 0].tolist() == [False, True, True]
    assert out.first_step.tolist() == [1] and out.n == 1
    assert out.kind.tolist() == [metrics.CollisionType.STOPPED_TRACK]  # not "stopped ego" later
    assert metrics.at_fault_factor(out, track.kinds) == 0.0
    # TTC: 0 at the at-fault step, the track is gone after it
    ttc = metrics.time_to_collision(ego, track, out, np.ones(3, bool))
    assert ttc[1] == 0.0 and math.isinf(ttc[2])


def test_time_to_collision_with_a_standing_car_ahead():
    # 10 m/s, the standing car's rear 10 m ahead of the ego's front: TTC 1.0 s
    ego = _ego(10.0)
    track = _one(2.25 + 10.0 + 2.25, 0.0, 0.0)
    none = metrics.classify_collisions(ego, track, np.array([True]))
    ttc = metrics.time_to_collision(ego, track, none, np.array([True]))
    assert ttc[0] == pytest.approx(1.0)
    # the same car behind the ego never counts; a stopped ego has no TTC
    behind = _one(-14.5, 0.0, 0.0)
    assert math.isinf(metrics.time_to_collision(ego, behind, none, np.array([True]))[0])
    assert math.isinf(metrics.time_to_collision(_ego(0.0), track, none, np.array([True]))[0])


def test_progress_ratio_and_score_by_hand():
    assert metrics.progress_ratio(50.0, 100.0) == 0.5
    assert metrics.progress_ratio(150.0, 100.0) == 1.0
    assert metrics.progress_ratio(1.0, 1.0) == 1.0  # both below 2 m: the threshold
    assert metrics.progress_ratio(-3.0, 100.0) == 0.0
    full = dict(fault_factor=1.0, drivable_ok=True, direction_score=1.0, progress=1.0,
                min_ttc_s=math.inf, comfortable=True)  # fmt: skip
    assert metrics.run_score(**full) == 1.0
    assert metrics.run_score(**{**full, "min_ttc_s": 0.5}) == pytest.approx(7 / 12)
    assert metrics.run_score(**{**full, "progress": 0.5}) == pytest.approx(9.5 / 12)
    assert metrics.run_score(**{**full, "progress": 0.1}) == 0.0  # not making progress
    assert metrics.run_score(**{**full, "drivable_ok": False}) == 0.0
    assert metrics.run_score(**{**full, "drivable_ok": None}) == 1.0  # no lanes: not judged
    assert metrics.run_score(**{**full, "direction_score": 0.5}) == 0.5


def test_drivable_area_and_driving_direction_on_the_road():
    lanes = [lane.centerline for lane in road_map().lanes]
    t = np.arange(0.0, 3.01, 0.1)
    on_road = metrics.EgoHistory(
        times_s=t, xy=np.stack([10.0 * t, np.zeros_like(t)], 1), heading_rad=np.zeros_like(t),
        speed_mps=np.full_like(t, 10.0), length_m=4.5, width_m=1.8,
    )  # fmt: skip
    assert metrics.drivable_area_ok(on_road, lanes, 3.5)[0] is True
    assert metrics.driving_direction(on_road, lanes, 3.5)[0] == 1.0
    off_road = dataclasses.replace(
        on_road, xy=on_road.xy + np.array([0.0, -4.0])
    )  # 2.25 m past the edge
    assert metrics.drivable_area_ok(off_road, lanes, 3.5)[0] is False
    assert metrics.drivable_area_ok(on_road, [], 3.5)[0] is None
    # 1.6 m off the lane centre: the outer corners 0.75 m outside the 3.5 m corridor;
    # allowed when the recorded driver went as far out (a lane wider than 3.5 m)
    wide = dataclasses.replace(on_road, xy=on_road.xy + np.array([0.0, -1.6]))
    assert metrics.corridor_excursion_m(wide, lanes, 3.5) == pytest.approx(np.full(31, 0.75))
    assert metrics.drivable_area_ok(wide, lanes, 3.5)[0] is False
    assert metrics.drivable_area_ok(wide, lanes, 3.5, allowance_m=0.75)[0] is True
    # backwards in the ego's lane at 10 m/s: 10 m per second against the lane
    wrong = dataclasses.replace(on_road, xy=on_road.xy[::-1].copy())
    score, worst = metrics.driving_direction(wrong, lanes, 3.5)
    assert score == 0.0 and worst == pytest.approx(-10.0)


def test_comfort_of_a_steady_drive_and_of_a_hard_stop():
    t = np.arange(0.0, 5.01, 0.1)
    steady = metrics.EgoHistory(
        times_s=t, xy=np.stack([10.0 * t, 0 * t], 1), heading_rad=0 * t,
        speed_mps=np.full_like(t, 10.0), length_m=4.5, width_m=1.8,
    )  # fmt: skip
    assert metrics.comfort(steady).comfortable
    hard = dataclasses.replace(steady, speed_mps=np.maximum(10.0 - 6.0 * t, 0.0))
    out = metrics.comfort(hard)
    assert not out.comfortable and out.min_lon_accel_mps2 == pytest.approx(-6.0, abs=0.3)


# ---------------------------------------------------------------------- the reactive model
def _slow_leaders(rails, arc, speed, length, width, obstacles, self_index, s):
    """One agent at a time, one probe at a time, one obstacle at a time."""
    out = []
    for k in range(rails.n):
        cum = rails.arc_m[k]

        def pose(a, k=k, cum=cum):
            a = min(max(a, 0.0), cum[-1])
            return (np.interp(a, cum, rails.xy[k, :, 0]), np.interp(a, cum, rails.xy[k, :, 1]),
                    np.interp(a, cum, rails.heading_rad[k]))  # fmt: skip

        reach = s.min_lookahead_m + speed[k] * s.headway_s + speed[k] ** 2 / s.decel_mps2
        step = reach / (s.probes - 1)
        x0, y0, h0 = pose(arc[k])
        best = (math.inf, 0.0, -1)
        for p in range(s.probes):
            px, py, ph = pose(arc[k] + p * step)
            hits = []
            for j in range(obstacles.n):
                if j == self_index[k]:
                    continue
                ox, oy = obstacles.xy[j]
                if (ox - x0) * math.cos(h0) + (oy - y0) * math.sin(h0) <= 0:
                    continue
                if boxes_overlap(px, py, ph, length[k], width[k], ox, oy, obstacles.heading_rad[j],
                                 obstacles.length_m[j], obstacles.width_m[j]):  # fmt: skip
                    hits.append(j)
            if not hits:
                continue
            bx, by, bh = pose(arc[k] + max(p - 1, 0) * step)
            for j in hits:
                if p == 0:
                    g = 0.0
                else:
                    corners = box_corners(
                        obstacles.xy[j, 0], obstacles.xy[j, 1], obstacles.heading_rad[j],
                        obstacles.length_m[j], obstacles.width_m[j],
                    )  # fmt: skip
                    near = min(
                        (cx - bx) * math.cos(bh) + (cy - by) * math.sin(bh) for cx, cy in corners
                    )
                    g = min(max((p - 1) * step + near - length[k] / 2, (p - 1) * step), p * step)
                v = obstacles.speed_mps[j] * math.cos(obstacles.heading_rad[j] - ph)
                if (g, j) < (best[0], best[2]):
                    best = (g, v, j)
            break
        out.append(best)
    return out


def _random_world(seed: int):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 7))
    t = np.linspace(0.0, 1.0, 30)
    # gently curving rails, mostly in one of two lanes, some crossing
    start = rng.uniform([-30, -4], [30, 4], size=(k, 2))
    heading0 = rng.choice([0.0, 0.0, 0.0, np.pi / 2], size=k) + rng.normal(0, 0.1, k)
    curve = rng.normal(0, 0.3, k)
    heading = heading0[:, None] + curve[:, None] * t[None, :]
    step = 3.0
    xy = (
        start[:, None, :]
        + np.cumsum(step * np.stack([np.cos(heading), np.sin(heading)], -1), axis=1)
        - step * np.stack([np.cos(heading[:, :1]), np.sin(heading[:, :1])], -1)
    )
    rails = reactive.Rails.from_positions(xy, heading)
    arc = rng.uniform(0.0, 20.0, k)
    speed = rng.uniform(0.0, 15.0, k)
    length = rng.uniform(3.5, 12.0, k)
    width = rng.uniform(1.6, 2.6, k)
    pos, hdg = rails.poses(arc[:, None])
    extra = int(rng.integers(0, 4))  # the ego and replayed agents
    obstacles = reactive.Boxes(
        xy=np.vstack([pos[:, 0], rng.uniform([-20, -5], [60, 5], size=(extra, 2))]),
        heading_rad=np.append(hdg[:, 0], rng.uniform(-np.pi, np.pi, extra)),
        length_m=np.append(length, rng.uniform(0.5, 5.0, extra)),
        width_m=np.append(width, rng.uniform(0.5, 2.0, extra)),
        speed_mps=np.append(speed, rng.uniform(0.0, 10.0, extra)),
    )
    return rails, arc, speed, length, width, obstacles, np.arange(k)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000))
def test_leaders_match_a_slow_per_agent_oracle(seed):
    s = reactive.ReactiveSettings(probes=12)
    world = _random_world(seed)
    gap, lead_speed, leader = reactive.find_leaders(*world, s)
    slow = _slow_leaders(*world, s)
    assert leader.tolist() == [j for _, _, j in slow]
    np.testing.assert_allclose(gap, [g for g, _, _ in slow], atol=1e-9)
    np.testing.assert_allclose(lead_speed, [v for _, v, _ in slow], atol=1e-9)


def test_idm_by_hand_and_the_step_never_reverses():
    s = reactive.ReactiveSettings()
    # free road at the desired speed: no acceleration; at half of it: a0 (1 - 1/16)
    free = reactive.idm_acceleration(np.array([10.0, 5.0]), np.array([10.0, 10.0]),
                                     np.array([np.inf, np.inf]), np.zeros(2), s)  # fmt: skip
    np.testing.assert_allclose(free, [0.0, 2.0 * (1 - 1 / 16)])
    # standing behind a standing car 2 m ahead: s* = s0 = s, so a = a0 (1 - 0 - 1) = 0
    assert (
        reactive.idm_acceleration(np.zeros(1), np.ones(1), np.array([2.0]), np.zeros(1), s)[0]
        == 0.0
    )
    # fast onto a standing car close ahead: clipped at -b
    hard = reactive.idm_acceleration(
        np.array([20.0]), np.array([20.0]), np.array([5.0]), np.zeros(1), s
    )
    assert hard[0] == -s.decel_mps2
    arc, v = reactive.advance(
        np.array([0.0, 0.0]), np.array([1.0, 10.0]), np.array([-4.0, -4.0]), 0.5
    )
    np.testing.assert_allclose(v, [0.0, 8.0])
    np.testing.assert_allclose(arc, [1.0 / 8.0, 4.5])  # stops after v^2 / 2b; else trapezoid


def test_a_reactive_agent_stops_behind_a_standing_obstacle():
    s = reactive.ReactiveSettings()
    x = np.linspace(0.0, 200.0, 201)
    rails = reactive.Rails.from_positions(np.stack([x, 0 * x], 1)[None], np.zeros((1, 201)))
    wall = reactive.Boxes(xy=np.array([[60.0, 0.0]]), heading_rad=np.zeros(1),
                          length_m=np.array([4.5]), width_m=np.array([1.8]),
                          speed_mps=np.zeros(1))  # fmt: skip
    arc, v = np.array([0.0]), np.array([12.0])
    for _ in range(400):
        arc, v = reactive.step(rails, arc, v, np.array([12.0]), np.array([4.5]), np.array([1.8]),
                               wall, np.array([-1]), 0.1, s)  # fmt: skip
    front, wall_rear = arc[0] + 2.25, 60.0 - 2.25
    assert v[0] == pytest.approx(0.0, abs=1e-6)
    assert 0.5 < wall_rear - front <= s.min_gap_m + 0.5


# ---------------------------------------------------------------------- the CLI
def _plan(*args: object):
    return CliRunner().invoke(main, ["plan", *map(str, args), "--no-progress", "--workers", "1"])


@pytest.mark.parametrize("agents", ["log", "reactive"])
def test_cli_agents_and_tracker_options(follower_scene, tmp_path, agents):
    out = tmp_path / "out"
    report = tmp_path / "report.md"
    result = _plan(follower_scene, "-o", out, "--closed-loop", "--agents", agents,
                   "--tracker", "perfect", "--filter", "radius:10", "--no-plots",
                   "--report", report)  # fmt: skip
    assert result.exit_code == 0, result.output
    text = report.read_text()
    assert "### idm: closed loop" in text and "Paired with the all-agents run" in text
    # radius:10 adds one at-fault collision per run against all agents: +1.000
    assert "| radius:10 | 1 | +1.000" in text
    runs = pl.read_parquet(out / "closed_loop.parquet")
    for column in ("collisions", "rear_end_collisions", "at_fault_collisions",
                   "drivable_area_ok", "progress_ratio", "min_ttc_s", "comfortable", "score",
                   "ego_kind", "agents", "tracker"):  # fmt: skip
        assert column in runs.columns
    assert set(runs["agents"]) == {agents} and set(runs["tracker"]) == {"perfect"}
    assert set(runs["ego_kind"]) == {"vehicle"}
    by = {r["filter"]: r for r in runs.iter_rows(named=True)}
    assert by["none"]["at_fault_collisions"] == 0
    # radius:10 drops the standing car until it is 10 m off: too late to stop from 10 m/s
    cut = by["radius:10"]
    assert cut["at_fault_collisions"] == 1 and cut["stopped_track_collisions"] == 1
    assert cut["score"] == 0.0 and cut["min_ttc_s"] == 0.0
    # the replayed follower then runs into the standing ego: counted, not at fault
    assert cut["stopped_ego_collisions"] == (1 if agents == "log" else 0)
    assert "at fault" in result.output


def test_lqr_tracker_runs_the_follower_scene(follower_scene):
    settings = ClosedLoopSettings(plan=PlanSettings(filters=()), agents="reactive", tracker="lqr")
    (row,) = run_ego(follower_scene, EGO, settings)
    assert row["tracker"] == "lqr" and row["at_fault_collisions"] == 0


def test_an_unknown_agents_mode_is_refused():
    with pytest.raises(Exception, match="unknown agents mode"):
        ClosedLoopSettings(agents="ghosts")
