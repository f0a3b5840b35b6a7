"""``replay plan`` through click's CliRunner, on the hand-made two-lane road with known
answers (tests/planner_scenes.py): the stopped car ahead changes the plan, the oncoming
car far off, the slower car behind and the car parked off the road change nothing."""

from __future__ import annotations

import importlib
import json
import pathlib
import shutil
import sys

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from replay.cli.app import main
from tests.planner_scenes import (
    BEHIND,
    ONCOMING,
    OTHERS,
    PARKED_OFF_ROAD,
    STOPPED,
    write_road_scene,
)

HAS_FISS = importlib.util.find_spec("fiss_planner") is not None
PLANNERS = ["idm", "fop"] if HAS_FISS else ["idm"]


def plan(*args: object) -> object:
    return CliRunner().invoke(main, ["plan", *map(str, args), "--no-progress", "--workers", "1"])


@pytest.fixture(scope="module")
def road(tmp_path_factory) -> pathlib.Path:
    return write_road_scene(tmp_path_factory.mktemp("road") / "road.mcap", OTHERS)


@pytest.fixture(scope="module")
def harmless_road(tmp_path_factory) -> pathlib.Path:
    """The road without the stopped car: nothing there can change the plan."""
    return write_road_scene(
        tmp_path_factory.mktemp("road") / "harmless.mcap", (ONCOMING, BEHIND, PARKED_OFF_ROAD)
    )


@pytest.mark.parametrize("planner", PLANNERS)
def test_a_cut_that_drops_the_stopped_car_changes_the_plan(road, tmp_path, planner):
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--planner", planner, "--filter", "radius:10",
                  "--filter", "nearest:1", "--filter", "cascade")  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet")
    for column in ("scene", "ego_id", "t_s", "filter", "n_agents", "filter_ms", "plan_ms",
                   "plan_ok", "changed", "max_shift_m"):  # fmt: skip
        assert column in rows.columns
    first = rows.filter(pl.col("frame") == 0)
    by = {r["filter"]: r for r in first.iter_rows(named=True)}
    assert by["none"]["plan_ok"] and by["none"]["n_agents"] == 4
    # within 10 m there is nobody at t = 0 (the stopped car is 40 m ahead)
    assert by["radius:10"]["n_agents"] == 0 and by["radius:10"]["changed"] is True
    # the nearest agent is the slower car 20 m behind: the stopped car is dropped
    assert by["nearest:1"]["changed"] is True and by["nearest:1"]["max_shift_m"] > 0.5
    # the cascade keeps the stopped car in the ego's lane: the plan is the same
    assert by["cascade"]["changed"] is False
    summary = json.loads((out / "summary.json").read_text())
    assert summary["planners"][planner]["filters"]["radius:10"]["changed"]["share"] > 0.5
    assert (out / "plan_time.png").stat().st_size > 0  # one planner: no suffix
    assert str(out / "plans.parquet") in result.output


@pytest.mark.parametrize("planner", PLANNERS)
def test_agents_that_cannot_matter_change_nothing(harmless_road, tmp_path, planner):
    out = tmp_path / "out"
    result = plan(harmless_road, "-o", out, "--planner", planner, "--filter", "radius:10",
                  "--no-plots")  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet").filter(pl.col("filter") == "radius:10")
    assert rows["plan_ok"].all()
    assert rows["changed"].to_list() == [False] * rows.height


@pytest.mark.parametrize("planner", PLANNERS)
def test_planner_truth_labels_the_stopped_car_only(road, tmp_path, planner):
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--planner", planner, "--truth", "--no-plots")
    assert result.exit_code == 0, result.output
    agents = pl.read_parquet(out / "agents.parquet").filter(pl.col("frame") == 0)
    label = dict(zip(agents["agent_id"], agents["planner_label"], strict=True))
    assert label[STOPPED] is True
    assert label[ONCOMING] is False and label[BEHIND] is False
    assert label[PARKED_OFF_ROAD] is False


@pytest.mark.parametrize("planner", PLANNERS)
def test_closed_loop_with_all_agents_does_not_collide(road, tmp_path, planner):
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--planner", planner, "--closed-loop", "--filter",
                  "radius:10", "--no-plots")  # fmt: skip
    assert result.exit_code == 0, result.output
    runs = pl.read_parquet(out / "closed_loop.parquet")
    for column in ("collisions", "min_gap_m", "time_headway_below_1s_s", "progress_m",
                   "plan_ms_median", "plan_ms_p95"):  # fmt: skip
        assert column in runs.columns
    everyone = runs.filter(pl.col("filter") == "none").row(0, named=True)
    assert everyone["collisions"] == 0 and everyone["min_gap_m"] > 0.0
    assert everyone["progress_m"] > 5.0  # it drove, towards the stopped car


def test_matched_cuts_keep_the_cascades_mean(road, tmp_path):
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--filter", "cascade", "--filter", "nearest:match",
                  "--filter", "radius:match", "--no-plots")  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    matched = summary["matched_cuts"]
    cascade_kept = summary["planners"]["idm"]["filters"]["cascade"]["mean_kept"]
    assert matched["nearest_k"] == round(matched["cascade_mean_kept"])
    assert abs(matched["cascade_mean_kept"] - cascade_kept) < 1e-9
    radius = summary["planners"]["idm"]["filters"][f"radius:{matched['radius_m']:g}"]
    assert radius["mean_kept"] >= cascade_kept - 1e-9


def test_an_unknown_filter_lists_the_valid_forms(road, tmp_path):
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--filter", "closest:3")
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:")
    assert "nearest:K" in lines[0] and "radius:R" in lines[0]
    assert not out.exists()


def test_a_frenet_planner_without_the_extra_names_the_install(road, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "fiss_planner", None)  # makes the import fail
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--planner", "fop")
    assert result.exit_code != 0
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "pip install 'riskreplay[planner]'" in lines[0]
    assert not out.exists()


def test_an_ego_without_a_path_is_counted_not_unchanged(tmp_path):
    import numpy as np

    from converters.scene.writer import write_scene
    from risk import Frame, Scene
    from tests.planner_scenes import road_map

    # The ego stands with a one-point path (no path to plan along).
    frames = [
        Frame.from_arrays(
            xy=np.array([[0.0, 0.0], [30.0, 0.0]]),
            heading=np.zeros(2),
            speed=np.array([0.0, 5.0]),
            length=np.full(2, 4.5),
            width=np.full(2, 1.8),
            paths=[np.array([[0.0, 0.0]]), np.array([[30.0, 0.0], [200.0, 0.0]])],
            ego=0,
            t=0.1 * k,
        )
        for k in range(3)
    ]
    path = write_scene(tmp_path / "nopath.mcap", Scene(road_map(), frames, 0.1, ego_id=0))
    out = tmp_path / "out"
    result = plan(path, "-o", out, "--filter", "radius:10", "--no-plots")
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet")
    assert not rows["plan_ok"].any()
    assert rows["changed"].null_count() == rows.height
    summary = json.loads((out / "summary.json").read_text())
    assert summary["planners"]["idm"]["ego_frames_without_path"] == 3
    assert "3 without a path" in result.output


def test_help_explains_the_filters():
    result = CliRunner().invoke(main, ["plan", "--help"])
    assert result.exit_code == 0
    for word in ("nearest:K", "radius:R", "--closed-loop", "plans.parquet", "--truth"):
        assert word in result.output


@pytest.mark.parametrize("planner", PLANNERS)
def test_run_with_a_planner_draws_both_plans_and_labels_the_table(road, tmp_path, planner):
    from tests.test_recordings import read_rrd, scalars

    rrd, table = tmp_path / "road.rrd", tmp_path / "road.parquet"
    result = CliRunner().invoke(
        main,
        [
            "run",
            str(road),
            "-o",
            str(rrd),
            "--table",
            str(table),
            "--planner",
            planner,
            "--no-progress",
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"Planner {planner}:" in result.output
    rows = pl.read_parquet(table).filter(pl.col("frame") == 0)
    label = dict(zip(rows["agent_id"], rows["planner_label"], strict=True))
    assert label == {STOPPED: True, ONCOMING: False, BEHIND: False, PARKED_OFF_ROAD: False}
    entities = read_rrd(rrd)
    strips = entities["/scene/ego/plan_all_agents"].column("strips", rows_with="strips")
    assert len(strips) > 0 and len(strips[0][0]) >= 2  # a plan of several points
    assert "/scene/ego/plan_filtered" in entities
    times = scalars(entities["/timing_ms/plan_all_agents"])
    assert np.isfinite(times).any() and (times[np.isfinite(times)] > 0).all()


def test_run_without_a_planner_has_no_planner_columns(road, tmp_path):
    table = tmp_path / "road.parquet"
    result = CliRunner().invoke(
        main, ["run", str(road), "--no-rrd", "--table", str(table), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    assert "planner_label" not in pl.read_parquet(table).columns


@pytest.mark.skipif(not HAS_FISS, reason="needs the optional extra riskreplay[planner]")
def test_two_planners_run_the_same_frames(road, tmp_path):
    out = tmp_path / "out"
    result = plan(road, "-o", out, "--planner", "idm", "--planner", "fiss_plus",
                  "--filter", "radius:10")  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet")
    per = rows.group_by("planner").agg(pl.len(), pl.col("frame").n_unique())
    assert sorted(per["planner"].to_list()) == ["fiss_plus", "idm"]
    assert per["len"].n_unique() == 1 and per["frame"].n_unique() == 1
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["planners"]) == {"idm", "fiss_plus"}
    assert (out / "plan_time_idm.png").exists() and (out / "plan_time_fiss_plus.png").exists()
    assert "Planner idm:" in result.output and "Planner fiss_plus:" in result.output


def test_scenes_of_two_roots_with_one_name_stay_two_and_one_file_twice_is_read_once(road, tmp_path):
    """Issue 36: d1/a/x.mcap and d2/a/x.mcap were merged into one scene (rows
    cross-matched, egos and frames miscounted); a scene given twice was planned twice."""
    for root in ("d1", "d2"):
        (tmp_path / root / "a").mkdir(parents=True)
        shutil.copyfile(road, tmp_path / root / "a" / "x.mcap")
    out = tmp_path / "out"
    result = plan(tmp_path / "d1", tmp_path / "d2", tmp_path / "d1" / "a" / "x.mcap",
                   "-o", out, "--filter", "radius:10", "--no-plots")  # fmt: skip
    assert result.exit_code == 0, result.output
    plans = pl.read_parquet(out / "plans.parquet")
    assert sorted(plans["scene"].unique().to_list()) == ["d1/a/x", "d2/a/x"]
    one = plans.filter(pl.col("scene") == "d1/a/x")
    # each scene's ego-frames once per filter (the all-agents plan and radius:10)
    assert one.group_by("filter").len()["len"].to_list() == [one.height // 2] * 2
    assert one.select("ego_id", "frame", "filter").is_duplicated().sum() == 0
