"""The source registry, the moving default ego, Argoverse 2 Sensor logs, INTERACTION
recordings of several CSVs, and the recorded corpus (``../shared/data/recorded``)."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from converters import av2_sensor, sources
from converters.errors import ConversionError
from converters.interaction import read_scene as read_interaction
from converters.scene.reader import read_scene as read_mcap
from converters.sources import SOURCES, ReadOptions, SourceInput
from converters.tracks import Skipped, TrackTable, moving_ego
from replay.batch.driver import discover as batch_discover
from replay.cli.app import main
from risk import MODELS, evaluate
from risk.frame import Kind

V, P = int(Kind.VEHICLE), int(Kind.PEDESTRIAN)


# ---------------------------------------------------------------------- moving ego
def _table(xy: np.ndarray, valid: np.ndarray, kinds: list[int], ids: list[int]) -> TrackTable:
    T, N = valid.shape
    return TrackTable(
        ids=np.array(ids, np.int64), kinds=np.array(kinds, np.int8), t_s=np.arange(T) * 0.1,
        xy=xy, heading=np.zeros((T, N)), speed=np.ones((T, N)), length=np.full((T, N), 4.0),
        width=np.full((T, N), 2.0), valid=valid,
    )  # fmt: skip


def test_moving_ego_is_not_the_parked_car_with_the_most_states():
    T = 50
    xy = np.zeros((T, 3, 2))
    valid = np.zeros((T, 3), bool)
    valid[:, 0] = True  # track 5: parked at (3, 3) for all 50 steps, with 2 cm jitter
    xy[:, 0] = 3.0 + 0.02 * (np.arange(T) % 2)[:, None]
    valid[10:40, 1] = True  # track 9: 30 steps, 1 m per step east
    xy[10:40, 1, 0] = np.arange(30.0)
    valid[:, 2] = True  # track 2: a pedestrian walking 2 m per step: moves most, not a vehicle
    xy[:, 2, 1] = 2.0 * np.arange(T)
    table = _table(xy, valid, [V, V, P], [5, 9, 2])
    # track 9 is present in 30 of 50 frames: the vehicles present for half of them first
    assert moving_ego(table) == (
        1, "the vehicle that travels farthest (29.0 m) of those present in at least half of"
        " the frames"
    )  # fmt: skip
    # No vehicle moves 5 m: the agent of any kind that travels farthest.
    table = _table(xy, valid, [V, P, P], [5, 9, 2])
    assert moving_ego(table) == (
        2, "the agent that travels farthest (98.0 m) of those present in at least half of the"
        " frames"
    )  # fmt: skip
    # Nothing moves 5 m: the most states (ties: the lowest id).
    still = _table(np.zeros((T, 2, 2)), np.ones((T, 2), bool), [V, V], [7, 3])
    assert moving_ego(still)[0] == 1 and "most states (50)" in moving_ego(still)[1]


def test_moving_ego_ignores_jitter_and_invalid_values():
    # Track 1 jitters by 0.9 m back and forth for 400 steps (summed path: 360 m, extent
    # 0.9 m); track 2 drives 6 m. An invalid state far away does not count.
    T = 400
    xy = np.zeros((T, 2, 2))
    xy[:, 0, 0] = 0.9 * (np.arange(T) % 2)
    xy[:, 1, 0] = np.linspace(0, 6, T)
    valid = np.ones((T, 2), bool)
    valid[5, 1] = False
    xy[5, 1] = (1e6, 1e6)
    assert moving_ego(_table(xy, valid, [V, V], [1, 2])) == (
        1,
        "the vehicle that travels farthest (6.0 m) of those present in at least half of the frames",
    )


def test_moving_ego_prefers_a_vehicle_present_for_most_of_the_scene():
    """Issue 31: the farthest traveller, in 27 of 76 frames, left most frames without an
    ego view. A vehicle present in most frames that moves 5 m is chosen instead; when
    none is, the short one is chosen with a warning."""
    T = 76
    xy = np.zeros((T, 2, 2))
    valid = np.zeros((T, 2), bool)
    valid[:27, 0] = True  # track 1: 27 frames, 2 m per frame (52 m)
    xy[:27, 0, 0] = 2.0 * np.arange(27)
    valid[:, 1] = True  # track 2: all 76 frames, waits, then moves 8 m
    xy[60:, 1, 1] = np.linspace(0.0, 8.0, T - 60)
    index, why = moving_ego(_table(xy, valid, [V, V], [1, 2]))
    assert index == 1 and "(8.0 m) of those present in at least half" in why
    assert "warning" not in why
    xy[:, 1] = 0.0  # track 2 parked: the only mover is the short one, chosen with a warning
    index, why = moving_ego(_table(xy, valid, [V, V], [1, 2]))
    assert index == 0 and why.startswith("the vehicle that travels farthest (52.0 m);")
    assert "warning: it is present in only 27 of 76 frames" in why and "--ego" in why


# ---------------------------------------------------------------------- AV2 Sensor
def _quat_z(yaw: float) -> tuple[float, float, float, float]:
    return math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)


def _write_log(folder: pathlib.Path, pose_stamps: list[int]) -> pathlib.Path:
    folder.mkdir(parents=True)
    stamps = [1_000_000_000, 1_100_000_000]
    n = len(pose_stamps)
    qw, qx, qy, qz = _quat_z(math.pi / 2)  # every pose: at (100, 200, 5), facing +y
    poses = {
        "timestamp_ns": pose_stamps, "qw": [qw] * n, "qx": [qx] * n, "qy": [qy] * n,
        "qz": [qz] * n, "tx_m": [100.0] * n, "ty_m": [200.0] * n, "tz_m": [5.0] * n,
    }  # fmt: skip
    pl.DataFrame(poses).write_ipc(folder / "city_SE3_egovehicle.feather")
    # One car 10 m ahead of the vehicle (its +x), turned 90 deg left, moving 1 m per sweep
    # in the vehicle's +x; one bollard (static: left out).
    rows = [
        (stamps[0], "car", "REGULAR_VEHICLE", 4.0, 2.0, *_quat_z(math.pi / 2), 10.0, 0.0, 0.5),
        (stamps[1], "car", "REGULAR_VEHICLE", 4.0, 2.0, *_quat_z(math.pi / 2), 11.0, 0.0, 0.5),
        (stamps[0], "post", "BOLLARD", 0.3, 0.3, 1.0, 0.0, 0.0, 0.0, 5.0, 5.0, 0.0),
    ]
    cols = ("timestamp_ns", "track_uuid", "category", "length_m", "width_m", "qw", "qx", "qy",
            "qz", "tx_m", "ty_m", "tz_m")  # fmt: skip
    pl.DataFrame(rows, schema=cols, orient="row").write_ipc(folder / "annotations.feather")
    return folder


def test_av2_sensor_cuboid_transformed_by_hand(tmp_path):
    log = _write_log(tmp_path / "log", [900_000_000, 1_000_000_000, 1_100_000_000])
    scene = av2_sensor.read_scene(log)
    assert len(scene.frames) == 2 and scene.frame_period_s == pytest.approx(0.1)
    f = scene.frames[0]
    assert f.n_agents == 2 and scene.metadata["static_tracks_left_out"] == "1"
    ego, car = f.ego, 1 - f.ego
    # The vehicle stands at (100, 200) facing +y (yaw 90 deg): its +x is the city's +y.
    # The car at (10, 0) in the vehicle frame is at (100, 210) in the city, and its own
    # 90 deg turn adds to the vehicle's: heading 180 deg.
    np.testing.assert_allclose(f.xy[ego], (100, 200), atol=1e-9)
    assert f.heading[ego] == pytest.approx(math.pi / 2)
    np.testing.assert_allclose(f.xy[car], (100, 210), atol=1e-9)
    assert abs(math.remainder(f.heading[car] - math.pi, 2 * math.pi)) < 1e-9
    assert (f.length[car], f.width[car]) == (4.0, 2.0) and f.kinds[car] == V
    assert f.speed[car] == pytest.approx(10.0)  # 1 m in 0.1 s
    assert f.speed[ego] == 0.0 and scene.metadata["ego_track"] == "EGO"
    np.testing.assert_allclose(scene.frames[1].xy[car], (100, 211), atol=1e-9)


def test_av2_sensor_missing_poses_name_the_timestamps(tmp_path):
    log = _write_log(tmp_path / "log", [1_000_000_000])
    with pytest.raises(ConversionError) as err:
        av2_sensor.read_scene(log)
    message = str(err.value)
    assert "\n" not in message and str(log) in message
    assert "no pose for 1 annotation timestamp(s): 1100000000" in message


def test_quaternion_matrices_are_rotations():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(20, 4))
    r = av2_sensor.quaternion_matrices(q)
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape),
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(np.linalg.det(r), 1.0)


# ---------------------------------------------------------------------- INTERACTION, 2 CSVs
OSM = """<?xml version='1.0'?><osm version='0.6'>
<node id='1' lat='0' lon='0'/><node id='2' lat='0' lon='0.001'/>
<node id='3' lat='0.00003' lon='0'/><node id='4' lat='0.00003' lon='0.001'/>
<way id='10'><nd ref='3'/><nd ref='4'/></way><way id='11'><nd ref='1'/><nd ref='2'/></way>
<relation id='20'><member type='way' ref='10' role='left'/>
<member type='way' ref='11' role='right'/><tag k='type' v='lanelet'/></relation></osm>"""


def test_two_csvs_of_one_recording_make_one_scene(tmp_path):
    (tmp_path / "m.osm").write_text(OSM)
    veh = tmp_path / "vehicle_tracks_000.csv"
    ped = tmp_path / "pedestrian_tracks_000.csv"
    veh.write_text(
        "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width\n"
        + "".join(f"1,{k},{100 * k},car,{5 * k},1.5,50,0,0,4,2\n" for k in range(1, 6))
    )
    ped.write_text(
        "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy\n"
        + "".join(f"P1,{k},{100 * k},pedestrian/bicycle,20,{k},0,10\n" for k in range(2, 5))
    )
    scene = read_interaction([veh, ped], tmp_path / "m.osm")
    f = scene.frames[1]
    assert f.ids.tolist() == [1, 2] and f.kinds.tolist() == [V, P]
    assert f.valid.tolist() == [True, True] and scene.metadata["renamed_tracks"] == '{"P1": 2}'
    assert (f.length[1], f.width[1]) == (0.5, 0.5) and f.heading[1] == pytest.approx(math.pi / 2)
    assert scene.metadata["source_file"] == "vehicle_tracks_000.csv,pedestrian_tracks_000.csv"
    # The same track in two files: an error naming both.
    with pytest.raises(ConversionError, match=r"track 1 is also in .*vehicle_tracks_000.csv"):
        read_interaction([veh, veh], tmp_path / "m.osm")
    # The registry groups the two files into one input, vehicles first, with the map.
    [inp] = sources.discover([tmp_path]).inputs
    assert (inp.source, inp.path, inp.extra, inp.map) == (
        "interaction",
        veh,
        (ped,),
        tmp_path / "m.osm",
    )


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("source", "name", "content", "expected"),
    [
        ("commonroad", "x.xml", b"<html/>", "not a CommonRoad scenario"),
        ("commonroad", "x.xml", b"<commonRoad timeStepSize='0.1'><dyn", "not well-formed XML"),
        ("interaction", "x.csv", b"a,b\n1,2\n", "missing column(s) track_id"),
        ("waymo", "x.tfrecord", b"\x00" * 40, "record 0"),
        ("av2", "scenario_x.parquet", b"PAR1garbage", "not a readable parquet file"),
    ],
)
def test_damaged_and_foreign_files_give_one_line_naming_the_file(
    tmp_path, source, name, content, expected
):
    path = tmp_path / name
    path.write_bytes(content)
    (tmp_path / "m.osm").write_text(OSM)
    result = CliRunner().invoke(main, ["convert", source, str(path), "-o", str(tmp_path / "o")])
    assert result.exit_code == 1
    [line] = result.output.strip().splitlines()
    assert line.startswith(f"Error: {path}") and expected in line, line
    assert "Traceback" not in result.output and not (tmp_path / "o").exists()


def test_damaged_av2_sensor_log_gives_one_line(tmp_path):
    log = _write_log(tmp_path / "log", [1_000_000_000, 1_100_000_000])
    (log / "annotations.feather").write_bytes(b"ARROW1 cut")
    result = CliRunner().invoke(
        main, ["convert", "av2-sensor", str(log), "-o", str(tmp_path / "o")]
    )
    assert result.exit_code == 1
    [line] = result.output.strip().splitlines()
    assert line.startswith(f"Error: {log / 'annotations.feather'}: not a readable Feather file")


def test_discovery_sorts_sources_and_reports_foreign_data(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "scene.xml").write_text("<commonRoad timeStepSize='0.1'/>")
    (tmp_path / "a" / "page.xml").write_text("<html/>")
    (tmp_path / "a" / "README.md").write_text("notes")
    _write_log(tmp_path / "logs" / "l1", [1_000_000_000, 1_100_000_000])
    found = sources.discover([tmp_path])
    assert [(i.source, i.path.name) for i in found.inputs] == [
        ("av2-sensor", "l1"), ("commonroad", "scene.xml"),
    ]  # fmt: skip
    assert found.unreadable == [tmp_path / "a" / "page.xml"]
    assert "no converter reads this file" in sources.unreadable_reason(found.unreadable[0])
    files = batch_discover([tmp_path])
    problems = [f for f in files if f.problem]
    assert [f.path.name for f in problems] == ["page.xml"]
    assert {f.source for f in files} == {"av2-sensor", "commonroad", None}


# ---------------------------------------------------------------------- the corpus
DATASETS = ("sind", "mona", "ind", "exid", "highd", "ngsim", "interaction", "av2-sensor")


def _first_input(corpus: pathlib.Path, dataset: str) -> SourceInput:
    found = sources.discover([corpus / dataset])
    assert not found.unreadable
    return found.inputs[0]


@pytest.mark.realdata
@pytest.mark.parametrize("dataset", DATASETS)
def test_one_file_of_each_dataset_converts_and_every_valid_agent_is_scored(shared_data, dataset):
    corpus = shared_data / "recorded"
    if not corpus.is_dir():
        pytest.skip(f"the recorded corpus is not at {corpus}")
    inp = _first_input(corpus, dataset)
    [(_, build)] = list(SOURCES[inp.source].scenes(inp, ReadOptions(), Skipped()))
    scene = build()
    assert len(scene.frames) > 1
    meta = scene.metadata
    if dataset == "av2-sensor":
        assert meta["ego_track"] == "EGO"
    else:
        assert meta["ego_choice"].startswith("the vehicle that travels farthest")
    if dataset == "interaction":
        kinds = scene.frames[0].kinds
        assert (kinds == P).sum() == 23 and (kinds == V).sum() == 74  # pedestrians joined
    ego_speed = np.array([f.speed[f.ego] for f in scene.frames if f.ego_id == scene.ego_id])
    assert ego_speed.max() > 1.0  # a moving ego
    # ... present for most of the scene, or said not to be (issue 31: SinD's farthest
    # traveller was in 27 of 76 frames, so most frames had no ego view, without a word)
    if ego_speed.size < 0.5 * len(scene.frames):
        assert f"present in only {ego_speed.size} of " in meta.get("ego_choice", ""), meta
    for f in scene.frames[:: max(1, len(scene.frames) // 3)]:
        risks = evaluate(f)
        assert set(risks) == set(MODELS)
        scored = f.valid.copy()
        scored[f.ego] = False
        for name, r in risks.items():
            assert np.isfinite(r[scored]).all(), (dataset, name)


@pytest.mark.realdata
def test_interaction_cli_with_two_csvs_keeps_the_pedestrians(shared_data, tmp_path):
    folder = shared_data / "recorded" / "interaction"
    if not folder.is_dir():
        pytest.skip(f"the recorded corpus is not at {folder.parent}")
    out = tmp_path / "x.mcap"
    result = CliRunner().invoke(
        main,
        ["convert", "interaction", str(folder / "vehicle_tracks_000.csv"),
         str(folder / "pedestrian_tracks_000.csv"), "--map",
         str(folder / "I_INTERACTION_0_USA.osm"), "-o", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "vehicle_tracks_000: ego 27 (id 27): the vehicle that travels farthest" in result.stderr
    scene = read_mcap(out)
    frames = scene.frames
    peds = frames[0].kinds == P
    assert peds.sum() == 23
    # Pedestrians are valid (present) in some frames of the ego's lifetime.
    assert any((f.valid & peds).any() for f in frames)
    assert len(scene.map.lanes) == 59


def test_convert_and_run_say_which_agent_is_the_ego_and_why(tmp_path):
    (tmp_path / "m.osm").write_text(OSM)
    csv = tmp_path / "vehicle_tracks_001.csv"
    rows = ["track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width"]
    for k in range(1, 11):
        rows.append(f"4,{k},{100 * k},car,30,1,0,0,0,4,2")  # parked, every frame
        if k > 2:
            rows.append(f"6,{k},{100 * k},car,{2 * k},1.7,20,0,0,4,2")  # drives 14 m
    csv.write_text("\n".join(rows) + "\n")
    out = tmp_path / "s.mcap"
    runner = CliRunner()
    result = runner.invoke(main, ["convert", "interaction", str(csv), "-o", str(out)])
    assert result.exit_code == 0, result.output
    why = "the vehicle that travels farthest (14.0 m)"
    assert f"vehicle_tracks_001: ego 6 (id 6): {why}" in result.stderr
    table = str(out.with_suffix(".parquet"))
    result = runner.invoke(main, ["run", str(out), "--no-rrd", "--table", table, "--no-progress"])
    assert result.exit_code == 0, result.output
    assert f"Ego: agent 6 (source track 6): {why}" in result.stderr
    result = runner.invoke(
        main, ["run", str(out), "--no-rrd", "--table", table, "--no-progress", "--ego", "4"]
    )
    assert result.exit_code == 0 and "Ego:" not in result.stderr  # the user chose it
