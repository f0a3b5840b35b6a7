"""INTERACTION: a tiny hand-written CSV and Lanelet2 map, the projection, errors, the CLI
and the sample."""

from __future__ import annotations

import math

import numpy as np
import pytest
from click.testing import CliRunner
from lanelet2.core import BasicPoint3d
from lanelet2.io import Origin
from lanelet2.projection import UtmProjector

from converters.errors import ConversionError
from converters.interaction import (
    DEFAULT_SIZES,
    MOVING_MPS,
    read_lane_map,
    read_rows,
    read_scene,
)
from converters.scene.reader import read_scene as read_mcap
from converters.tracks import Skipped
from replay.cli.app import main
from risk.frame import Kind

# node id -> local (x, y)
NODES = {
    1: (0, 2), 2: (50, 2), 3: (0, -2), 4: (50, -2),  # lanelet 10, east
    5: (100, 2), 6: (100, -2),  # lanelet 11 continues it
    7: (150, 2), 8: (150, -2),  # lanelet 12: its left way is stored west-pointing
    9: (0, 12), 10: (50, 12), 11: (0, 8), 12: (50, 8),  # lanelet 13, two-way
    13: (20, -6), 14: (20, 6), 15: (24, -6), 16: (24, 6),  # lanelet 14, a crosswalk
}  # fmt: skip
WAYS = {
    101: [1, 2], 102: [3, 4], 103: [2, 5], 104: [4, 6], 105: [7, 5], 106: [6, 8],
    107: [9, 10], 108: [11, 12], 109: [13, 14], 110: [15, 16],
}  # fmt: skip
LANELETS = {  # id: (left way, right way, tags)
    10: (101, 102, {"subtype": "road"}),
    11: (103, 104, {"subtype": "road", "one_way": "yes"}),
    12: (105, 106, {"subtype": "road"}),
    13: (107, 108, {"subtype": "road", "one_way": "no"}),
    14: (110, 109, {"subtype": "crosswalk"}),
}


def osm_text() -> str:
    # lat/lon of the local positions: the inverse of the projection at origin (0, 0).
    projector = UtmProjector(Origin(0.0, 0.0))
    nodes = []
    for nid, (x, y) in NODES.items():
        gps = projector.reverse(BasicPoint3d(x, y, 0.0))
        nodes.append(f'<node id="{nid}" lat="{gps.lat!r}" lon="{gps.lon!r}"/>')
    ways = []
    for wid, refs in WAYS.items():
        nds = "".join(f'<nd ref="{n}"/>' for n in refs)
        ways.append(f'<way id="{wid}">{nds}<tag k="type" v="line_thin"/></way>')
    rels = []
    for lid, (left, right, tags) in LANELETS.items():
        t = "".join(f'<tag k="{k}" v="{v}"/>' for k, v in {"type": "lanelet", **tags}.items())
        rels.append(
            f'<relation id="{lid}"><member type="way" ref="{left}" role="left"/>'
            f'<member type="way" ref="{right}" role="right"/>{t}</relation>'
        )
    rels.append('<relation id="99"><tag k="type" v="regulatory_element"/></relation>')
    return f"<?xml version='1.0'?><osm version='0.6'>{''.join(nodes + ways + rels)}</osm>"


HEADER = "track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy,psi_rad,length,width"


def vehicle_csv() -> str:
    lines = [HEADER]
    for k in range(1, 6):  # car 1: frames 1-5 east on lanelet 10 at 10 m/s
        lines.append(f"1,{k},{100 * k},car,{10 + k},0.5,10,0,0,4.2,1.9")
    for k in range(2, 5):  # truck 2: frames 2-4 west on the two-way lanelet 13
        lines.append(f"2,{k},{100 * k},truck,{40 - 0.8 * k},10,-8,0,{math.pi},8,2.5")
    return "\n".join(lines) + "\n"


@pytest.fixture
def files(tmp_path):
    osm = tmp_path / "map.osm"
    osm.write_text(osm_text())
    csv = tmp_path / "vehicle_tracks_007.csv"
    csv.write_text(vehicle_csv())
    return csv, osm


def test_lanelets_orientation_successors_two_way_and_kinds(files):
    lanes = read_lane_map(files[1]).by_id()
    for lane in lanes.values():  # the lat/lon round trip is exact to far below a millimetre
        lane.centerline[:] = np.round(lane.centerline, 6)
    assert sorted(lanes) == [-13, 10, 11, 12, 13, 14]
    np.testing.assert_allclose(lanes[10].centerline, [(0, 0), (50, 0)])
    np.testing.assert_allclose(lanes[12].centerline, [(100, 0), (150, 0)])  # left way flipped
    assert lanes[10].successors == (11,) and lanes[11].successors == (12,)
    np.testing.assert_allclose(lanes[13].centerline, [(0, 10), (50, 10)])
    np.testing.assert_allclose(lanes[-13].centerline, [(50, 10), (0, 10)])
    assert lanes[14].kind == "crosswalk" and lanes[10].kind == "vehicle"
    # The crosswalk's members are given right-then-left of the +y direction: it points -y.
    assert lanes[14].centerline[0][1] > lanes[14].centerline[-1][1]


def test_tracks_ego_period_and_paths(files):
    csv, osm = files
    scene = read_scene(csv, osm)
    # Car 1 travels 4 m, truck 2 1.6 m: nobody moves 5 m, so the most states decide.
    assert scene.metadata["ego_track"] == "1"
    assert scene.metadata["ego_choice"] == "no agent travels 5 m: the one with the most states (5)"
    assert len(scene.frames) == 5 and scene.frame_period_s == pytest.approx(0.1)
    f = scene.frames[1]
    assert f.t == pytest.approx(0.2)
    assert f.ids.tolist() == [1, 2] and f.valid.tolist() == [True, True]
    assert scene.frames[0].valid.tolist() == [True, False]
    assert f.speed.tolist() == pytest.approx([10, 8])
    assert f.heading[1] == pytest.approx(math.pi)
    assert (f.length[1], f.width[1]) == pytest.approx((8, 2.5))
    (car,) = f.agent_paths(0)
    np.testing.assert_allclose(car[-1], (150, 0), atol=1e-6)  # lanelets 10 -> 11 -> 12, to the end
    (truck,) = f.agent_paths(1)  # west on the reversed copy of the two-way lanelet
    assert truck[-1][0] < 0 and truck[1][1] == pytest.approx(10)
    scene = read_scene(csv, osm, ego=2, paths="hindsight")
    # Every step with an agent stays a frame; the truck (2) is the ego at three of them.
    assert len(scene.frames) == 5 and scene.ego_id == 2
    assert sum(f.ego_id == 2 for f in scene.frames) == 3
    with pytest.raises(ConversionError, match=r"no track with id 5 \(ids: 1, 2\)"):
        read_scene(csv, osm, ego=5)


def test_pedestrian_file_without_heading_or_sizes(tmp_path, files):
    csv = tmp_path / "pedestrian_tracks_000.csv"
    rows = ["track_id,frame_id,timestamp_ms,agent_type,x,y,vx,vy"]
    speeds = [
        (0.0, 0.0),
        (0.0, 1.0),
        (0.0, 0.05),
        (-1.0, 0.0),
        (0.0, 0.0),
    ]  # still, N, slow, W, still
    for k, (vx, vy) in enumerate(speeds, start=1):
        rows.append(f"P1,{k},{100 * k},pedestrian/bicycle,22,{k * 0.1},{vx},{vy}")
        rows.append(f"P2,{k},{100 * k},pedestrian/bicycle,30,0,0,0")
    csv.write_text("\n".join(rows) + "\n")
    scene = read_scene(csv, files[1])
    heading = [f.heading[0] for f in scene.frames]
    # back-filled from the first moving row, held while slower than MOVING_MPS
    assert MOVING_MPS > 0.05
    assert heading == pytest.approx([math.pi / 2] * 3 + [math.pi] * 2)
    assert [f.heading[1] for f in scene.frames] == [0.0] * 5  # never moves
    f = scene.frames[0]
    assert f.ids.tolist() == [0, 1] and scene.metadata["renamed_tracks"] == '{"P1": 0, "P2": 1}'
    assert f.kinds.tolist() == [Kind.PEDESTRIAN] * 2
    assert (f.length[0], f.width[0]) == DEFAULT_SIZES[Kind.PEDESTRIAN]


def test_missing_columns_and_bad_rows(tmp_path, files):
    csv = tmp_path / "t.csv"
    csv.write_text("track_id,frame_id,x,y\n1,1,0,0\n")
    with pytest.raises(
        ConversionError, match=r"missing column\(s\) timestamp_ms, agent_type, vx, vy"
    ):
        read_rows(csv)
    text = vehicle_csv().splitlines()
    text[3] = text[3].replace(",13,", ",thirteen,")  # line 4: x is not a number
    csv.write_text("\n".join(text) + "\n")
    with pytest.raises(ConversionError, match=r"t\.csv: line 4: a required value is missing"):
        read_rows(csv)
    skipped = Skipped()
    df = read_rows(csv, skip_bad=True, skipped=skipped)
    assert df.height == 7 and len(skipped) == 1 and "line 4" in skipped.what[0]


def test_map_errors(tmp_path):
    bad = tmp_path / "bad.osm"
    bad.write_text("<commonRoad/>")
    with pytest.raises(ConversionError, match=r"not an OSM map \(root element <commonRoad>"):
        read_lane_map(bad)
    bad.write_text(osm_text().replace('<way id="101">', '<way id="1001">'))
    with pytest.raises(ConversionError, match=r"lanelet 10: .*nonexistent member 101"):
        read_lane_map(bad)


def test_cli(files, tmp_path):
    csv, osm = files
    runner = CliRunner()
    out = tmp_path / "out"
    result = runner.invoke(
        main, ["convert", "interaction", str(csv), "--map", str(osm), "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    written = out / "vehicle_tracks_007.mcap"
    assert result.stdout.strip() == str(written)
    assert read_mcap(written).metadata["map_file"] == "map.osm"
    # Without --map: the only .osm beside the CSV; with none there, an error says --map.
    result = runner.invoke(main, ["convert", "interaction", str(csv), "-o", str(out)])
    assert result.exit_code == 0, result.output
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / csv.name).write_text(csv.read_text())
    result = runner.invoke(main, ["convert", "interaction", str(alone / csv.name), "-o", str(out)])
    assert result.exit_code == 1
    assert (
        result.output.strip()
        .splitlines()[-1]
        .endswith("no .osm map beside it (nor in ../maps/); name the map with --map MAP.osm")
    )
    result = runner.invoke(
        main,
        ["convert", "interaction", str(csv), "--map", str(osm), "-o", str(out), "--origin", "x"],
    )
    assert result.exit_code == 2 and "LAT,LON" in result.output


@pytest.mark.realdata
def test_real_sample(shared_data, tmp_path):
    folder = shared_data / "interaction"
    lanes = read_lane_map(folder / "TestScenarioForScripts.osm").by_id()
    # The test map was drawn on a 1 m grid: the projection must give it back exactly.
    np.testing.assert_allclose(lanes[20].centerline, [(1, 2.5), (101, 2.5)], atol=1e-5)
    np.testing.assert_allclose(lanes[21].centerline, [(101, 5.5), (1, 5.5)], atol=1e-5)
    out = tmp_path / "i.mcap"
    result = CliRunner().invoke(
        main,
        ["convert", "interaction", str(folder / "vehicle_tracks_000.csv"), "--map",
         str(folder / "TestScenarioForScripts.osm"), "-o", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    scene = read_mcap(out)
    assert len(scene.frames) == 100 and scene.frames[0].n_agents == 2
    assert sum(int(f.valid.sum()) for f in scene.frames) == 170  # every CSV row
    # Track 2 drives west on lanelet 21 (the map's westbound lane): a lane path.
    f = scene.frames[50]
    (path,) = f.agent_paths(1)
    assert path[-1][0] < f.xy[1][0] and path[1][1] == pytest.approx(5.5, abs=1e-3)
