"""``replay calibrate`` on the job engine (issue 38), for the survival and the planner
reference: a failing scene is listed while the others complete, the parts folder
(--scores-cache, default OUTPUT.parts/) makes a rerun skip the complete scenes with the
same TOML, and Ray writes the same TOML as local processes."""

from __future__ import annotations

import pathlib

import pytest
from click.testing import CliRunner, Result
from jobs_fixtures import ray_instance, road_corpus  # noqa: F401

from replay.cli.app import main
from replay.jobs import read_failures

#: The two references, each with small settings that three road scenes can satisfy.
REFERENCES = {
    "survival": ("--max-fn-rate", "0"),
    "planner": (
        "--reference", "planner", "--planner", "idm", "--miss-rate", "0.4",
        "--confidence", "0.5", "--every", "0.5",
    ),
}  # fmt: skip


def calibrate(*args: object) -> Result:
    return CliRunner().invoke(main, ["calibrate", *map(str, args), "--no-progress"])


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> list[pathlib.Path]:
    return road_corpus(tmp_path_factory.mktemp("calibrate-jobs"))


@pytest.fixture(scope="module")
def local_runs(scenes, tmp_path_factory) -> dict[str, pathlib.Path]:
    """Each reference calibrated on local processes: its TOML (parts beside it)."""
    out = {}
    for name, options in REFERENCES.items():
        toml = tmp_path_factory.mktemp(f"calibrate-{name}") / "cascade.toml"
        result = calibrate(*scenes, "-o", toml, *options, "--workers", "2")
        assert result.exit_code == 0, result.output
        assert "1 failed" in result.output and "local engine" in result.output
        out[name] = toml
    return out


@pytest.mark.parametrize("reference", list(REFERENCES))
def test_a_failing_scene_is_listed_and_the_others_complete(local_runs, reference):
    toml = local_runs[reference]
    parts = toml.with_name("cascade.toml.parts")
    failures = read_failures(parts / "failures.csv")
    assert [(f.scene, f.stage) for f in failures] == [("setB/broken", "read")]
    assert len(list((parts / "parts").rglob("*.parquet"))) >= 3


@pytest.mark.parametrize("reference", list(REFERENCES))
def test_a_rerun_skips_the_complete_scenes_and_writes_the_same_toml(
    scenes, local_runs, reference, tmp_path
):
    toml = local_runs[reference]
    again = tmp_path / "again.toml"
    cache = toml.with_name("cascade.toml.parts")
    result = calibrate(*scenes, "-o", again, *REFERENCES[reference], "--scores-cache", cache)
    assert result.exit_code == 0, result.output
    assert "0 scene(s) computed, 3 skipped (complete)" in result.output
    assert _without_output_name(again) == _without_output_name(toml)


def _without_output_name(toml: pathlib.Path) -> str:
    """The TOML's text with the output file's own name (in its provenance) blanked."""
    return toml.read_text().replace(toml.name, "OUT.toml")


@pytest.mark.parametrize("reference", list(REFERENCES))
def test_ray_writes_the_local_toml(scenes, local_runs, reference, ray_instance, tmp_path):  # noqa: F811
    toml = tmp_path / "cascade.toml"
    result = calibrate(*scenes, "-o", toml, *REFERENCES[reference], "--engine", "ray")
    assert result.exit_code == 0, result.output
    assert "ray engine" in result.output and "1 failed" in result.output
    assert toml.read_text() == local_runs[reference].read_text()
    parts = toml.with_name("cascade.toml.parts")
    local = local_runs[reference].with_name("cascade.toml.parts")
    assert read_failures(parts / "failures.csv") == read_failures(local / "failures.csv")
