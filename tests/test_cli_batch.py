"""``replay batch`` on the command line: exit codes, messages, summary, converters."""

from __future__ import annotations

import pathlib
import sys

import polars as pl
import pytest
from click.testing import CliRunner

from replay.batch import read_failures
from replay.cli.app import main


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    """Three short synthetic scenes and one damaged file."""
    from converters.scene.writer import write_scene
    from converters.synthetic import SyntheticSettings, generate_scene

    folder = tmp_path_factory.mktemp("cli-batch") / "scenes"
    folder.mkdir()
    settings = SyntheticSettings(n_agents=12, duration_s=0.5)
    for i in range(3):
        write_scene(folder / f"s{i}.mcap", generate_scene(settings, seed=i))
    # A damaged file: the first 2 kB of a good one (header, no summary).
    (folder / "bad.mcap").write_bytes((folder / "s0.mcap").read_bytes()[:2000])
    return folder


def _run(*args: str):
    return CliRunner().invoke(main, ["batch", *args], catch_exceptions=False)


def test_help_explains_engines_and_resuming():
    result = _run("--help")
    assert result.exit_code == 0
    for phrase in ("--engine [local|ray]", "--ray-address", "failures.csv", "resumes", "--strict"):
        assert phrase in result.output


@pytest.mark.slow
def test_batch_runs_reports_and_resumes(scenes: pathlib.Path, tmp_path: pathlib.Path):
    out = tmp_path / "out"
    result = _run(str(scenes), "-o", str(out), "--workers", "2", "--no-progress")
    assert result.exit_code == 0, result.output
    assert "replayed 3" in result.output and "failures: 1" in result.output
    assert "bad [read] SceneFormatError" in result.output
    assert f"{out / 'stats'}/" in result.output and str(out / "failures.csv") in result.output
    assert [f.scene for f in read_failures(out / "failures.csv")] == ["bad"]
    assert sorted(p.name for p in (out / "tables").iterdir()) == [
        "s0.parquet", "s1.parquet", "s2.parquet",
    ]  # fmt: skip

    again = _run(str(scenes), "-o", str(out), "--no-progress")
    assert again.exit_code == 0
    assert "replayed 0, skipped 3 (complete from an earlier run)" in again.output

    strict = _run(str(scenes), "-o", str(out), "--strict", "--no-progress")
    assert strict.exit_code == 1
    assert strict.output.splitlines()[-1].startswith("Error: 1 failure(s) (--strict)")
    assert "Traceback" not in strict.output


@pytest.mark.slow
def test_rrd_adds_recordings_to_complete_scenes(scenes: pathlib.Path, tmp_path: pathlib.Path):
    out = tmp_path / "out"
    first = _run(str(scenes / "s0.mcap"), "-o", str(out), "--workers", "1", "--no-progress")
    assert first.exit_code == 0, first.output
    # The table is complete, but a recording is asked for now: the scene runs again.
    second = _run(
        str(scenes / "s0.mcap"), "-o", str(out), "--rrd", "--workers", "1", "--no-progress"
    )
    assert second.exit_code == 0, second.output
    assert "replayed 1" in second.output
    assert (out / "recordings" / "s0.rrd").stat().st_size > 0


def test_everything_failed_is_an_error(scenes: pathlib.Path, tmp_path: pathlib.Path):
    result = _run(str(scenes / "bad.mcap"), "-o", str(tmp_path / "out"), "--workers", "1",
                  "--no-progress")  # fmt: skip
    assert result.exit_code == 1
    assert result.output.splitlines()[-1].startswith("Error: all 1 scene(s) failed; see ")


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["missing-folder"], 1, "Error: missing-folder: no such file or folder"),
        (["SCENES", "--ray-address", "auto"], 2, "--ray-address needs --engine ray"),
        (
            ["SCENES", "--convert", "waymo", "--map", "SCENES/s0.mcap"],
            2,
            "--map applies to INTERACTION track files only",
        ),
        (["SCENES", "--workers", "0"], 2, "Invalid value for '--workers'"),
    ],
)
def test_argument_errors(scenes, tmp_path, args, code, message):
    args = [a.replace("SCENES", str(scenes)) for a in args]
    result = _run(*args, "-o", str(tmp_path / "out"))
    assert result.exit_code == code
    assert message in result.output
    assert "Traceback" not in result.output


def test_ray_missing_says_how_to_install(scenes, tmp_path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    result = _run(str(scenes), "-o", str(tmp_path / "out"), "--engine", "ray", "--no-progress")
    assert result.exit_code == 1
    assert result.output.strip().splitlines()[-1] == (
        "Error: Ray is not installed; install it with: pip install 'riskreplay[ray]'"
    )


@pytest.mark.slow
@pytest.mark.realdata
def test_convert_commonroad_in_place_with_a_bad_file(shared_data: pathlib.Path, tmp_path):
    bad = tmp_path / "not_commonroad.xml"
    bad.write_text("<html><body>no scenario here</body></html>")
    inputs = [shared_data / "commonroad" / n for n in ("BEL_Putte-8_2_T-1.xml",
                                                       "DEU_TestIntersectionInteract-3_1_T-1.xml")]  # fmt: skip
    out = tmp_path / "out"
    result = _run(*map(str, inputs), str(bad), "-o", str(out), "--convert", "commonroad",
                  "--workers", "2", "--no-progress")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "converted 3 commonroad input(s)" in result.output
    assert sorted(p.name for p in (out / "scenes").iterdir()) == [
        "BEL_Putte-8_2_T-1.mcap", "DEU_TestIntersectionInteract-3_1_T-1.mcap",
    ]  # fmt: skip
    [failure] = read_failures(out / "failures.csv")
    assert (failure.stage, failure.error_type) == ("convert", "ConversionError")
    assert failure.input == str(bad)
    per_scene = pl.read_csv(out / "stats" / "per_scene.csv")
    assert per_scene["scene"].to_list() == [
        "BEL_Putte-8_2_T-1",
        "DEU_TestIntersectionInteract-3_1_T-1",
    ]

    again = _run(*map(str, inputs), str(bad), "-o", str(out), "--convert", "commonroad",
                 "--workers", "1", "--no-progress")  # fmt: skip
    assert "converted 0 commonroad input(s), skipped 3" in again.output
    assert "replayed 0, skipped 2" in again.output
    assert [f.input for f in read_failures(out / "failures.csv")] == [str(bad)]


@pytest.mark.slow
@pytest.mark.realdata
def test_convert_waymo_names_scenes_by_scenario(shared_data: pathlib.Path, tmp_path):
    tfrecord = shared_data / "waymo" / "womd_637f20cafde22ff8.tfrecord"
    truncated = tmp_path / "cut.tfrecord"
    truncated.write_bytes(tfrecord.read_bytes()[:5000])
    out = tmp_path / "out"
    result = _run(str(tfrecord), str(truncated), "-o", str(out), "--convert", "waymo",
                  "--workers", "2", "--no-progress")  # fmt: skip
    assert result.exit_code == 0, result.output
    [scene] = (out / "scenes" / "womd_637f20cafde22ff8").glob("*.mcap")
    assert (out / "tables" / "womd_637f20cafde22ff8" / f"{scene.stem}.parquet").is_file()
    failures = read_failures(out / "failures.csv")
    assert {(f.input, f.stage) for f in failures} == {(str(truncated), "convert")}


@pytest.mark.realdata
def test_detects_each_files_source_in_a_mixed_folder(shared_data: pathlib.Path, tmp_path):
    # A folder as a user has it: a CommonRoad file, an INTERACTION recording of one CSV
    # with its map, a page that only looks like data, and notes. No --convert.
    data = tmp_path / "data"
    (data / "cr").mkdir(parents=True)
    (data / "inter").mkdir()
    src = shared_data / "commonroad" / "DEU_TestIntersectionInteract-3_1_T-1.xml"
    (data / "cr" / src.name).symlink_to(src)
    for name in ("vehicle_tracks_000.csv", "TestScenarioForScripts.osm"):
        (data / "inter" / name).symlink_to(shared_data / "interaction" / name)
    (data / "cr" / "page.xml").write_text("<html><body>not a scenario</body></html>")
    (data / "README.md").write_text("notes")
    out = tmp_path / "out"
    result = _run(str(data), "-o", str(out), "--workers", "1", "--no-progress")
    assert result.exit_code == 0, result.output
    assert "converted 2 input(s)" in result.output
    # Scenes keep the inputs' folders (one folder per dataset).
    assert sorted(p.relative_to(out / "scenes").as_posix()
                  for p in (out / "scenes").rglob("*.mcap")) == [
        "cr/DEU_TestIntersectionInteract-3_1_T-1.mcap", "inter/vehicle_tracks_000.mcap",
    ]  # fmt: skip
    [failure] = read_failures(out / "failures.csv")
    assert failure.input == str(data / "cr" / "page.xml")
    assert "no converter reads this file" in failure.reason and "\n" not in failure.reason
