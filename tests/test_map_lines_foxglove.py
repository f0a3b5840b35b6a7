"""Scene format version 2 map lines, their sources, and the optional Foxglove channels."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from click.testing import CliRunner
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from converters import av2, commonroad, map_lines, waymo
from converters.scene import foxglove as fg
from converters.scene import schema as sf
from converters.scene.reader import read_scene
from converters.scene.writer import write_scene
from replay.cli.app import main
from risk.frame import Frame, Lane, LaneMap, MapLine, Scene

HERE = pathlib.Path(__file__).parent


def lined_map() -> LaneMap:
    return LaneMap(
        (Lane(1, np.array([[0.0, 0.0], [40.0, 0.0]]), ()),),
        lines=(
            MapLine(10, "lane_boundary", np.array([[0.0, 1.75], [40.0, 1.75]]), style="dashed"),
            MapLine(11, "road_edge", np.array([[0.0, -1.75], [20.0, -1.8], [40.0, -1.75]])),
            MapLine(
                12, "crosswalk", np.array([[10.0, -2.0], [13.0, -2.0], [13.0, 2.0], [10.0, 2.0]]),
                closed=True,
            ),
        ),
    )  # fmt: skip


def two_frames() -> tuple[Frame, ...]:
    def frame(t: float) -> Frame:
        xy = np.array([[0.0 + 10 * t, 0.0], [30.0, 0.5], [12.0, -1.0]])
        heading = np.array([0.0, np.pi, np.pi / 2])
        paths = [np.array([p, p + 10.0]) for p in xy]
        return Frame.from_arrays(
            xy, heading, np.full(3, 5.0), np.array([4.5, 4.0, 0.6]), np.array([1.8, 1.8, 0.6]),
            paths, ego=0, ids=[5, 6, 7], kinds=[0, 0, 1], t=t,
        )  # fmt: skip

    return (frame(0.0), frame(0.1))


def scene() -> Scene:
    return Scene(lined_map(), two_frames(), 0.1, metadata={"source": "test"})


# ---------------------------------------------------------------------- format version 2
def test_map_lines_round_trip(tmp_path):
    path = write_scene(tmp_path / "s.mcap", scene())
    lines = read_scene(path).map.lines
    assert [(ln.id, ln.kind, ln.closed, ln.style) for ln in lines] == [
        (10, "lane_boundary", False, "dashed"),
        (11, "road_edge", False, ""),
        (12, "crosswalk", True, ""),
    ]
    for got, want in zip(lines, lined_map().lines, strict=True):
        np.testing.assert_allclose(got.points, want.points, atol=5e-4)
    # Write what was read: the same bytes (rounding is idempotent for map lines too).
    again = write_scene(tmp_path / "t.mcap", read_scene(path))
    assert again.read_bytes() == path.read_bytes()


def test_a_version_1_file_still_reads(tmp_path):
    """A version 1 file is a version 2 file without Map.lines and with version "1"."""
    path = write_scene(tmp_path / "s.mcap", Scene(LaneMap(lined_map().lanes), two_frames(), 0.1))
    data = path.read_bytes()
    marker = b"format_version\x01\x00\x00\x00" + str(sf.FORMAT_VERSION).encode()
    assert sf.FORMAT_VERSION == 2 and data.count(marker) == 1
    path.write_bytes(data.replace(marker, marker[:-1] + b"1"))
    old = read_scene(path)
    assert old.map.lines == () and len(old.map.lanes) == 1 and len(old.frames) == 2


def test_unknown_map_line_kind_is_refused(tmp_path):
    bad = LaneMap((), lines=(MapLine(1, "hedge", np.zeros((2, 2))),))
    with pytest.raises(Exception, match="kind 'hedge' is not one of lane_boundary"):
        write_scene(tmp_path / "s.mcap", Scene(bad, two_frames(), 0.1))
    assert list(tmp_path.iterdir()) == []


def test_dedupe_drops_shared_bounds_in_either_direction():
    a = MapLine(1, "lane_boundary", np.array([[0.0, 0.0], [10.0, 0.0]]))
    b = MapLine(2, "lane_boundary", np.array([[10.0, 0.001], [0.0, 0.0]]))  # same, reversed
    c = MapLine(3, "road_edge", np.array([[0.0, 5.0], [10.0, 5.0]]))
    one_point = MapLine(4, "other", np.array([[1.0, 1.0]]))
    assert [ln.id for ln in map_lines.dedupe_lines([a, b, c, one_point])] == [1, 3]


def test_commonroad_bounds_edges_and_crosswalks():
    root = ET.fromstring(
        """<commonRoad>
        <lanelet id="1"><leftBound><point><x>0</x><y>3</y></point><point><x>10</x><y>3</y></point>
          <lineMarking>dashed</lineMarking></leftBound>
          <rightBound><point><x>0</x><y>0</y></point><point><x>10</x><y>0</y></point></rightBound>
          <adjacentLeft ref="2" drivingDir="same"/></lanelet>
        <lanelet id="2"><leftBound><point><x>0</x><y>6</y></point><point><x>10</x><y>6</y></point>
          </leftBound><rightBound><point><x>0</x><y>3</y></point><point><x>10</x><y>3</y></point>
          </rightBound><adjacentRight ref="1" drivingDir="same"/></lanelet>
        <lanelet id="3"><leftBound><point><x>4</x><y>0</y></point><point><x>4</x><y>6</y></point>
          </leftBound><rightBound><point><x>6</x><y>0</y></point><point><x>6</x><y>6</y></point>
          </rightBound><laneletType>crosswalk</laneletType></lanelet>
        </commonRoad>"""
    )
    got = [(ln.id, ln.kind, ln.style, len(ln.points)) for ln in map_lines.commonroad_lines(root)]
    # Lanelet 1: its left bound (shared with 2, drawn once) is a lane boundary, its right
    # bound has no neighbour (road edge); lanelet 2's left bound is the other road edge.
    assert got == [
        (1, "lane_boundary", "dashed", 2),
        (1, "road_edge", "", 2),
        (2, "road_edge", "", 2),
        (3, "crosswalk", "", 4),
    ]


def test_av2_boundaries_and_crossings():
    def pts(*xy):
        return [{"x": x, "y": y, "z": 0.0} for x, y in xy]

    data = {
        "lane_segments": {
            "5": {"id": 5, "left_lane_boundary": pts((0, 3), (10, 3)),
                  "right_lane_boundary": pts((0, 0), (10, 0)), "left_neighbor_id": 6,
                  "right_neighbor_id": None, "left_lane_mark_type": "DASHED_WHITE",
                  "right_lane_mark_type": "SOLID_WHITE"},
        },
        "pedestrian_crossings": {
            "9": {"id": 9, "edge1": pts((2, 0), (2, 6)), "edge2": pts((4, 0), (4, 6))}
        },
    }  # fmt: skip
    got = map_lines.av2_lines(data)
    assert [(ln.id, ln.kind, ln.style, ln.closed) for ln in got] == [
        (5, "lane_boundary", "dashed_white", False),
        (5, "road_edge", "solid_white", False),
        (9, "crosswalk", "", True),
    ]
    np.testing.assert_array_equal(got[2].points, [[2, 0], [2, 6], [4, 6], [4, 0]])


def test_real_sources_carry_map_lines(shared_data, tmp_path):
    w = next(iter(waymo.read_scenes(next((shared_data / "waymo").glob("*.tfrecord")))))
    kinds = {k: sum(ln.kind == k for ln in w.map.lines) for k in sf.MAP_LINE_KINDS}
    # The sample's 301 map features: 199 lanes, 58 road lines, 28 road edges,
    # 4 crosswalks (the rest: stop signs, speed bumps, driveways).
    assert (len(w.map.lanes), kinds["lane_boundary"], kinds["road_edge"], kinds["crosswalk"]) == (
        199, 58, 28, 4,
    )  # fmt: skip
    m = av2.read_lane_map(next((shared_data / "av2").glob("*.json")))
    assert {ln.kind for ln in m.lines} == {"lane_boundary", "road_edge", "crosswalk"}
    raw = json.loads(next((shared_data / "av2").glob("*.json")).read_text())
    assert sum(ln.kind == "crosswalk" for ln in m.lines) == len(raw["pedestrian_crossings"])
    xml = next((shared_data / "commonroad").glob("*.xml"))
    c = commonroad.read_scene(xml)
    assert {ln.kind for ln in c.map.lines} >= {"lane_boundary", "road_edge"}
    back = read_scene(write_scene(tmp_path / "w.mcap", w))
    assert len(back.map.lines) == len(w.map.lines)


# ---------------------------------------------------------------------- Foxglove
def test_foxglove_channels_decode_with_foreign_readers(tmp_path):
    path = write_scene(tmp_path / "f.mcap", scene(), foxglove=True)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert schemas[fg.TOPIC_FOXGLOVE_SCENE] == schemas[fg.TOPIC_FOXGLOVE_MAP] == fg.SCHEMA_NAME
        # Foxglove's own message class on the raw bytes (not our reader) ...
        maps = [
            SceneUpdate.FromString(m.data)
            for _, _, m in reader.iter_messages(topics=[fg.TOPIC_FOXGLOVE_MAP])
        ]
    (map_update,) = maps
    (entity,) = map_update.entities
    assert entity.id == "map" and len(entity.lines) == 1 + 3  # one lane, three map lines
    crosswalk = entity.lines[-1]
    assert len(crosswalk.points) == 5  # closed: first point repeated
    # ... and the schema embedded in the file, decoded by mcap-protobuf-support.
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        frames = [
            (m.log_time, proto)
            for _, _, m, proto in reader.iter_decoded_messages(topics=[fg.TOPIC_FOXGLOVE_SCENE])
        ]
    assert [t for t, _ in frames] == [0, 100_000_000]
    (agents,) = frames[1][1].entities
    assert agents.id == "agents" and agents.frame_id == fg.FRAME_ID
    assert agents.timestamp.nanos == 100_000_000
    cubes = agents.cubes
    assert len(cubes) == 3
    assert (cubes[0].pose.position.x, cubes[0].pose.position.y) == pytest.approx((1.0, 0.0))
    assert (cubes[0].size.x, cubes[0].size.y) == pytest.approx((4.5, 1.8))
    # Heading pi/2 about z: quaternion (0, 0, sin(pi/4), cos(pi/4)).
    q = cubes[2].pose.orientation
    assert (q.z, q.w) == pytest.approx((np.sqrt(0.5), np.sqrt(0.5)))
    assert (cubes[0].color.g, cubes[1].color.g) == pytest.approx((0.78, 0.85))  # ego green
    # riskreplay's reader ignores the extra channels.
    assert len(read_scene(path).frames) == 2


def test_foxglove_schema_holds_every_import():
    fds = descriptor_pb2.FileDescriptorSet.FromString(fg.schema_data())
    names = {f.name for f in fds.file}
    for f in fds.file:
        assert set(f.dependency) <= names
    assert "foxglove/SceneUpdate.proto" in names


def test_cli_convert_foxglove(tmp_path):
    src = write_scene(tmp_path / "s.mcap", scene())
    before = src.read_bytes()
    out = tmp_path / "f.mcap"
    res = CliRunner().invoke(main, ["convert", "foxglove", str(src), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert src.read_bytes() == before
    with open(out, "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert {fg.TOPIC_FOXGLOVE_MAP, fg.TOPIC_FOXGLOVE_SCENE} <= topics
    res = CliRunner().invoke(main, ["convert", "foxglove", str(src), "-o", str(src)])
    assert res.exit_code == 1
    assert res.output.strip().splitlines()[-1].startswith("Error: ")
    assert "may not be the input" in res.output and src.read_bytes() == before


def test_rerun_mcap_check_passes_with_foxglove_channels(tmp_path):
    rerun = shutil.which("rerun", path=str(pathlib.Path(sys.executable).parent))
    if rerun is None:
        pytest.skip("the rerun CLI is not installed beside this Python")
    path = write_scene(tmp_path / "f.mcap", scene(), foxglove=True)
    res = subprocess.run([rerun, "mcap", "check", str(path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "/foxglove/scene" in res.stdout


def test_mcap_core_reads_the_file(tmp_path):
    """@mcap/core (npm), when installed: MCAP_CORE_NODE_MODULES names the folder that
    holds its node_modules (with fzstd), e.g. after ``npm install @mcap/core fzstd``."""
    modules = os.environ.get("MCAP_CORE_NODE_MODULES")
    if not modules or shutil.which("node") is None:
        pytest.skip("set MCAP_CORE_NODE_MODULES to a folder with @mcap/core and fzstd installed")
    path = write_scene(tmp_path / "f.mcap", scene(), foxglove=True)
    script = pathlib.Path(modules) / "riskreplay_mcap_check.mjs"
    shutil.copy(HERE / "fixtures" / "mcap_core_check.mjs", script)
    res = subprocess.run(["node", str(script), str(path)], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    counts = json.loads(res.stdout)["counts"]
    assert counts == {"/map": 1, "/agents": 2, "/paths": 2, "/foxglove/map": 1,
                      "/foxglove/scene": 2}  # fmt: skip


def test_commonroad_shared_bound_is_a_lane_boundary_without_adjacency_tags():
    root = ET.fromstring(
        """<commonRoad>
        <lanelet id="1"><leftBound><point><x>0</x><y>3</y></point><point><x>10</x><y>3</y></point>
          </leftBound><rightBound><point><x>0</x><y>0</y></point><point><x>10</x><y>0</y></point>
          </rightBound></lanelet>
        <lanelet id="2"><leftBound><point><x>10</x><y>3</y></point><point><x>0</x><y>3</y></point>
          </leftBound><rightBound><point><x>10</x><y>6</y></point><point><x>0</x><y>6</y></point>
          </rightBound></lanelet>
        </commonRoad>"""
    )  # lanelet 2 runs the other way; its left bound is lanelet 1's left bound, reversed
    got = [(ln.id, ln.kind) for ln in map_lines.commonroad_lines(root)]
    assert got == [(1, "lane_boundary"), (1, "road_edge"), (2, "road_edge")]
