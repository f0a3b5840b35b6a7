"""ScenarioNet: safe loading, hand-made scenarios, lane chaining, bad input, the real scenes."""

from __future__ import annotations

import collections
import json
import math
import os
import pickle
import re

import numpy as np
import pytest
from click.testing import CliRunner

from converters import safe_pickle, scenarionet, sources
from converters.errors import ConversionError
from converters.lane_chain import chain_successors
from converters.lanegraph import PathSettings
from converters.scene.reader import read_scene
from replay import batch
from replay.cli.app import main
from risk.frame import Kind

T = 30  # steps of the hand-made scenario, 10 Hz


# ---------------------------------------------------------------------- hand-made scenario
def _track(kind, xy, heading, speed, valid=None, size=(4.5, 1.9), column=True) -> dict:
    """A nuScenes-like track: sizes (T, 1) when ``column``, else (T,) as in Waymo."""
    xy = np.broadcast_to(np.asarray(xy, dtype=float), (T, 2))
    position = np.concatenate([xy, np.zeros((T, 1))], axis=1)
    h = np.full(T, float(heading))
    velocity = np.stack([speed * np.cos(h), speed * np.sin(h)], axis=1)
    shape = (T, 1) if column else (T,)
    return {
        "type": kind,
        "metadata": {"type": kind.lower()},
        "state": {
            "position": position,
            "heading": h,
            "velocity": velocity,
            "valid": np.ones(T) if valid is None else np.asarray(valid, dtype=float),
            "length": np.full(shape, size[0]),
            "width": np.full(shape, size[1]),
            "height": np.full(shape, 1.5),
        },
    }


def _arc(center, radius, a0, a1, n=12) -> list[tuple[float, float]]:
    a = np.linspace(a0, a1, n)
    return [(center[0] + radius * math.cos(t), center[1] + radius * math.sin(t)) for t in a]


def chained_map() -> dict:
    """Lanes without connectivity, as nuScenes has them: A (0,0)->(50,0), B (50,0)->(100,0),
    C a left turn from (100,0) to (120,20); D starts at B's end but heads back (no link);
    E starts 2 m beside A's end (no link). Points as lists of tuples, as nuScenes stores."""
    return {
        "A": {"type": "LANE_SURFACE_STREET", "polyline": [(0.0, 0.0, 0.0), (50.0, 0.0, 0.0)]},
        "B": {"type": "LANE_SURFACE_STREET", "polyline": [(50.0, 0.0), (75.0, 0.0), (100.0, 0.0)]},
        "C": {"type": "LANE_SURFACE_STREET", "polyline": _arc((100.0, 20.0), 20.0, -math.pi / 2, 0.0)},
        "D": {"type": "LANE_SURFACE_STREET", "polyline": [(100.0, 0.3), (50.0, 0.3)]},
        "E": {"type": "LANE_SURFACE_STREET", "polyline": [(50.0, 2.0), (90.0, 2.0)]},
        "line-1": {"type": "ROAD_LINE_SOLID_SINGLE_WHITE", "polyline": [[0.0, -2.0], [100.0, -2.0]]},
        "cw": {"type": "CROSSWALK", "polygon": [[60.0, -2.0], [64.0, -2.0], [64.0, 2.0], [60.0, 2.0]]},
        "stop": {"type": "STOP_SIGN", "position": np.zeros(3)},
    }  # fmt: skip


def scenario(**changes) -> dict:
    """Ego on lane A at 10 m/s; a pedestrian; a cone; a car parked 30 m off every lane,
    which drives off at step 10 (its recorded future is its path)."""
    parked = _track("VEHICLE", (30.0, 40.0), 0.0, 0.0)
    parked["state"]["position"][10:, 0] = 30.0 + 0.5 * np.arange(T - 10)
    parked["state"]["velocity"][10:, 0] = 5.0
    tracks = {
        "ego": _track("VEHICLE", np.stack([10.0 + np.arange(T), np.zeros(T)], 1), 0.0, 10.0),
        "f00d": _track("PEDESTRIAN", (20.0, 5.0), -math.pi / 2, 1.0, size=(0.5, 0.5)),
        "c0ne": _track("TRAFFIC_CONE", (40.0, -1.5), 0.0, 0.0, valid=[0] * 5 + [1] * (T - 5)),
        "b1ke": parked,
    }
    sd = {
        "id": "hand-1",
        "version": "test",
        "length": T,
        "metadata": {
            "ts": np.arange(T) * 0.1,
            "sdc_id": "ego",
            "dataset": "nuscenes",
            "scenario_id": "hand-1",
            "map": "test-town",
        },
        "tracks": tracks,
        "dynamic_map_states": {},
        "map_features": chained_map(),
    }
    sd.update(changes)
    return sd


def write(path, obj, protocol=4):
    path.write_bytes(pickle.dumps(obj, protocol=protocol))
    return path


# ---------------------------------------------------------------------- safe loading
class _Opens:
    """Unpickling this object would call ``open(marker, 'w')``: it would create a file."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


class _Shell:
    """Unpickling this would run ``touch marker`` through os.system."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.mark.parametrize("payload", [_Opens, _Shell])
def test_malicious_pickle_is_refused_and_never_runs(tmp_path, payload):
    marker = tmp_path / "pwned"
    bad = write(tmp_path / "evil.pkl", scenario(extra=payload(str(marker))))
    with pytest.raises(ConversionError) as err:
        safe_pickle.load(bad)
    msg = str(err.value)
    assert "\n" not in msg
    assert re.search(r"names the global (io\.open|builtins\.open|posix\.system|os\.system)", msg)
    assert "not a plain ScenarioNet scenario" in msg
    assert not marker.exists()
    # the same through the command: one Error line, nothing written, nothing run
    out = tmp_path / "out"
    line = _one_error(_cli(bad, "-o", out))
    assert "names the global" in line
    assert not marker.exists()
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize(
    "data",
    [
        # ndarray((5,)) called directly: ndarray only stands in for _reconstruct's argument
        b"\x80\x02cnumpy\nndarray\nK\x05\x85R.",
        # _reconstruct(ndarray, (10**9,), b'b'): a billion-element seed array
        b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nJ\x00\xca\x9a;\x85C\x01b\x87R.",
        # bytes(10**9) through a builtin the allow-list leaves out
        b"\x80\x02c__builtin__\nbytes\nJ\x00\xca\x9a;\x85R.",
    ],
)
def test_allowed_globals_only_in_numpys_own_call_shape(data):
    with pytest.raises(ConversionError):
        safe_pickle.loads(data)


def test_loader_reads_numpy_arrays_and_defaultdicts_as_pickled_by_scenarionet():
    value = {
        "a": np.arange(6, dtype=np.float32).reshape(2, 3),
        "b": np.array([True, False]),
        "c": collections.defaultdict(int, {"VEHICLE": 3}),
        "d": [1, 2.5, "x", None, (1, 2), {3}],
    }
    for protocol in (3, 4):
        got = safe_pickle.loads(pickle.dumps(value, protocol=protocol))
        np.testing.assert_array_equal(got["a"], value["a"])
        assert got["a"].dtype == np.float32
        np.testing.assert_array_equal(got["b"], value["b"])
        assert type(got["c"]) is dict and got["c"] == {"VEHICLE": 3}
        assert got["d"] == value["d"]


def test_deeply_nested_pickle_is_one_error(tmp_path):
    """A million nested lists (2 MB): refused while loading, before it is walked."""
    n = 1_000_000
    bad = tmp_path / "deep.pkl"
    bad.write_bytes(b"\x80\x04" + b"]" * n + b"a" * (n - 1) + b".")
    line = _one_error(_cli(bad, "-o", tmp_path / "out"))
    assert "refused to load: it stacks more than" in line


def test_file_size_limit(tmp_path, monkeypatch):
    path = write(tmp_path / "s.pkl", scenario())
    monkeypatch.setattr(safe_pickle, "MAX_FILE_BYTES", 100)
    with pytest.raises(ConversionError, match="more than the 100"):
        safe_pickle.load(path)


# ---------------------------------------------------------------------- lane chaining
def test_chain_links_only_joints_with_continuous_heading():
    lanes = [
        np.asarray(f["polyline"], float)[:, :2] for k, f in chained_map().items() if k in "ABCDE"
    ]
    assert chain_successors(lanes) == [(1,), (2,), (), (), ()]  # A->B, B->C; D, E unlinked


def test_chain_matches_a_plain_loop_on_random_lanes():
    rng = np.random.default_rng(3)
    starts = rng.uniform(0, 30, (60, 2))
    lanes = [np.stack([s, s + rng.uniform(-5, 5, 2), s + rng.uniform(-8, 8, 2)]) for s in starts]
    lanes += [
        np.stack([ln[-1] + rng.normal(0, 0.4, 2), ln[-1] + 5 * rng.normal(size=2)])
        for ln in lanes[:40]
    ]
    got = chain_successors(lanes, max_gap_m=1.0, max_heading_rad=0.6)
    for i, a in enumerate(lanes):
        ha = math.atan2(*(a[-1] - a[-2])[::-1])
        want = tuple(
            j for j, b in enumerate(lanes)
            if j != i and math.dist(a[-1], b[0]) <= 1.0
            and abs((math.atan2(*(b[1] - b[0])[::-1]) - ha + math.pi) % (2 * math.pi) - math.pi) <= 0.6
        )  # fmt: skip
        assert got[i] == want
    assert sum(map(len, got)) > 5  # the random map does have joints


def test_paths_follow_chained_lanes_to_the_horizon(tmp_path):
    settings = PathSettings(map_path_m=0.0)  # v*T + margin = 10 * 12 + 10 = 130 m
    scene = scenarionet.read_scene(write(tmp_path / "s.pkl", scenario()), settings=settings)
    f0 = scene.frames[0]
    ego = f0.index_of(scene.ego_id)
    [path] = f0.agent_paths(ego)
    length = np.hypot(*np.diff(path, axis=0).T).sum()
    assert length == pytest.approx(130.0, abs=0.5)  # never shorter than the horizon
    # through B's end and onto the turn C (not straight on along x)
    assert np.isclose(path, [100.0, 0.0], atol=0.05).all(axis=1).any()
    c = np.asarray(chained_map()["C"]["polyline"])
    # every vertex after B lies on C, then C's end goes on straight to 130 m
    inner = path[(path[:, 0] > 100.5)][:-1]
    gap = np.hypot(inner[:, None, 0] - c[None, :, 0], inner[:, None, 1] - c[None, :, 1])
    assert len(inner) >= 5 and gap.min(axis=1).max() < 1e-6
    assert math.dist(path[-1], c[-1]) == pytest.approx(130.0 - 90.0 - 31.3, abs=0.3)
    assert "chained" in scene.metadata["lane_links"]


def test_path_sources_per_agent(tmp_path):
    scene = scenarionet.read_scene(write(tmp_path / "s.pkl", scenario()))
    ids = dict(zip(("b1ke", "c0ne", "ego", "f00d"), range(4), strict=True))  # sorted names
    assert scene.labels["paths_lane_graph"] == (ids["ego"],)
    assert scene.labels["paths_recorded_future"] == (ids["b1ke"],)
    assert set(scene.labels["paths_straight"]) == {ids["c0ne"], ids["f00d"]}
    # the off-lane car's path at frame 0 is its recorded future: it reaches (44.5, 40)
    f0 = scene.frames[0]
    [path] = f0.agent_paths(f0.index_of(ids["b1ke"]))
    assert np.isclose(path, [30.0 + 0.5 * (T - 11), 40.0], atol=1e-6).all(axis=1).any()


def test_hand_made_scenario_mapping(tmp_path):
    scene = scenarionet.read_scene(write(tmp_path / "s.pkl", scenario()))
    f = scene.frames[0]
    kinds = dict(zip(f.ids.tolist(), f.kinds.tolist(), strict=True))
    assert kinds == {0: Kind.VEHICLE, 1: Kind.OTHER, 2: Kind.VEHICLE, 3: Kind.PEDESTRIAN}
    assert scene.ego_id == 2 and scene.metadata["ego_track"] == "ego"
    assert not f.valid[f.index_of(1)] and scene.frames[5].valid[f.index_of(1)]  # the cone
    assert f.length[f.index_of(3)] == 0.5 and f.width[f.index_of(2)] == 1.9  # (T, 1) sizes
    assert f.speed[f.index_of(2)] == pytest.approx(10.0)
    assert len(scene.frames) == T and scene.frame_period_s == pytest.approx(0.1)
    assert len(scene.map.lanes) == 5
    assert sorted((ln.kind, ln.closed) for ln in scene.map.lines) == [
        ("crosswalk", True), ("lane_boundary", False)
    ]  # fmt: skip
    assert scene.metadata["map_features_left_out"] == '{"STOP_SIGN": 1}'
    assert scene.metadata["dataset"] == "nuscenes" and scene.metadata["map"] == "test-town"


def test_waymo_shapes_labels_and_traffic_lights(tmp_path):
    sd = scenario()
    tracks = {
        "7": _track("VEHICLE", np.stack([10.0 + np.arange(T), np.zeros(T)], 1), 0.0, 10.0, column=False),
        "12": _track("CYCLIST", (5.0, 0.0), 0.0, 2.0, column=False),
    }  # fmt: skip
    sd.update(tracks=tracks)
    sd["metadata"].update(
        sdc_id="7", dataset="waymo", objects_of_interest=["12"],
        tracks_to_predict={"12": {"track_index": 1, "difficulty": 1}},
    )  # fmt: skip
    states = ["LANE_STATE_STOP"] * 10 + ["LANE_STATE_GO"] * (T - 10)
    sd["dynamic_map_states"] = {
        "9": {"type": "TRAFFIC_LIGHT", "lane": 9, "stop_point": np.array([1.0, 2.0, 0.0]),
              "state": {"object_state": states}},
    }  # fmt: skip
    sd["map_features"] = {
        "9": {"type": "LANE_SURFACE_STREET", "polyline": np.array([[0.0, 0], [50, 0]]), "exit_lanes": [10]},
        "10": {"type": "LANE_SURFACE_STREET", "polyline": np.array([[50.0, 0], [90, 0]]), "exit_lanes": []},
    }  # fmt: skip
    scene = scenarionet.read_scene(write(tmp_path / "w.pkl", sd))
    assert scene.ego_id == 7
    assert scene.labels["objects_of_interest"] == (12,)
    assert scene.labels["tracks_to_predict"] == (12,)
    assert {ln.id: ln.successors for ln in scene.map.lanes} == {9: (10,), 10: ()}
    assert scene.metadata["lane_links"] == "exit_lanes"
    lights = json.loads(scene.metadata["traffic_lights"])
    assert lights == [
        {"lane": 9, "stop_point_m": [1.0, 2.0], "states": [[0.0, "STOP"], [1.0, "GO"]]}
    ]


# ---------------------------------------------------------------------- bad input
def _cli(*args):
    return CliRunner().invoke(main, ["convert", "scenarionet", *map(str, args)])


def _one_error(result) -> str:
    assert result.exit_code != 0, result.output
    assert "Traceback" not in result.output
    errors = [ln for ln in result.output.splitlines() if ln.startswith("Error:")]
    assert len(errors) == 1, result.output
    return errors[0]


@pytest.mark.parametrize(
    ("make", "expect"),
    [
        (lambda p: p.write_bytes(pickle.dumps(scenario(), protocol=4)[:5000]), "ends early"),
        (lambda p: write(p, [1, 2, 3]), "holds a list"),
        (lambda p: write(p, {k: v for k, v in scenario().items() if k != "tracks"}), "no 'tracks'"),
        (lambda p: write(p, scenario(metadata={"ts": np.arange(T) * 0.1})), "no 'sdc_id'"),
        (
            lambda p: write(p, scenario(tracks={"ego": {"type": "VEHICLE", "state": {}}})),
            "'position'",
        ),
        (lambda p: p.write_bytes(b"not a pickle at all"), "not a readable pickle"),
    ],
    ids=["truncated", "list", "missing-keys", "no-sdc_id", "empty-state", "garbage"],
)
def test_bad_files_give_one_error_line_and_write_nothing(tmp_path, make, expect):
    bad = tmp_path / "bad.pkl"
    make(bad)
    before = bad.read_bytes()
    out = tmp_path / "out"
    line = _one_error(_cli(bad, "-o", out))
    assert expect in line and str(bad) in line
    assert bad.read_bytes() == before
    assert not out.exists() or not any(out.iterdir())


def test_database_whose_mapping_names_a_missing_file(tmp_path):
    db = tmp_path / "db"
    (db / "part").mkdir(parents=True)
    write(db / "part" / "a.pkl", scenario())
    write(db / scenarionet.MAPPING_FILE, {"a.pkl": "part", "gone.pkl": ""})
    out = tmp_path / "out"
    line = _one_error(_cli(db, "-o", out))
    assert "gone.pkl" in line and "does not exist" in line
    assert not out.exists() or not any(out.iterdir())  # not even a.mcap


def test_an_index_file_given_as_the_input(tmp_path):
    index = write(tmp_path / scenarionet.SUMMARY_FILE, {"a.pkl": {}})
    assert "give its folder" in _one_error(_cli(index, "-o", tmp_path / "out"))


def test_database_folder_mapping_into_a_sub_folder(tmp_path):
    db = tmp_path / "db"
    (db / "part").mkdir(parents=True)
    write(db / "part" / "a.pkl", scenario())
    write(
        db / "b.pkl",
        scenario(id="hand-2", metadata={**scenario()["metadata"], "scenario_id": "hand-2"}),
    )
    write(db / "stray.pkl", [1])  # not in the index: not read
    write(db / scenarionet.MAPPING_FILE, {"a.pkl": "part", "b.pkl": ""})
    result = _cli(db, "-o", tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["hand-1.mcap", "hand-2.mcap"]
    [inp] = sources.discover([db]).inputs
    assert inp.source == "scenarionet" and inp.path == db.absolute()


# ---------------------------------------------------------------------- the real scenes
def _real_files(shared_data):
    root = shared_data / "scenarionet"
    if not root.is_dir():
        pytest.skip(f"ScenarioNet samples not found at {root}")
    files = sorted(p for p in root.rglob("*.pkl") if p.name not in scenarionet.INDEX_FILES)
    assert len(files) == 9
    return files


def _plain(path):
    with open(path, "rb") as fh:  # the shared test data is trusted: an independent reader
        return pickle.load(fh)


KIND_OF = {"VEHICLE": Kind.VEHICLE, "PEDESTRIAN": Kind.PEDESTRIAN, "CYCLIST": Kind.CYCLIST}


def test_real_scenes_against_the_pickles(shared_data, tmp_path):
    files = _real_files(shared_data)
    # the whole folder of databases at once: one scene per scenario, named by its id
    result = _cli(files[0].parents[1], "-o", tmp_path)
    assert result.exit_code == 0, result.output
    assert len(list(tmp_path.glob("*.mcap"))) == len(files)
    for path in files:
        sd = _plain(path)
        md, tracks = sd["metadata"], sd["tracks"]
        scene = read_scene(tmp_path / f"{sd['id']}.mcap")
        f = scene.frames[0]
        want = collections.Counter(
            Kind.VEHICLE
            if t["metadata"].get("type", "").startswith("vehicle.motorcycle")  # our rule
            else KIND_OF.get(t["type"], Kind.OTHER)
            for t in tracks.values()
        )
        assert collections.Counter(Kind(k) for k in f.kinds.tolist()) == want, path
        assert scene.metadata["dataset"] == md["dataset"]
        assert len(scene.frames) == len(md["ts"])
        # the ego: its positions at every step (to the format's millimetre)
        ego = tracks[md["sdc_id"]]["state"]
        xy = np.array([fr.xy[fr.index_of(scene.ego_id)] for fr in scene.frames])
        np.testing.assert_allclose(xy, ego["position"][:, :2], atol=5e-4)
        assert scene.metadata["ego_track"] == md["sdc_id"]
        # map features, per kind
        types = collections.Counter(m["type"] for m in sd["map_features"].values())
        lines = collections.Counter(ln.kind for ln in scene.map.lines)
        assert len(scene.map.lanes) == sum(n for t, n in types.items() if t.startswith("LANE_"))
        assert lines["lane_boundary"] == sum(
            n for t, n in types.items() if t.startswith("ROAD_LINE")
        )
        assert lines["road_edge"] == sum(n for t, n in types.items() if t.startswith("ROAD_EDGE"))
        assert lines["crosswalk"] == types["CROSSWALK"]
        # validity: every state valid in the pickle is valid in the scene, and only those
        n_valid = sum(int((t["state"]["valid"] > 0).sum()) for t in tracks.values())
        assert sum(int(fr.valid.sum()) for fr in scene.frames) == n_valid
        if md["dataset"] == "waymo":
            assert scene.labels["objects_of_interest"] == tuple(
                int(i) for i in md["objects_of_interest"]
            )
            assert scene.labels["tracks_to_predict"] == tuple(
                int(i) for i in md["tracks_to_predict"]
            )
            assert scene.metadata["lane_links"] == "exit_lanes"
            lights = json.loads(scene.metadata["traffic_lights"])
            assert len(lights) == len(sd["dynamic_map_states"])
        else:
            assert "chained" in scene.metadata["lane_links"]
            assert "objects_of_interest" not in scene.labels


def test_real_nuscenes_chaining_links_most_lane_ends(shared_data):
    path = next(p for p in _real_files(shared_data) if "scene-0061" in p.name)
    scene = scenarionet.read_scene(path)
    lanes = scene.map.lanes
    dead = sum(not ln.successors for ln in lanes)
    assert len(lanes) == 460 and dead == 49  # measured: 411 of 460 lane ends continue
    # the ego's path follows lanes: lane-graph paths at most of its frames
    ego_frames = [fr for fr in scene.frames if fr.valid[fr.index_of(scene.ego_id)]]
    assert scene.ego_id in scene.labels["paths_lane_graph"] and len(ego_frames) == 191


def test_batch_discovers_one_input_per_scenarionet_folder(shared_data):
    root = _real_files(shared_data)[0].parents[1]
    found = sources.discover([root])
    assert sorted(i.path.name for i in found.inputs) == [
        "nuscenes_0", "nuscenes_1", "nuscenes_2", "nuscenes_4", "overpass"
    ]  # fmt: skip
    assert {i.source for i in found.inputs} == {"scenarionet"}
    assert not found.unreadable and not found.scenes
    # batch names: one per folder, so that OUT/scenes/<folder>/<scenario>.mcap is a dataset
    names = sorted(f.name for f in batch.discover([root]))
    assert names == ["nuscenes_0", "nuscenes_1", "nuscenes_2", "nuscenes_4", "overpass"]


def _keys(d, pre=()):
    if isinstance(d, dict):
        for k, v in d.items():
            yield (*pre, k)
            yield from _keys(v, (*pre, k))


def test_any_field_of_the_wrong_type_is_a_conversion_error_or_converts():
    """Every field of a scenario (also lights, labels, exit_lanes) replaced by values of
    other types and shapes: a ConversionError or a scene, never another exception."""
    base = scenario()
    base["dynamic_map_states"] = {
        "9": {"type": "TRAFFIC_LIGHT", "lane": "A", "stop_point": np.array([1.0, 2.0, 0.0]),
              "state": {"object_state": ["LANE_STATE_GO"] * T}},
    }  # fmt: skip
    base["metadata"]["objects_of_interest"] = ["ego"]
    base["map_features"]["A"]["exit_lanes"] = ["B"]
    values = [None, 7, True, "x", [], {}, [1, 2], np.zeros((2, 2)), np.array(["a"]),
              [[1, 2], [3]], [(1, "a")], np.zeros(T), np.zeros((T, 5)), math.nan]  # fmt: skip
    settings = PathSettings(map_path_m=0.0)
    outcomes = collections.Counter()
    for key in list(_keys(base)):
        for value in values:
            sd = pickle.loads(pickle.dumps(base))  # a deep copy
            parent = sd
            for k in key[:-1]:
                parent = parent[k]
            parent[key[-1]] = value
            try:
                scenarionet.scenario_to_scene(sd, source="fuzz", settings=settings)
                outcomes["scene"] += 1
            except ConversionError as exc:
                assert "\n" not in str(exc)
                outcomes["error"] += 1
    assert outcomes["scene"] > 100 and outcomes["error"] > 500


def test_nuscenes_motorcycles_are_vehicles_bicycles_cyclists(tmp_path):
    sd = scenario()
    sd["tracks"]["m0to"] = _track("CYCLIST", (0.0, 3.0), 0.0, 5.0)
    sd["tracks"]["m0to"]["metadata"] = {"type": "vehicle.motorcycle"}
    sd["tracks"]["b1cy"] = _track("CYCLIST", (0.0, 6.0), 0.0, 3.0)
    sd["tracks"]["b1cy"]["metadata"] = {"type": "vehicle.bicycle"}
    scene = scenarionet.read_scene(write(tmp_path / "m.pkl", sd))
    f = scene.frames[0]
    kinds = dict(zip(f.ids.tolist(), f.kinds.tolist(), strict=True))
    # sorted keys: b1cy 0, b1ke 1, c0ne 2, ego 3, f00d 4, m0to 5
    assert kinds[5] == Kind.VEHICLE and kinds[0] == Kind.CYCLIST
