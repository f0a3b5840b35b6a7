"""Argoverse 2: a tiny hand-made scenario parquet and map, errors, the CLI, the sample."""

from __future__ import annotations

import json
import math
import pathlib
import re

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from converters.av2 import DEFAULT_SIZES, parquet_to_scene, read_scenes
from converters.errors import ConversionError
from converters.scene.reader import read_scene
from replay.cli.app import main
from risk.frame import Kind

SCENARIO_ID = "tiny-0001"


def _row(t, tid, typ, cat, x, y, h, vx, vy) -> dict:
    return dict(
        observed=t < 2, track_id=tid, object_type=typ, object_category=cat, timestep=t,
        position_x=x, position_y=y, heading=h, velocity_x=vx, velocity_y=vy,
        scenario_id=SCENARIO_ID, start_timestamp=1e18, end_timestamp=1e18 + 4e8,
        num_timestamps=5, focal_track_id="10", city="test",
    )  # fmt: skip


def _rows() -> pl.DataFrame:
    """AV driving east at 5 m/s on lane 1; pedestrian 10 (focal); bus 20 (scored), missing
    at step 2; motorcyclist 30 (a fragment) from step 1 on. 5 steps at 10 Hz."""
    rows = []
    for t in range(5):
        rows.append(_row(t, "AV", "vehicle", 1, 10 + 0.5 * t, 0.0, 0.0, 5.0, 0.0))
        rows.append(_row(t, "10", "pedestrian", 3, 30.0, 5.0 - 0.1 * t, -math.pi / 2, 0.0, -1.0))
        if t != 2:
            rows.append(_row(t, "20", "bus", 2, 60 - t, 3.5, math.pi, -3.0, -4.0))
        if t >= 1:
            rows.append(_row(t, "30", "motorcyclist", 0, 0.0, 0.2, 0.0, 9.0, 0.0))
    return pl.DataFrame(rows)


def _map() -> dict:
    def seg(i, pts, succ, lane_type="VEHICLE"):
        return {
            "id": i, "centerline": [{"x": x, "y": y, "z": 0.0} for x, y in pts],
            "successors": succ, "predecessors": [], "lane_type": lane_type,
            "is_intersection": False, "left_neighbor_id": None, "right_neighbor_id": None,
        }  # fmt: skip

    return {
        "lane_segments": {
            "1": seg(1, [(0, 0), (50, 0)], [2]),
            "2": seg(2, [(50, 0), (150, 0)], []),
            "3": seg(3, [(150, 3.5), (0, 3.5)], [], "BUS"),
            "4": seg(4, [(0, -3), (150, -3)], [], "BIKE"),
        },
        "drivable_areas": {},
        "pedestrian_crossings": {},
    }


def write_scenario(folder: pathlib.Path, scenario_id: str = SCENARIO_ID) -> pathlib.Path:
    folder.mkdir(parents=True, exist_ok=True)
    parquet = folder / f"scenario_{scenario_id}.parquet"
    _rows().with_columns(pl.lit(scenario_id).alias("scenario_id")).write_parquet(parquet)
    (folder / f"log_map_archive_{scenario_id}.json").write_text(json.dumps(_map()))
    return parquet


def test_tracks_validity_ids_sizes_and_labels(tmp_path):
    scene = parquet_to_scene(write_scenario(tmp_path))
    assert len(scene.frames) == 5
    assert scene.frame_period_s == pytest.approx(0.1)
    f = scene.frames[2]
    assert f.t == pytest.approx(0.2)
    # Track order as in the file; "AV" is numbered after the largest numeric id.
    assert f.ids.tolist() == [31, 10, 20, 30]
    assert f.ego == 0 and f.ego_id == 31
    assert scene.metadata["renamed_tracks"] == '{"AV": 31}'
    assert f.valid.tolist() == [True, True, False, True]  # 'observed' is not validity
    assert scene.frames[0].valid.tolist() == [True, True, True, False]
    assert f.kinds.tolist() == [Kind.VEHICLE, Kind.PEDESTRIAN, Kind.VEHICLE, Kind.VEHICLE]
    g = scene.frames[3]
    assert g.speed[2] == pytest.approx(5.0)  # |(-3, -4)|
    assert (g.length[2], g.width[2]) == DEFAULT_SIZES["bus"]
    assert (g.length[1], g.width[1]) == DEFAULT_SIZES["pedestrian"]
    assert (g.length[3], g.width[3]) == DEFAULT_SIZES["motorcyclist"]
    assert scene.labels == {"focal": (10,), "scored": (20,)}
    lanes = scene.map.by_id()
    assert lanes[1].successors == (2,) and lanes[3].kind == "bus" and lanes[4].kind == "bike"
    # The AV follows lane 1 into lane 2 to the map's end at x = 150 (the whole known path,
    # longer than the 5 m/s * 12 s + 10 m it needs); the bus drives west on the bus lane.
    (av,) = f.agent_paths(0)
    np.testing.assert_allclose(av[-1], (150, 0))
    (bus,) = g.agent_paths(2)
    np.testing.assert_allclose(bus[-1], (57 - (5 * 12 + 10), 3.5))


def test_without_a_map_every_path_is_straight(tmp_path):
    parquet = write_scenario(tmp_path)
    (tmp_path / f"log_map_archive_{SCENARIO_ID}.json").unlink()
    scene = parquet_to_scene(parquet)
    assert scene.map.lanes == () and scene.metadata["map_file"] == ""
    assert all(len(p) == 2 for p in scene.frames[0].agent_paths(0))


def test_missing_ego_column_and_damaged_files(tmp_path):
    parquet = write_scenario(tmp_path)
    _rows().filter(pl.col("track_id") != "AV").write_parquet(parquet)
    with pytest.raises(ConversionError, match="no ego track 'AV'"):
        parquet_to_scene(parquet)
    _rows().drop("heading").write_parquet(parquet)
    with pytest.raises(ConversionError, match=r"missing column\(s\) heading"):
        parquet_to_scene(parquet)
    write_scenario(tmp_path)
    data = parquet.read_bytes()
    parquet.write_bytes(data[: len(data) // 2])
    with pytest.raises(ConversionError, match=re.escape(f"{parquet}: not a readable parquet file")):
        parquet_to_scene(parquet)


def test_bad_map_json(tmp_path):
    parquet = write_scenario(tmp_path)
    (tmp_path / f"log_map_archive_{SCENARIO_ID}.json").write_text('{"lane_segments": 3}')
    with pytest.raises(ConversionError, match="not an Argoverse 2 map"):
        parquet_to_scene(parquet)


def test_split_folder_with_a_truncated_scenario(tmp_path):
    write_scenario(tmp_path / "a", "aaa")
    bad = write_scenario(tmp_path / "b", "bbb")
    bad.write_bytes(bad.read_bytes()[:100])
    with pytest.raises(ConversionError, match=r"scenario_bbb\.parquet"):
        list(read_scenes(tmp_path))
    runner = CliRunner()
    result = runner.invoke(main, ["convert", "av2", str(tmp_path), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert (
        result.output.strip().splitlines()[-1].startswith(f"Error: {bad}: not a readable parquet")
    )
    assert not (tmp_path / "out" / "bbb.mcap").exists()
    result = runner.invoke(
        main, ["convert", "av2", str(tmp_path), "-o", str(tmp_path / "out"), "--skip-bad"]
    )
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["aaa.mcap"]
    assert "Skipped 1 bad record(s)" in result.stderr and "scenario_bbb" in result.stderr


def test_cli_scenario_folder_to_one_file(tmp_path):
    write_scenario(tmp_path / "s")
    out = tmp_path / "scene.mcap"
    result = CliRunner().invoke(
        main, ["convert", "av2", str(tmp_path / "s"), "-o", str(out), "--paths", "hindsight"]
    )
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(out)
    scene = read_scene(out)
    assert scene.labels == {"focal": (10,), "scored": (20,)}
    assert scene.metadata["paths"] == "hindsight"


@pytest.mark.realdata
def test_real_sample(shared_data, tmp_path):
    out = tmp_path / "av2.mcap"
    result = CliRunner().invoke(main, ["convert", "av2", str(shared_data / "av2"), "-o", str(out)])
    assert result.exit_code == 0, result.output
    scene = read_scene(out)
    assert len(scene.frames) == 110
    f = scene.frames[0]
    assert f.n_agents == 58
    assert len(scene.map.lanes) == 71
    assert scene.labels == {"focal": (138951,), "scored": (139344,)}
    assert scene.metadata["ego_track"] == "AV"
    assert f.ego_id == json.loads(scene.metadata["renamed_tracks"])["AV"]
    # validity is row presence: 1130 + 1304 rows in the file
    assert sum(int(fr.valid.sum()) for fr in scene.frames) == 2434


@pytest.mark.slow
@pytest.mark.realdata
def test_real_sample_replays_with_every_valid_agent_scored(shared_data, tmp_path):
    out, table = tmp_path / "av2.mcap", tmp_path / "risks.parquet"
    runner = CliRunner()
    assert (
        runner.invoke(main, ["convert", "av2", str(shared_data / "av2"), "-o", str(out)]).exit_code
        == 0
    )
    result = runner.invoke(
        main, ["run", str(out), "--no-rrd", "--table", str(table), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(table)
    scene = read_scene(out)
    expected = {(i, int(a)) for i, f in enumerate(scene.frames) for a in f.ids[f.others]}
    assert set(zip(rows["frame"].to_list(), rows["agent_id"].to_list(), strict=True)) == expected
    risks = [c for c in rows.columns if c.startswith("risk_")]
    assert rows.select(pl.all_horizontal([pl.col(c).is_finite() for c in risks])).to_series().all()


def test_cli_skip_bad_drops_a_non_finite_state(tmp_path):
    """`replay convert av2 --skip-bad` reaches the converter's bad-value rule: a NaN
    position stops the default run and is dropped, counted, with the option."""
    parquet = write_scenario(tmp_path / "s")
    df = pl.read_parquet(parquet)
    df = df.with_columns(
        pl.when(pl.int_range(pl.len()) == 1).then(float("nan")).otherwise(pl.col("position_x"))
        .alias("position_x")
    )  # fmt: skip
    df.write_parquet(parquet)
    runner = CliRunner()
    out = tmp_path / "out.mcap"
    strict = runner.invoke(main, ["convert", "av2", str(tmp_path / "s"), "-o", str(out)])
    assert strict.exit_code == 1 and not out.exists()
    result = runner.invoke(
        main, ["convert", "av2", str(tmp_path / "s"), "-o", str(out), "--skip-bad"]
    )
    assert result.exit_code == 0, result.output
    assert parquet_to_scene(parquet, skip_bad=True).metadata["bad_states_dropped"] == "1"
