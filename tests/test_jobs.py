"""The job runner (replay.jobs) under replay evaluate and replay stats: scene identity,
failures listed while the other scenes complete, reruns that skip complete scenes, and
the same answers from local processes and from Ray."""

from __future__ import annotations

import importlib.util
import json
import os
import pathlib
import pickle

import polars as pl
import pytest
from click.testing import CliRunner
from test_cli_evaluate import straight_scene

from converters.scenarionet import MAPPING_FILE, scenario_files
from converters.scene.writer import write_scene
from replay.batch import discover
from replay.cli.app import main
from replay.jobs import (
    Inputs,
    Job,
    SceneOutput,
    SceneRef,
    fingerprint,
    read_failures,
    resolve_inputs,
    run_jobs,
    scene_refs,
)
from replay.jobs.runner import part_path

HAS_RAY = importlib.util.find_spec("ray") is not None


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """Three scenes in two datasets (two of them with an agent that comes close)."""
    root = tmp_path_factory.mktemp("jobs")
    (root / "setA").mkdir()
    (root / "setB").mkdir()
    write_scene(root / "setA" / "S_SiteA-1_1.mcap", straight_scene(crossing=True))
    write_scene(root / "setA" / "S_SiteA-1_2.mcap", straight_scene())
    write_scene(root / "setB" / "S_SiteB-2_1.mcap", straight_scene(crossing=True))
    return root


# ---------------------------------------------------------------------- identity
def test_keys_that_differ_only_in_unsafe_characters_get_their_own_part_files(tmp_path):
    parts = tmp_path / "parts"
    assert part_path(parts, "t", "a b") != part_path(parts, "t", "a_b")
    assert part_path(parts, "t", "d1/x") == parts / "t" / "d1" / "x.parquet"


def test_same_relative_name_under_two_roots_is_two_scenes(tmp_path):
    for d in ("d1", "d2"):
        (tmp_path / d / "a").mkdir(parents=True)
        (tmp_path / d / "a" / "x.mcap").write_bytes(d.encode())
    refs = scene_refs(resolve_inputs([tmp_path / "d1", tmp_path / "d2"]))
    assert [r.key for r in refs] == ["d1/a/x", "d2/a/x"]


def test_one_folder_keeps_file_names_and_a_scene_beside_a_table_keeps_suffixes(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"1")
    (tmp_path / "y.mcap").write_bytes(b"2")
    assert [r.key for r in scene_refs(resolve_inputs([tmp_path]))] == ["x", "y"]
    refs = scene_refs(Inputs((tmp_path / "x.mcap",), (tmp_path / "x.parquet",)))
    assert [r.key for r in refs] == ["x.mcap", "x.parquet"]


def test_the_same_file_given_twice_or_through_a_link_is_read_once(tmp_path):
    (tmp_path / "data").mkdir()
    scene = tmp_path / "data" / "x.mcap"
    scene.write_bytes(b"1")
    (tmp_path / "link.mcap").symlink_to(scene)
    os.link(scene, tmp_path / "hard.mcap")
    found = resolve_inputs(
        [tmp_path / "data", scene, tmp_path / "link.mcap", tmp_path / "hard.mcap"]
    )
    assert found.scenes == (scene,)


# ---------------------------------------------------------------------- failures, resume
def _summary(out: pathlib.Path) -> dict:
    data = json.loads((out / "summary.json").read_text())
    data.pop("time_s", None)
    return data


def test_a_failing_scene_is_listed_and_the_others_complete_then_a_rerun_skips(corpus, tmp_path):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for f in corpus.rglob("*.mcap"):
        (scenes / f.name).symlink_to(f)
    (scenes / "broken.mcap").write_bytes(b"not an mcap file")
    out = tmp_path / "out"
    args = ("evaluate", scenes, "-o", out, "--bootstrap", "20", "--no-plots", "--no-progress")
    first = invoke(*args, "--workers", "2")
    assert first.exit_code == 0, first.output
    assert "3 scene(s) computed" in first.output and "1 failed" in first.output
    [failure] = read_failures(out / "failures.csv")
    assert failure.scene == "broken" and failure.stage == "read"
    assert sorted(p.stem for p in (out / "parts" / "agents").glob("*.parquet")) == [
        "S_SiteA-1_1", "S_SiteA-1_2", "S_SiteB-2_1",
    ]  # fmt: skip
    summary = _summary(out)
    assert summary["scenes"] == 3 and summary["failed_scenes"] == ["broken"]
    again = invoke(*args, "--workers", "2")
    assert again.exit_code == 0, again.output
    assert "0 scene(s) computed, 3 skipped" in again.output
    assert _summary(out) == summary
    # Other replay settings: the scenes are recomputed, and the run says so.
    other = invoke(*args, "--workers", "1", "--every", "2")
    assert "3 recomputed" in other.output


def test_every_scene_failing_is_an_error(tmp_path):
    (tmp_path / "a.mcap").write_bytes(b"junk")
    r = invoke("stats", tmp_path / "a.mcap", "-o", tmp_path / "out", "--no-progress")
    assert r.exit_code == 1 and r.output.startswith("Error: every input failed (1): ")
    assert r.output.count("\n") == 1 and "a.mcap" in r.output
    assert not (tmp_path / "out").exists()  # nothing half-written


# ---------------------------------------------------------------------- local against Ray
def _tables(out: pathlib.Path, names: list[str], drop_prefix: str = "") -> dict:
    tables = {}
    for name in names:
        df = pl.read_parquet(out / f"{name}.parquet")
        tables[name] = df.select([c for c in df.columns if not (drop_prefix and drop_prefix in c)])
    return tables


def _untimed(value):
    """``value`` without the keys that hold wall-clock times."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if "time" not in k and k != "compute"}
    if isinstance(value, list):
        return [_untimed(v) for v in value]
    return value


@pytest.mark.skipif(not HAS_RAY, reason="ray is not installed (pip install 'riskreplay[ray]')")
def test_ray_gives_the_local_answers_for_evaluate_and_stats(corpus, tmp_path):
    runs = {}
    for engine in ("local", "ray"):
        ev, st = tmp_path / f"ev-{engine}", tmp_path / f"st-{engine}"
        common = ("--engine", engine, "--workers", "2", "--no-plots", "--no-progress")
        r = invoke("evaluate", corpus, "-o", ev, "--bootstrap", "50", *common)
        assert r.exit_code == 0, r.output
        assert f"{engine} engine" in r.output
        # a local Ray instance keeps Ray's default authentication, without a warning about it
        assert "Token authentication" not in r.output
        r = invoke("stats", corpus, "-o", st, *common)
        assert r.exit_code == 0, r.output
        runs[engine] = (ev, st)
    (ev_l, st_l), (ev_r, st_r) = runs["local"], runs["ray"]
    assert _summary(ev_l) == _summary(ev_r)
    names = ["roc", "miss_rates", "budgets", "positives"]
    for name, df in _tables(ev_l, names).items():
        assert df.equals(_tables(ev_r, names)[name]), name
    # Stats: timing fields and columns aside (compute times differ from run to run).
    stats_l = _untimed(json.loads((st_l / "summary.json").read_text()))
    assert stats_l == _untimed(json.loads((st_r / "summary.json").read_text()))
    assert stats_l["cascade"]["stages"]  # the comparison kept the substance
    for name in ("roc", "errors", "per_scene"):
        a, b = _tables(st_l, [name], "time")[name], _tables(st_r, [name], "time")[name]
        assert a.equals(b), name


def test_batch_reads_a_file_found_through_a_link_once(tmp_path):
    (tmp_path / "data").mkdir()
    scene = tmp_path / "data" / "x.mcap"
    write_scene(scene, straight_scene(duration_s=1.0))
    (tmp_path / "link.mcap").symlink_to(scene)
    found = discover([tmp_path / "data", tmp_path / "link.mcap"])
    assert [f.path for f in found] == [tmp_path / "data" / "x.mcap"]


def test_a_scenarionet_mapping_naming_one_file_twice_converts_it_once(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.pkl").write_bytes(b"scenario")
    (tmp_path / "b.pkl").symlink_to(tmp_path / "sub" / "a.pkl")
    (tmp_path / MAPPING_FILE).write_bytes(pickle.dumps({"a.pkl": "sub", "b.pkl": ""}))
    assert scenario_files(tmp_path) == [tmp_path / "b.pkl"]


# ---------------------------------------------------------------------- the runner alone
def killing_job(ref: SceneRef, settings: str) -> SceneOutput:
    """A job whose worker process dies on the scene named ``settings`` (module-level, so
    that spawned workers can import it)."""
    if ref.key == settings:
        os._exit(3)  # a crash in native code, the out-of-memory killer
    return SceneOutput(
        {"rows": pl.DataFrame({"scene": [ref.key], "size": [ref.path.stat().st_size]})}
    )


def test_a_worker_that_dies_is_listed_and_the_others_complete(tmp_path):
    for name in ("a", "b", "c", "d"):
        (tmp_path / f"{name}.mcap").write_bytes(name.encode() * 3)
    refs = scene_refs(resolve_inputs([tmp_path]))
    job = Job("test", killing_job, "c", fingerprint("test", {"kill": "c"}))
    report = run_jobs(job, refs, tmp_path / "out", workers=2, progress=False)
    assert [d.ref.key for d in report.done] == ["a", "b", "d"]
    [failure] = report.failures
    assert (failure.scene, failure.stage, failure.error_type) == ("c", "worker", "WorkerDied")
    assert read_failures(tmp_path / "out" / "failures.csv") == [failure]
    rows = report.scan("rows").collect()
    assert rows["scene"].to_list() == ["a", "b", "d"] and rows["size"].to_list() == [3, 3, 3]
    # The rerun skips the three complete scenes and tries the failed one again; a worker
    # killed mid-write left a temporary file: it goes.
    stale = tmp_path / "out" / "parts" / "rows" / ".c.parquet.0123456789ab.tmp"
    stale.write_bytes(b"half")
    again = run_jobs(job, refs, tmp_path / "out", workers=2, progress=False)
    assert not stale.exists()
    assert (again.skipped, again.computed, len(again.failures)) == (3, 0, 1)


def interrupted_job(ref: SceneRef, settings: str) -> SceneOutput:
    """A job stopped (Ctrl-C, SIGTERM) while it runs the scene named ``settings``."""
    if ref.key == settings:
        raise KeyboardInterrupt
    return SceneOutput({"rows": pl.DataFrame({"scene": [ref.key]})})


def test_a_stopped_run_says_which_scenes_it_kept_and_a_rerun_resumes(tmp_path):
    for name in ("a", "b", "c"):
        (tmp_path / f"{name}.mcap").write_bytes(name.encode())
    refs = scene_refs(resolve_inputs([tmp_path]))
    out = tmp_path / "out"
    stopped = Job("test", interrupted_job, "c", fingerprint("test", {"stop": "c"}))
    with pytest.raises(KeyboardInterrupt) as info:
        run_jobs(stopped, refs, out, workers=1, progress=False)
    kept = info.value.kept  # the line the CLI prints after "Stopped by SIGINT: "
    assert kept.startswith("2 complete scene(s) of test are kept in ") and "resume" in kept
    # Stopped before anything was complete: nothing to say beyond the CLI's default line.
    with pytest.raises(KeyboardInterrupt) as first:
        run_jobs(Job("first", interrupted_job, "a", "f1"), refs, tmp_path / "o2", workers=1,
                 progress=False)  # fmt: skip
    assert not getattr(first.value, "kept", None)
    resumed = run_jobs(Job("test", interrupted_job, "none", stopped.fingerprint), refs, out,
                       workers=1, progress=False)  # fmt: skip
    assert (resumed.skipped, resumed.computed) == (2, 1)


def test_a_rerun_with_every_scene_complete_starts_no_engine(tmp_path, monkeypatch):
    """``shared_engine`` opens its engine (a local Ray instance, a cluster connection)
    only when a job has a scene to run."""
    from replay.jobs import place as place_module

    for name in ("a", "b"):
        (tmp_path / f"{name}.mcap").write_bytes(name.encode())
    refs = scene_refs(resolve_inputs([tmp_path]))
    opened: list[str] = []
    real = place_module.make_engine

    def counting(name, **kwargs):
        opened.append(name)
        return real(name, **kwargs)

    monkeypatch.setattr(place_module, "make_engine", counting)
    job = Job("test", interrupted_job, "none", fingerprint("test", {"stop": "none"}))
    where = place_module.JobPlace(tmp_path / "out", engine="local", workers=2, progress=False)
    for expected_opened, expected_computed in ((1, 2), (1, 0)):
        with place_module.shared_engine(where, scenes=2) as shared:
            report = place_module.run_job(job, refs, shared, "test")
        assert report.computed == expected_computed and len(opened) == expected_opened
