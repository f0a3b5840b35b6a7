"""``replay convert synthetic`` and ``replay inspect`` through click's CliRunner."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from converters.scene import schema as sf
from converters.scene import writer as mcap_io
from converters.scene.reader import open_scene, read_scene
from converters.synthetic import SyntheticSettings, generate_scene
from replay.cli.app import main


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def invoke(runner: CliRunner, *args: str):
    return runner.invoke(main, list(args), catch_exceptions=False)


def test_convert_lists_every_source_that_exists(runner):
    result = invoke(runner, "convert", "--help")
    assert result.exit_code == 0
    assert "synthetic" in result.output
    assert "atomically" in result.output


def test_synthetic_scene_file(runner, tmp_path):
    out = tmp_path / "scene.mcap"
    result = invoke(
        runner, "convert", "synthetic", "-o", str(out), "--agents", "40", "--seed", "5",
        "--duration", "2",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert str(out) in result.stdout.splitlines()[-1]  # the output path is printed last
    scene = read_scene(out)
    assert len(scene.frames) == 20
    assert scene.frames[0].n_agents == 40
    assert scene.metadata["seed"] == "5"
    # the CLI writes exactly what the Python API generates
    expected = generate_scene(SyntheticSettings(n_agents=40, duration_s=2.0), 5)
    np.testing.assert_array_equal(
        scene.frames[-1].xy, np.round(expected.frames[-1].xy * 1000) / 1000
    )


def test_synthetic_options_reach_the_generator(runner, tmp_path):
    out = tmp_path / "s.mcap"
    args = ["convert", "synthetic", "-o", str(out), "--agents", "12", "--lanes", "3"]
    result = invoke(runner, *args, "--duration", "1", "--period", "0.5", "--arm-length", "80")
    assert result.exit_code == 0, result.output
    reader = open_scene(out)
    assert reader.n_frames == 2
    assert reader.frame_period_s == 0.5
    assert reader.metadata["lanes_per_direction"] == "3"
    settings = json.loads(reader.metadata["settings"])
    assert settings["intersection"]["arm_length_m"] == 80.0
    assert len(reader.map.lanes) == 4 * (2 * 3 + 3 + 2)


def test_synthetic_situations_folder(runner, tmp_path):
    folder = tmp_path / "sit"
    result = invoke(
        runner, "convert", "synthetic", "--situations", "3", "-o", str(folder), "--seed", "10"
    )
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["situation_0000.mcap", "situation_0001.mcap", "situation_0002.mcap"]
    counts = []
    for k, name in enumerate(names):
        reader = open_scene(folder / name)
        assert reader.n_frames == 1
        assert reader.metadata["seed"] == str(10 + k)
        counts.append(reader.frame_stats().n_agents[0])
    assert all(30 <= c <= 100 for c in counts)
    assert "situations" in result.stderr  # the progress bar goes to stderr
    assert result.stdout.strip() == str(folder)


def test_situations_refuse_a_file_as_folder(runner, tmp_path):
    target = tmp_path / "x.mcap"
    target.write_text("")
    result = runner.invoke(main, ["convert", "synthetic", "--situations", "2", "-o", str(target)])
    assert result.exit_code == 2
    assert "not a folder" in result.output


def test_impossible_settings_are_one_line_errors(runner, tmp_path):
    out = tmp_path / "s.mcap"
    result = runner.invoke(main, ["convert", "synthetic", "-o", str(out), "--agents", "5000"])
    assert result.exit_code == 1
    assert result.output.startswith("Error: ")
    assert "do not fit" in result.output
    assert "Traceback" not in result.output
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_interrupted_conversion_leaves_nothing(runner, tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mcap_io, "encode_frame", boom)
    out = tmp_path / "s.mcap"
    result = runner.invoke(main, ["convert", "synthetic", "-o", str(out), "--agents", "30"])
    assert result.exit_code != 0
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- inspect


@pytest.fixture
def scene_file(tmp_path):
    scene = generate_scene(SyntheticSettings(n_agents=50, duration_s=3.0), 2)
    return mcap_io.write_scene(tmp_path / "scene.mcap", scene)


def test_inspect_table(runner, scene_file):
    result = invoke(runner, "inspect", str(scene_file))
    assert result.exit_code == 0
    out = result.output
    assert "frames          30 at 0.1 s" in out
    assert "/agents  riskreplay.scene.v1.Agents  30" in out
    assert "id 0  (a valid agent in 30 of 30 frames)" in out
    assert "converter            synthetic-intersection" in out
    assert "50 / 50 / 50 stored" in out
    assert "..." in out  # the long settings JSON is cut


def test_inspect_json_matches_the_file(runner, scene_file):
    result = invoke(runner, "inspect", str(scene_file), "--json")
    info = json.loads(result.output)
    reader = open_scene(scene_file)
    stats = reader.frame_stats()
    assert info["frames"] == 30
    assert info["duration_s"] == pytest.approx(3.0)
    assert info["t_last_s"] == pytest.approx(2.9)
    assert info["valid_agents_per_frame"] == {
        "min": int(stats.n_valid.min()),
        "median": float(np.median(stats.n_valid)),
        "max": int(stats.n_valid.max()),
    }
    assert info["ego_ids"] == [0]
    assert {c["topic"]: c["messages"] for c in info["channels"]} == {
        "/map": 1,
        "/agents": 30,
        "/paths": 30,
    }
    assert info["metadata"]["settings"] == reader.metadata["settings"]  # uncut
    assert info["lanes"] == 32
    assert info["format_version"] == sf.FORMAT_VERSION


def test_inspect_shows_labels(runner, tmp_path):
    base = generate_scene(SyntheticSettings(n_agents=30, duration_s=0.2), 1)
    scene = type(base)(base.map, base.frames, base.frame_period_s, base.metadata, {"focal": (3, 4)})
    path = mcap_io.write_scene(tmp_path / "l.mcap", scene)
    out = invoke(runner, "inspect", str(path)).output
    assert "focal  2 agents: 3, 4" in out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"not an mcap at all", "not an MCAP file"),
        (b"", "it is empty"),
    ],
)
def test_inspect_bad_files(runner, tmp_path, content, message):
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    result = runner.invoke(main, ["inspect", str(path)])
    assert result.exit_code == 1
    assert result.output.startswith("Error: ")
    assert message in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_inspect_truncated_file(runner, scene_file, tmp_path):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(scene_file.read_bytes()[:-100])
    result = runner.invoke(main, ["inspect", str(cut)])
    assert result.exit_code == 1
    assert "truncated" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_inspect_missing_file_is_a_usage_error(runner, tmp_path):
    result = runner.invoke(main, ["inspect", str(tmp_path / "nope.mcap")])
    assert result.exit_code == 2
    assert "does not exist" in result.output
