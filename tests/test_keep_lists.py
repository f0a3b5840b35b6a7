"""``replay run --keep-lists``: the cascade's per-frame answer by agent id, the same as
``risk.filter_frame`` on the frame read back from the scene."""

from __future__ import annotations

import json

import polars as pl
from click.testing import CliRunner

from converters.scene.reader import open_scene
from replay.cli.app import main
from risk import CascadeConfig, filter_frame
from tests.test_cli_run import scene, scene_file  # noqa: F401  (fixtures)


def test_jsonl_rows_match_filter_frame(scene, tmp_path):  # noqa: F811
    out = tmp_path / "keep.jsonl"
    result = CliRunner().invoke(
        main, ["run", str(scene), "--no-rrd", "--no-progress", "--keep-lists", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert str(out) in result.output
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    frames = list(open_scene(scene).frames())
    assert len(rows) == len(frames) == 20
    config = CascadeConfig.default()
    for row, frame in zip(rows, frames, strict=True):
        answer = filter_frame(frame, config)
        assert row["kept"] == answer.kept_ids.tolist()
        assert row["dropped"] == {str(k): v for k, v in answer.dropped.items()}
        assert row["tier_behavior"] == list(answer.tiers["behavior"])
        others = set(frame.ids[frame.others].tolist())
        assert set(row["kept"]) | {int(k) for k in row["dropped"]} == others
        assert row["ego_id"] == frame.ego_id and row["frame"] == rows.index(row)


def test_parquet_keep_lists_and_a_bad_suffix(scene, tmp_path):  # noqa: F811
    out = tmp_path / "keep.parquet"
    result = CliRunner().invoke(
        main, ["run", str(scene), "--no-rrd", "--no-progress", "--keep-lists", str(out)]
    )
    assert result.exit_code == 0, result.output
    table = pl.read_parquet(out)
    assert table.height == 20
    assert table.schema["kept"] == pl.List(pl.Int64)
    assert (table["dropped_ids"].list.len() == table["dropped_by"].list.len()).all()
    bad = tmp_path / "keep.txt"
    result = CliRunner().invoke(main, ["run", str(scene), "--no-rrd", "--keep-lists", str(bad)])
    assert result.exit_code != 0
    assert result.output.startswith("Error:") and ".jsonl" in result.output
    assert not bad.exists()
