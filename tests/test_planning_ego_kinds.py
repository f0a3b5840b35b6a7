"""Car planners plan for vehicle egos only: ``replay plan --ego all`` skips pedestrians and
cyclists (counted in summary.json and the closing lines) unless ``--ego-kinds all``;
``plans.parquet`` says each ego's kind; a planner beside a replay skips them too."""

from __future__ import annotations

import json
import math

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from replay.cli.app import main
from replay.planning import IdmPlanner
from replay.planning.annotator import PlannerAnnotator
from risk import Frame, Scene
from tests.planner_scenes import road_map

DURATION_S = 4.0
# id: (kind, x0, y0, heading, speed): a car, a cyclist and a pedestrian that all move
# more than 5 m in 4 s (so --ego all takes each of them as an ego).
AGENTS = {
    0: ("vehicle", 0.0, 0.0, 0.0, 10.0),
    1: ("cyclist", 20.0, -1.0, 0.0, 4.0),
    2: ("pedestrian", 30.0, -6.0, math.pi / 2, 1.5),
}
N_FRAMES = round(DURATION_S / 0.1) + 1
EVERY_FRAMES = 10  # --every 1s at 10 Hz: frames 0, 10, 20, 30, 40


def _frame(t: float, ego: int = 0) -> Frame:
    ids = sorted(AGENTS)
    rows = [AGENTS[i] for i in ids]
    x = np.array([r[1] + math.cos(r[3]) * r[4] * t for r in rows])
    y = np.array([r[2] + math.sin(r[3]) * r[4] * t for r in rows])
    heading = np.array([r[3] for r in rows])
    paths = [
        np.array([[xi, yi], [xi + 300 * math.cos(h), yi + 300 * math.sin(h)]])
        for xi, yi, h in zip(x, y, heading, strict=True)
    ]
    return Frame.from_arrays(
        xy=np.stack([x, y], 1),
        heading=heading,
        speed=np.array([r[4] for r in rows]),
        length=np.array([4.5, 1.8, 0.5]),
        width=np.array([1.8, 0.6, 0.5]),
        paths=paths,
        ego=ego,
        ids=ids,
        kinds=[r[0] for r in rows],
        t=t,
    )


@pytest.fixture(scope="module")
def mixed_scene(tmp_path_factory):
    from converters.scene.writer import write_scene

    scene = Scene(
        map=road_map(),
        frames=tuple(_frame(round(k * 0.1, 6)) for k in range(N_FRAMES)),
        frame_period_s=0.1,
        metadata={"dataset": "hand-made", "scenario_id": "mixed-egos", "converter": "tests"},
        ego_id=0,
    )
    return write_scene(tmp_path_factory.mktemp("mixed") / "mixed.mcap", scene)


def _plan(*args: object):
    return CliRunner().invoke(
        main, ["plan", *map(str, args), "--no-progress", "--workers", "1", "--no-plots"]
    )


def test_ego_all_skips_pedestrians_and_cyclists_and_counts_them(mixed_scene, tmp_path):
    out = tmp_path / "out"
    result = _plan(mixed_scene, "-o", out, "--ego", "all", "--every", "1s")
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet")
    assert rows["ego_id"].unique().to_list() == [0]
    assert rows["ego_kind"].unique().to_list() == ["vehicle"]
    frames = N_FRAMES // EVERY_FRAMES + 1
    summary = json.loads((out / "summary.json").read_text())["planners"]["idm"]
    assert summary["skipped_ego_frames_by_kind"] == {"cyclist": frames, "pedestrian": frames}
    assert summary["skipped_egos_by_kind"] == {"cyclist": 1, "pedestrian": 1}
    assert summary["ego_frames"] == frames
    assert f"skipped {2 * frames} ego-frames of 2 egos that are not vehicles" in result.output
    assert "--ego-kinds all" in result.output


def test_ego_kinds_all_plans_for_every_ego(mixed_scene, tmp_path):
    out = tmp_path / "out"
    result = _plan(mixed_scene, "-o", out, "--ego", "all", "--every", "1s", "--ego-kinds", "all")
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet").filter(pl.col("filter") == "none")
    kinds = dict(rows.select("ego_id", "ego_kind").unique().iter_rows())
    assert kinds == {0: "vehicle", 1: "cyclist", 2: "pedestrian"}
    summary = json.loads((out / "summary.json").read_text())["planners"]["idm"]
    assert summary["skipped_ego_frames_by_kind"] == {}
    assert "not vehicles" not in result.output


def test_bad_ego_kinds_is_a_one_line_error(mixed_scene, tmp_path):
    result = _plan(mixed_scene, "-o", tmp_path / "out", "--ego-kinds", "cars")
    assert result.exit_code != 0
    assert "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


def test_a_planner_beside_a_replay_skips_a_pedestrian_ego():
    from outputs.sinks import FrameResult, SceneInfo

    annotator = PlannerAnnotator(IdmPlanner(), truth=True, filtered=True)
    info = SceneInfo.__new__(SceneInfo)  # annotate never reads it for a skipped ego
    annotator.info = info
    frame = _frame(0.0, ego=2)
    out = annotator.annotate(
        FrameResult(index=0, frame=frame, risks={}, cascade=None)  # type: ignore[arg-type]
    )
    assert not out["plan_all"].ok and "pedestrian" in out["plan_all"].reason
    assert out["plan_changed"] is None
    assert np.isnan(out["planner_label"]).all()
    assert annotator.skipped == {"pedestrian": 1}
    assert "skipped 1 frames whose ego is not a vehicle (pedestrian: 1)" in annotator.summary()


def test_an_unknown_ego_kinds_value_is_a_planning_error():
    from replay.planning.errors import PlanningError
    from replay.planning.inputs import plans_for

    with pytest.raises(PlanningError, match="vehicles, all"):
        plans_for(_frame(0.0), "cars")
    assert plans_for(_frame(0.0, ego=2), "all") and not plans_for(_frame(0.0, ego=2), "vehicles")
