"""CommonRoad XML: a tiny hand-written scenario, errors, the CLI and the five samples."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from click.testing import CliRunner

from converters.commonroad import read_scene
from converters.errors import ConversionError
from converters.lanegraph import lanelet_centerline
from converters.scene.reader import read_scene as read_mcap
from converters.tracks import Skipped
from replay.cli.app import main
from risk.frame import Kind


def _pts(*xy):
    return "".join(f"<point><x>{x}</x><y>{y}</y></point>" for x, y in xy)


def _state(t, x, y, orientation=None, velocity=None, tag="state"):
    parts = [f"<position><point><x>{x}</x><y>{y}</y></point></position>"]
    if orientation is not None:
        parts.append(f"<orientation><exact>{orientation}</exact></orientation>")
    parts.append(f"<time><exact>{t}</exact></time>")
    if velocity == "interval":
        parts.append(
            "<velocity><intervalStart>4</intervalStart><intervalEnd>6</intervalEnd></velocity>"
        )
    elif velocity is not None:
        parts.append(f"<velocity><exact>{velocity}</exact></velocity>")
    return f"<{tag}>{''.join(parts)}</{tag}>"


def _obstacle(oid, typ, shape, states):
    first, rest = states[0], states[1:]
    traj = f"<trajectory>{''.join(_state(*s) for s in rest)}</trajectory>" if rest else ""
    return (
        f'<dynamicObstacle id="{oid}"><type>{typ}</type><shape>{shape}</shape>'
        f"{_state(*first, tag='initialState')}{traj}</dynamicObstacle>"
    )


RECT = "<rectangle><length>4.0</length><width>2.0</width></rectangle>"


def scenario_xml(extra_obstacle: str = "") -> str:
    car = _obstacle(7, "car", RECT, [(t, 10 + t, 0, 0.0, 10.0) for t in range(5)])
    ped = _obstacle(
        8, "pedestrian", "<circle><radius>0.3</radius></circle>", [(2, 30, 5), (3, 30, 5.15)]
    )
    bike = _obstacle(
        9, "bicycle", f"<polygon>{_pts((-0.9, -0.3), (0.9, -0.3), (0.9, 0.3))}</polygon>",
        [(0, 60, -1, math.pi, "interval"), (1, 59.5, -1, math.pi, "interval")],
    )  # fmt: skip
    return f"""<?xml version='1.0' encoding='UTF-8'?>
<commonRoad timeStepSize="0.1" commonRoadVersion="2020a" benchmarkID="ZAM_Tiny-1_1_T-1" source="test">
  <lanelet id="1">
    <leftBound>{_pts((0, 2), (50, 2))}</leftBound>
    <rightBound>{_pts((0, -2), (25, -2), (50, -2))}</rightBound>
    <successor ref="2"/>
    <laneletType>urban</laneletType>
  </lanelet>
  <lanelet id="2">
    <leftBound>{_pts((50, 2), (150, 2))}</leftBound>
    <rightBound>{_pts((50, -2), (150, -2))}</rightBound>
    <predecessor ref="1"/>
  </lanelet>
  <lanelet id="3">
    <leftBound>{_pts((28, -5), (28, 10))}</leftBound>
    <rightBound>{_pts((32, -5), (32, 10))}</rightBound>
    <laneletType>sidewalk</laneletType>
  </lanelet>
  {car}{ped}{bike}{extra_obstacle}
  <planningProblem id="100">
    {_state(0, 0, 0, 0.0, 5.0, tag="initialState")}
    <goalState><position><lanelet ref="2"/></position><time><exact>50</exact></time></goalState>
  </planningProblem>
</commonRoad>"""


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "ZAM_Tiny-1_1_T-1.xml"
    path.write_text(scenario_xml())
    return path


def test_obstacles_lanelets_and_the_default_ego(tiny):
    scene = read_scene(tiny)
    assert len(scene.frames) == 5  # obstacle 7 has the most states: the ego
    assert scene.metadata["ego_track"] == "7" and scene.metadata["ego_choice"].endswith(
        "the one with the most states (5)"
    )
    assert scene.metadata["scenario_id"] == "ZAM_Tiny-1_1_T-1"
    assert scene.frame_period_s == pytest.approx(0.1)
    f = scene.frames[2]
    assert f.t == pytest.approx(0.2)
    assert f.ids.tolist() == [7, 8, 9]
    assert f.kinds.tolist() == [Kind.VEHICLE, Kind.PEDESTRIAN, Kind.CYCLIST]
    assert f.valid.tolist() == [True, True, False]
    assert scene.frames[0].valid.tolist() == [True, False, True]
    # The pedestrian has no velocity or orientation: 0.15 m per 0.1 s, heading north.
    assert f.speed[1] == pytest.approx(1.5)
    assert f.heading[1] == pytest.approx(math.pi / 2)
    assert (f.length[1], f.width[1]) == pytest.approx((0.6, 0.6))  # circle diameter
    g = scene.frames[0]
    assert g.speed[2] == pytest.approx(5.0)  # interval midpoint
    assert (g.length[2], g.width[2]) == pytest.approx((1.8, 0.6))  # polygon extents
    lanes = scene.map.by_id()
    np.testing.assert_allclose(lanes[1].centerline, [(0, 0), (25, 0), (50, 0)])
    assert lanes[1].successors == (2,) and lanes[3].kind == "walkway"
    assert sorted(lanes) == [1, 2, 3]  # the goal's <lanelet ref> is not a lanelet
    # The ego follows lanelet 1 into 2 to the map's end at x = 150 (more than the
    # 10 m/s * 12 s + 10 m = 130 m it needs beyond x = 12: the whole known path).
    (path,) = f.agent_paths(0)
    np.testing.assert_allclose(path[-1], (150, 0))


def test_chosen_ego_and_unknown_ego(tiny):
    scene = read_scene(tiny, ego=9, paths="hindsight")
    # Every step with an agent is a frame; the ego (9) is missing at three of them.
    assert len(scene.frames) == 5 and scene.metadata["steps_without_ego"] == "3"
    assert scene.ego_id == 9 and scene.metadata["ego_choice"] == "--ego"
    assert sum(f.ego_id == 9 for f in scene.frames) == 2
    with pytest.raises(ConversionError, match=r"no dynamic obstacle with id 99 \(ids: 7, 8, 9\)"):
        read_scene(tiny, ego=99)


def test_centerline_of_bounds_with_different_point_counts():
    left = np.array([(0.0, 2.0), (10.0, 2.0)])
    right = np.array([(0.0, 0.0), (4.0, 0.0), (10.0, 0.0)])
    np.testing.assert_allclose(lanelet_centerline(left, right), [(0, 1), (5, 1), (10, 1)])


def test_not_commonroad_and_malformed_xml(tmp_path):
    osm = tmp_path / "map.xml"
    osm.write_text("<osm version='0.6'/>")
    with pytest.raises(ConversionError, match=r"not a CommonRoad scenario \(root element <osm>"):
        read_scene(osm)
    broken = tmp_path / "broken.xml"
    broken.write_text("<commonRoad timeStepSize='0.1'><lanelet id='1'>")
    with pytest.raises(ConversionError, match="not well-formed XML"):
        read_scene(broken)
    no_dt = tmp_path / "nodt.xml"
    no_dt.write_text(scenario_xml().replace('timeStepSize="0.1"', ""))
    with pytest.raises(ConversionError, match="timeStepSize"):
        read_scene(no_dt)


def test_bad_obstacle_stops_or_is_skipped(tmp_path):
    path = tmp_path / "bad.xml"
    bad = '<dynamicObstacle id="66"><type>car</type><initialState/></dynamicObstacle>'
    path.write_text(scenario_xml(bad))
    with pytest.raises(ConversionError, match=r"dynamicObstacle '66': missing <shape>"):
        read_scene(path)
    skipped = Skipped()
    scene = read_scene(path, skip_bad=True, skipped=skipped)
    assert scene.frames[0].ids.tolist() == [7, 8, 9]
    assert len(skipped) == 1 and "'66'" in skipped.what[0]
    result = CliRunner().invoke(
        main, ["convert", "commonroad", str(path), "-o", str(tmp_path / "o.mcap")]
    )
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert not (tmp_path / "o.mcap").exists()
    result = CliRunner().invoke(
        main, ["convert", "commonroad", str(path), "-o", str(tmp_path / "o.mcap"), "--skip-bad"]
    )
    assert result.exit_code == 0 and "dynamicObstacle '66'" in result.stderr


def test_cli_to_folder_with_ego(tiny, tmp_path):
    out = tmp_path / "out"
    result = CliRunner().invoke(
        main, ["convert", "commonroad", str(tiny), "-o", str(out), "--ego", "9"]
    )
    assert result.exit_code == 0, result.output
    written = out / "ZAM_Tiny-1_1_T-1.mcap"
    assert result.stdout.strip() == str(written)
    scene = read_mcap(written)
    assert scene.ego_id == 9 and scene.metadata["dataset"] == "commonroad"


SAMPLES = (
    "USA_US101-5_1_T-1",
    "BEL_Putte-8_2_T-1",
    "DEU_Flensburg-10_1_T-1",
    "ZAM_Tjunction-1_97_T-1",
    "DEU_TestIntersectionInteract-3_1_T-1",
)


@pytest.mark.realdata
@pytest.mark.parametrize("name", SAMPLES)
def test_real_samples(shared_data, tmp_path, name):
    src = shared_data / "commonroad" / f"{name}.xml"
    out = tmp_path / "s.mcap"
    result = CliRunner().invoke(main, ["convert", "commonroad", str(src), "-o", str(out)])
    assert result.exit_code == 0, result.output
    scene = read_mcap(out)
    root = ET.parse(src).getroot()
    obstacles = root.findall("dynamicObstacle")
    times = {
        int(o.get("id")): {
            int(float(s.findtext("time/exact")))
            for s in o.iter()
            if s.tag in ("initialState", "state")
        }
        for o in obstacles
    }
    states = {oid: len(t) for oid, t in times.items()}
    ego = int(scene.metadata["ego_track"])
    # The moving-ego rule, as a plain loop: the vehicle that gets farthest from where it
    # was first seen.
    travelled = {}
    for o in obstacles:
        if o.findtext("type") not in ("car", "truck", "bus", "taxi", "motorcycle"):
            continue
        pts = sorted(
            (float(s.findtext("time/exact")), float(s.findtext("position/point/x")),
             float(s.findtext("position/point/y")))
            for s in o.iter() if s.tag in ("initialState", "state")
        )  # fmt: skip
        travelled[int(o.get("id"))] = max(
            math.hypot(p[1] - pts[0][1], p[2] - pts[0][2]) for p in pts
        )
    assert travelled[ego] == pytest.approx(max(travelled.values()))
    # Every time step with a recorded state is a frame; the scene's ego is named apart.
    all_times = set().union(*times.values())
    assert len(scene.frames) == len(all_times) and scene.ego_id == ego
    assert sum(f.ego_id == ego for f in scene.frames) == states[ego]
    assert scene.frames[0].n_agents == len(obstacles)
    assert len(scene.map.lanes) == len(root.findall("lanelet"))
    # Every recorded state is a valid agent in its frame.
    assert sum(int(f.valid.sum()) for f in scene.frames) == sum(states.values())


def test_static_obstacles_stand_and_traffic_lights_are_counted(tmp_path):
    parked = (
        f'<staticObstacle id="50"><type>parkedVehicle</type><shape>{RECT}</shape>'
        f"{_state(0, 20, 3.5, 0.5, tag='initialState')}</staticObstacle>"
        '<trafficLight id="60"><cycle><cycleElement><duration>5</duration><color>red</color>'
        "</cycleElement></cycle></trafficLight>"
    )
    path = tmp_path / "s.xml"
    path.write_text(scenario_xml(parked))
    scene = read_scene(path)
    assert scene.metadata["static_obstacles"] == "1" and scene.metadata["traffic_lights"] == "1"
    for f in scene.frames:  # in every frame, standing at its initial pose
        [k] = np.flatnonzero(f.ids == 50)
        assert f.valid[k] and f.speed[k] == 0.0 and f.kinds[k] == Kind.VEHICLE
        np.testing.assert_allclose((*f.xy[k], f.heading[k]), (20, 3.5, 0.5))
        assert (f.length[k], f.width[k]) == (4.0, 2.0)
