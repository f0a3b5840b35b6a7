"""The hindsight columns of the ``replay run --table`` table (replay.core.tables, reader)."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from converters.scene.reader import open_scene, read_scene
from converters.scene.writer import write_scene
from converters.synthetic import SyntheticSettings, generate_scene
from replay.cli.app import main
from replay.core.engine import run_scene
from replay.core.tables import TableSink
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings, hindsight_truth, tracks_from_frames


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    scene = generate_scene(SyntheticSettings(n_agents=30, duration_s=4.0), seed=7)
    return write_scene(tmp_path_factory.mktemp("hs") / "s.mcap", scene)


def test_reader_tracks_match_the_decoded_frames(scene_file):
    reader = open_scene(scene_file)
    a = reader.tracks()
    b = tracks_from_frames(read_scene(scene_file).frames, frame_period_s=reader.frame_period_s)
    np.testing.assert_array_equal(a.ids, b.ids)
    np.testing.assert_array_equal(a.valid, b.valid)
    np.testing.assert_allclose(a.xy[a.valid], b.xy[b.valid])
    np.testing.assert_allclose(a.heading[a.valid], b.heading[b.valid])


def test_tracks_after_a_replay_pass_are_the_tracks_read_from_the_file(scene_file):
    """After a complete pass of entries() the reader builds the tracks from the states it
    decoded instead of reading the file again: the same tracks, field by field. After a
    partial pass it still reads every frame."""
    fresh = open_scene(scene_file).tracks()
    whole = open_scene(scene_file)
    assert sum(1 for _ in whole.entries()) == whole.n_frames
    assert whole._agent_states is not None
    partial = open_scene(scene_file)
    next(iter(partial.entries()))
    assert partial._agent_states is None
    for reader in (whole, partial):
        got = reader.tracks()
        for name in ("ids", "kinds", "valid", "xy", "heading", "length", "width"):
            np.testing.assert_array_equal(getattr(got, name), getattr(fresh, name), name)
        assert (got.t0_s, got.dt_s) == (fresh.t0_s, fresh.dt_s)


def test_run_table_carries_the_hindsight_truth(scene_file, tmp_path):
    table = tmp_path / "t.parquet"
    result = CliRunner().invoke(
        main, ["run", str(scene_file), "--table", str(table), "--no-rrd", "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    df = pl.read_parquet(table)
    assert df.columns[-3:] == ["truth_gap_m", "truth_pet_s", "truth_label"]
    assert df.schema["truth_label"] == pl.Boolean
    # Independently: the truth from the decoded frames, looked up row by row.
    scene = read_scene(scene_file)
    tracks = tracks_from_frames(scene.frames, frame_period_s=scene.frame_period_s)
    ego = int(df["ego_id"][0])
    truth = hindsight_truth(tracks, tracks.index_of([ego]), settings=HindsightSettings())
    k = df["frame"].to_numpy()  # the synthetic scene has no missing frames
    a = tracks.index_of(df["agent_id"].to_numpy())
    np.testing.assert_allclose(
        df["truth_gap_m"].fill_null(np.nan).to_numpy(), truth.gap_m[k, 0, a], equal_nan=True
    )
    np.testing.assert_allclose(
        df["truth_pet_s"].fill_null(np.nan).to_numpy(), truth.pet_s[k, 0, a], equal_nan=True
    )
    want = truth.label[k, 0, a]
    got = df["truth_label"].to_numpy()
    assert [None if w < 0 else bool(w) for w in want] == got.tolist()
    # A 4 s scene with a 5 s horizon: every window is cut, so no label is a negative.
    assert df["truth_label"].null_count() + int(df["truth_label"].sum()) == df.height


def test_in_memory_scene_and_a_shorter_horizon(scene_file):
    scene = read_scene(scene_file)
    sink = TableSink(None, hindsight=HindsightSettings(horizon_s=1.0))
    run_scene(scene, sinks=[sink], progress=False)
    df = sink.dataframe()
    # Frames whose 1 s window lies inside the 4 s scene are decided (true or false).
    last = df["frame"].max()
    early = df.filter(pl.col("frame") <= last - 10)
    assert early["truth_label"].null_count() < early.height
    assert (df.filter(pl.col("frame") > last - 10)["truth_label"].fill_null(True)).all()


def test_every_ego_gets_its_own_truth(scene_file):
    from replay.core.worker import replay_scene

    tables = replay_scene(
        scene_file, name="s", cascade=CascadeConfig.default(),
        ego="all", hindsight=HindsightSettings(horizon_s=1.0),
    )  # fmt: skip
    df = tables.agents
    assert df["ego_id"].n_unique() > 1
    scene = read_scene(scene_file)
    tracks = tracks_from_frames(scene.frames, frame_period_s=scene.frame_period_s)
    egos = np.unique(df["ego_id"].to_numpy())
    truth = hindsight_truth(
        tracks, tracks.index_of(egos), settings=HindsightSettings(horizon_s=1.0)
    )
    e = np.searchsorted(egos, df["ego_id"].to_numpy())
    k = tracks.frame_of(df["t_s"].to_numpy())
    a = tracks.index_of(df["agent_id"].to_numpy())
    want = truth.label[k, e, a]
    got = df["truth_label"].to_list()
    assert [None if w < 0 else bool(w) for w in want] == got
    assert df["truth_label"].null_count() < df.height
