"""Every moving agent as the ego: the travel rule, the engine loop, ``replay run --ego all``."""

from __future__ import annotations

import pathlib

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from converters.scene.writer import write_scene
from replay.cli.app import main
from replay.core.egos import run_every_ego
from replay.core.engine import Stride
from replay.core.tables import TableSink
from replay.errors import ReplayError
from risk.frame import Frame, LaneMap, Scene
from risk.motion import moving_agent_ids, travel_extents


def _frame(t: float, xy: np.ndarray, valid: np.ndarray, ego: int) -> Frame:
    n = xy.shape[0]
    heading = np.zeros(n)
    paths = [np.stack([p, p + np.array([50.0, 0.0])]) for p in xy]
    return Frame.from_arrays(
        xy=xy, heading=heading, speed=np.full(n, 5.0), length=np.full(n, 4.5),
        width=np.full(n, 1.8), paths=paths, ego=ego, valid=valid, t=t,
        ids=np.arange(10, 10 + n),
    )  # fmt: skip


def _scene() -> Scene:
    """Four agents over 20 frames at 10 Hz:

    id 10 drives 1 m per frame (19 m in all); id 11 is parked with 0.3 m jitter (its summed
    frame-to-frame path is several metres, its extent under 1 m); id 12 drives 0.5 m per
    frame but only in frames 5..14 (4.5 m: not moving enough); id 13 drives 2 m per frame
    and appears from frame 10 on (18 m).
    """
    rng = np.random.default_rng(0)
    frames = []
    for k in range(20):
        xy = np.array(
            [
                [1.0 * k, 0.0],
                np.array([20.0, 10.0]) + rng.uniform(-0.15, 0.15, 2),
                [0.5 * k, 20.0],
                [2.0 * k, -15.0],
            ]
        )
        valid = np.array([True, True, 5 <= k <= 14, k >= 10])
        frames.append(_frame(0.1 * k, xy, valid, ego=0))
    return Scene(map=LaneMap(), frames=tuple(frames), frame_period_s=0.1)


def test_travel_extent_by_hand() -> None:
    ids, extent = travel_extents(_scene().frames)
    assert ids.tolist() == [10, 11, 12, 13]
    assert extent[0] == pytest.approx(19.0)
    assert extent[1] < 0.5  # jitter does not add up
    assert extent[2] == pytest.approx(4.5)
    assert extent[3] == pytest.approx(18.0)
    assert moving_agent_ids(_scene().frames).tolist() == [10, 13]
    assert moving_agent_ids(_scene().frames, 4.0).tolist() == [10, 12, 13]


@settings(max_examples=40, deadline=None)
@given(
    shift=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
    angle=st.floats(0, 2 * np.pi),
)
def test_travel_extent_is_rigid_motion_invariant(shift: tuple[float, float], angle: float) -> None:
    scene = _scene()
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    moved = [_frame(f.t, f.xy @ rot.T + np.array(shift), f.valid, ego=f.ego) for f in scene.frames]
    _, a = travel_extents(scene.frames)
    _, b = travel_extents(moved)
    np.testing.assert_allclose(a, b, atol=1e-6)


def test_empty_scene_has_no_moving_agents() -> None:
    ids, extent = travel_extents([])
    assert ids.size == 0 and extent.size == 0


@pytest.fixture
def scene_file(tmp_path: pathlib.Path) -> pathlib.Path:
    path = tmp_path / "egos.mcap"
    write_scene(path, _scene())
    return path


def test_every_moving_agent_becomes_the_ego(scene_file: pathlib.Path) -> None:
    sink = TableSink(None)
    summary = run_every_ego(scene_file, sinks=[sink], progress=False)
    assert summary.egos == (10, 13)
    df = sink.dataframe()
    assert sorted(df["ego_id"].unique().to_list()) == [10, 13]
    # id 13 is valid in frames 10..19 only: its replay covers exactly those frames.
    assert sorted(df.filter(pl.col("ego_id") == 13)["frame"].unique().to_list()) == list(
        range(10, 20)
    )
    # An ego never scores itself, and every other valid agent is scored in its frames.
    assert df.filter(pl.col("ego_id") == pl.col("agent_id")).height == 0
    ego10_frame12 = df.filter((pl.col("ego_id") == 10) & (pl.col("frame") == 12))
    assert sorted(ego10_frame12["agent_id"].to_list()) == [11, 12, 13]


def test_frame_stride(scene_file: pathlib.Path) -> None:
    sink = TableSink(None)
    run_every_ego(scene_file, sinks=[sink], every=5, progress=False)
    frames = sorted(sink.dataframe()["frame"].unique().to_list())
    assert frames == [0, 5, 10, 15]


def test_no_moving_agent_is_an_error(scene_file: pathlib.Path) -> None:
    with pytest.raises(ReplayError, match="no agent moves 100 m"):
        run_every_ego(scene_file, min_travel_m=100.0, progress=False)


def test_cli_run_ego_all_writes_one_table(scene_file: pathlib.Path) -> None:
    result = CliRunner().invoke(
        main, ["run", str(scene_file), "--ego", "all", "--every", "2", "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    table = scene_file.with_name("egos.egos.parquet")
    assert table.is_file()
    assert not scene_file.with_suffix(".rrd").exists()
    assert "Egos: 2 agents that move 5 m or more (10, 13)" in result.output
    assert str(table) in result.output
    df = pl.read_parquet(table)
    assert sorted(df["ego_id"].unique().to_list()) == [10, 13]
    assert set(df["frame"].unique().to_list()) <= set(range(0, 20, 2))


def test_cli_ego_option_errors(scene_file: pathlib.Path) -> None:
    runner = CliRunner()
    bad = runner.invoke(main, ["run", str(scene_file), "--ego", "some"])
    assert bad.exit_code == 2 and "neither an agent id" in bad.output
    stride = runner.invoke(main, ["run", str(scene_file), "--every", "0"])
    assert stride.exit_code == 2
    rrd = runner.invoke(main, ["run", str(scene_file), "--ego", "all", "-o", "x.rrd"])
    assert rrd.exit_code == 2 and "--ego all writes the table only" in rrd.output


def test_stride_leaves_out_egos_valid_only_between_replayed_frames(
    tmp_path: pathlib.Path,
) -> None:
    scene = _scene()
    # Agent 13 valid only in frames 11..13: with a stride of 5 no replayed frame has it.
    frames = []
    for k, f in enumerate(scene.frames):
        valid = f.valid.copy()
        valid[3] = 11 <= k <= 13
        frames.append(_frame(f.t, f.xy.copy(), valid, ego=0))
    for k, f in enumerate(frames):
        # agent 13 at 5 m per frame: 10 m over frames 11..13
        xy = f.xy.copy()
        xy[3] = [5.0 * k, -15.0]
        frames[k] = _frame(f.t, xy, f.valid, ego=0)
    path = tmp_path / "short.mcap"
    write_scene(path, Scene(map=LaneMap(), frames=tuple(frames), frame_period_s=0.1))
    assert run_every_ego(path, progress=False).egos == (10, 13)
    assert run_every_ego(path, every=5, progress=False).egos == (10,)


def test_stride_in_seconds_follows_the_frame_rate(scene_file: pathlib.Path) -> None:
    assert Stride.parse("1s").frames_at(0.1) == 10
    assert Stride.parse("1s").frames_at(0.04) == 25
    assert Stride.parse("0.01s").frames_at(0.1) == 1
    assert Stride.parse("7").frames_at(0.04) == 7
    with pytest.raises(ReplayError):
        Stride.parse("ten")
    sink = TableSink(None)
    run_every_ego(scene_file, sinks=[sink], every=Stride(seconds=0.5), progress=False)
    assert sorted(sink.dataframe()["frame"].unique().to_list()) == [0, 5, 10, 15]


def test_cli_stats_and_batch_take_ego_all(scene_file: pathlib.Path, tmp_path: pathlib.Path) -> None:
    runner = CliRunner()
    out = tmp_path / "stats"
    result = runner.invoke(
        main,
        ["stats", str(scene_file), "-o", str(out), "--ego", "all", "--every", "2",
         "--workers", "1", "--no-plots", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    per_frame = pl.read_parquet(out / "per_frame.parquet")
    assert sorted(per_frame["ego_id"].unique().to_list()) == [10, 13]
    # One situation per (ego, frame): ego 10 at the 10 even frames, ego 13 at 10..18.
    assert per_frame.height == 10 + 5

    batch_out = tmp_path / "batch"
    result = runner.invoke(
        main,
        ["batch", str(scene_file.parent), "-o", str(batch_out), "--ego", "all", "--every",
         "0.2s", "--workers", "1", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    table = pl.read_parquet(next((batch_out / "tables").glob("*.parquet")))
    assert sorted(table["ego_id"].unique().to_list()) == [10, 13]
    assert set(table["frame"].unique().to_list()) <= set(range(0, 20, 2))
    refused = runner.invoke(
        main, ["batch", str(scene_file.parent), "-o", str(batch_out), "--ego", "all", "--rrd"]
    )
    assert refused.exit_code == 2 and "cannot go with --ego all" in refused.output
