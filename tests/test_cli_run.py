"""``replay run``, ``replay demo`` and ``replay calibrate`` through click's CliRunner."""

from __future__ import annotations

import pathlib

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from replay.cli.app import main
from risk import MODELS
from risk.cascade import CascadeConfig


def small_scene(seed: int = 3, n_agents: int = 30, duration_s: float = 2.0):
    from converters.synthetic import SyntheticSettings, generate_scene

    settings = SyntheticSettings(n_agents=n_agents, duration_s=duration_s)
    return generate_scene(settings, seed=seed)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> pathlib.Path:
    """A 30-agent, 2 s synthetic intersection (20 frames)."""
    from converters.scene.writer import write_scene

    return write_scene(tmp_path_factory.mktemp("scene") / "small.mcap", small_scene())


@pytest.fixture
def scene(tmp_path, scene_file) -> pathlib.Path:
    """A private copy, so outputs written beside it do not collide between tests."""
    copy = tmp_path / scene_file.name
    copy.write_bytes(scene_file.read_bytes())
    return copy


def invoke(*args: str):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_run_writes_the_recording_beside_the_scene_and_a_table(scene, tmp_path):
    table = tmp_path / "out.parquet"
    # (the paper's cascade by name: its three stages are checked below)
    result = invoke("run", scene, "--table", table, "--no-progress", "--cascade", "survival")
    assert result.exit_code == 0, result.output
    rrd = scene.with_suffix(".rrd")
    assert rrd.is_file() and rrd.stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.parquet", "small.mcap", "small.rrd"]
    out = result.output
    assert "20 frames" in out and "ego id 0" in out and "30 agents" in out
    for stage in ("path_distance", "trajectory_distance", "gaussian"):
        assert stage in out
    assert f"Open the recording with: rerun {rrd}" in out and str(table) in out

    df = pl.read_parquet(table)
    from converters.scene.reader import read_scene

    frames = read_scene(scene).frames
    assert df.height == sum(int(f.others.sum()) for f in frames)
    assert set(df["frame"].unique().to_list()) == set(range(20))
    assert [f"risk_{m}" for m in MODELS] == [c for c in df.columns if c.startswith("risk_")]
    assert {"kept_path_distance", "kept_trajectory_distance", "kept_gaussian", "dropped_by",
            "tier", "baseline"} <= set(df.columns)  # fmt: skip
    # The table agrees with the models on the first frame.
    import risk

    first = frames[0]
    expected = risk.evaluate(first, models=["path_distance"])["path_distance"][first.others]
    got = df.filter(pl.col("frame") == 0)["risk_path_distance"].to_numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    # Kept after the last stage <=> not dropped; tiers only for survivors.
    survived = df["kept_gaussian"].to_numpy()
    np.testing.assert_array_equal(survived, df["dropped_by"].is_null().to_numpy())
    assert (
        df.filter(~pl.col("kept_gaussian"))["tier"].null_count()
        == df.filter(~pl.col("kept_gaussian")).height
    )


def test_run_csv_table_and_no_rrd(scene, tmp_path):
    table = tmp_path / "out.csv"
    result = invoke("run", scene, "--table", table, "--no-rrd", "--no-progress")
    assert result.exit_code == 0, result.output
    assert not scene.with_suffix(".rrd").exists()
    assert pl.read_csv(table).height > 0
    assert "Open the recording" not in result.output


def test_run_with_another_ego(scene, tmp_path):
    table = tmp_path / "t.parquet"
    result = invoke("run", scene, "--ego", 5, "--table", table, "--no-rrd", "--no-progress")
    assert result.exit_code == 0, result.output
    assert "ego id 5" in result.output
    df = pl.read_parquet(table)
    assert (df["ego_id"] == 5).all() and 5 not in df["agent_id"].to_list()


def test_unknown_ego_is_a_one_line_error_and_writes_nothing(scene, tmp_path):
    table = tmp_path / "t.parquet"
    result = CliRunner().invoke(main, ["run", str(scene), "--ego", "9999", "--table", str(table),
                                       "--no-progress"])  # fmt: skip
    assert result.exit_code == 1
    assert result.output.startswith("Error: agent id 9999 is not a valid agent")
    assert "valid ids include 0, 1, 2" in result.output
    assert "Traceback" not in result.output and result.output.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.mcap"]  # no .rrd, no table


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({"threshold": -1.0}, r"stages\[1\]\.threshold: must be a number >= 0"),
        ({"colour": "red"}, r"stages\[1\]\.colour: unknown key"),
        ({"model": "gauss"}, r"stages\[1\]\.model: unknown model 'gauss'"),
    ],
)
def test_invalid_cascade_file_names_the_key(scene, tmp_path, edit, message):
    import tomli_w

    data = CascadeConfig.named("survival").to_dict()
    data["stages"][1].update(edit)
    bad = tmp_path / "bad.toml"
    bad.write_text(tomli_w.dumps(data))
    result = CliRunner().invoke(main, ["run", str(scene), "--cascade", str(bad)])
    assert result.exit_code == 1
    assert result.output.startswith(f"Error: {bad}: ")
    import re

    assert re.search(message, result.output), result.output
    assert not scene.with_suffix(".rrd").exists()


def test_missing_key_in_cascade_file(scene, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[[stages]]\nmodel = "gaussian"\nthreshold = 0.1\n')
    result = CliRunner().invoke(main, ["run", str(scene), "--cascade", str(bad)])
    assert result.exit_code == 1 and "tiers: missing key" in result.output


def test_frames_without_the_ego_are_skipped_with_a_warning(tmp_path):
    from converters.scene.writer import SceneWriter

    sc = small_scene()
    path = tmp_path / "gaps.mcap"
    with SceneWriter(path, sc.map, frame_period_s=sc.frame_period_s) as writer:
        for k, frame in enumerate(sc.frames):
            # Frames 4-6 name an ego (id 999) that is not in them.
            writer.add_frame(frame, ego_id=999 if 4 <= k <= 6 else None)
    result = CliRunner().invoke(
        main, ["run", str(path), "--no-rrd", "--table", str(tmp_path / "t.parquet"),
               "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "Warning: 3 frame(s) skipped because the ego (id 0) is missing" in result.output
    assert "17 frames, 3 skipped (ego missing)" in result.output


def test_bad_table_suffix_fails_before_running(scene, tmp_path):
    result = CliRunner().invoke(main, ["run", str(scene), "--table", str(tmp_path / "t.xlsx")])
    assert result.exit_code == 1 and ".parquet or .csv" in result.output
    assert not scene.with_suffix(".rrd").exists()


def test_output_with_no_rrd_is_a_usage_error(scene, tmp_path):
    result = CliRunner().invoke(
        main, ["run", str(scene), "-o", str(tmp_path / "x.rrd"), "--no-rrd"]
    )
    assert result.exit_code == 2


def test_help_explains():
    result = invoke("run", "--help")
    assert result.exit_code == 0
    for word in ("--ego", "--cascade", "--table", "--no-rrd", "survival"):
        assert word in result.output


def test_demo_writes_scene_recording_and_table(tmp_path):
    out = tmp_path / "demo"
    result = invoke("demo", "-o", out, "--agents", 15, "--no-progress")
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["intersection.mcap", "intersection.parquet", "intersection.rrd"]
    assert f"rerun {out / 'intersection.rrd'}" in result.output


# ---------------------------------------------------------------------- calibrate
def test_calibrate_then_run_drops_no_baseline_agent(tmp_path):
    """End to end: thresholds calibrated with --max-fn-rate 0 on two scenes give a cascade
    with no false negative on those scenes."""
    from converters.scene.writer import write_scene

    scenes = [write_scene(tmp_path / f"s{k}.mcap", small_scene(seed=k)) for k in (11, 12)]
    toml = tmp_path / "c.toml"
    result = invoke("calibrate", *scenes, "-o", toml, "--no-progress", "--note", "two seeds")
    assert result.exit_code == 0, result.output
    config = CascadeConfig.from_toml(toml)
    assert config.stage_names == ("path_distance", "trajectory_distance", "gaussian")
    assert "Made by: replay calibrate s11.mcap s12.mcap -o c.toml" in config.provenance
    assert "Seeds: 11-12" in config.provenance and "Note: two seeds" in config.provenance
    assert "path_distance" in result.output and f"Wrote {toml}" in result.output
    for path in scenes:
        out = invoke("run", path, "--cascade", toml, "--no-rrd", "--table",
                     tmp_path / "t.parquet", "--no-progress").output  # fmt: skip
        fn_lines = [line for line in out.splitlines() if "FN " in line]
        assert len(fn_lines) == 3 and all("FN 0 " in line for line in fn_lines), out


def test_calibrate_rejects_unknown_stage_model(tmp_path, scene_file):
    result = CliRunner().invoke(
        main, ["calibrate", str(scene_file), "-o", str(tmp_path / "c.toml"), "--stages", "nope"]
    )
    assert result.exit_code == 1 and "unknown risk model 'nope'" in result.output
    assert not (tmp_path / "c.toml").exists()


def test_a_compiled_planner_is_warmed_up_before_its_first_timed_plan(scene, tmp_path, monkeypatch):
    """``replay run --planner pdm`` loads pdm's compiled code before the first plan, so that
    the first frame's plan time in the recording and the table is a plan, not a compile."""
    from replay.planning.pdm import PdmPlanner

    calls: list[str] = []
    plan, warm_up = PdmPlanner.plan, PdmPlanner.warm_up
    monkeypatch.setattr(
        PdmPlanner, "warm_up", lambda self: calls.append("warm_up") or warm_up(self)
    )
    monkeypatch.setattr(PdmPlanner, "plan", lambda self, r: calls.append("plan") or plan(self, r))
    table = tmp_path / "t.parquet"
    result = invoke("run", str(scene), "--planner", "pdm", "--no-rrd", "--table", str(table))
    assert result.exit_code == 0, result.output
    assert calls[0] == "warm_up" and calls.count("warm_up") == 1
    assert "plan" in calls
