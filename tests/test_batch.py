"""The batch layer: discovery, done-markers, tasks, engines (local processes and Ray).

One small synthetic dataset per module (6 scenes of 20 agents over 1 s, a truncated
MCAP and a scene whose ego is never present) is replayed by both engines; the local run
is shared by the tests that look at its outputs.
"""

from __future__ import annotations

import json
import os
import pathlib
import sys
from types import SimpleNamespace

import polars as pl
import pytest

from replay import batch as B
from replay.batch.driver import _Run
from replay.batch.tasks import _scene_name
from replay.errors import ReplayError
from risk.cascade import CascadeConfig

N_GOOD = 6


# ---------------------------------------------------------------------- the dataset
def _write_dataset(folder: pathlib.Path) -> pathlib.Path:
    from converters.scene.writer import SceneWriter, write_scene
    from converters.synthetic import SyntheticSettings, generate_scene

    folder.mkdir(parents=True, exist_ok=True)
    settings = SyntheticSettings(n_agents=20, duration_s=1.0)
    for i in range(N_GOOD):
        write_scene(folder / f"scene_{i}.mcap", generate_scene(settings, seed=i))
    # A damaged file: the first 2 kB of a good one (header, no summary).
    good = (folder / "scene_0.mcap").read_bytes()
    (folder / "broken.mcap").write_bytes(good[:2000])
    # A scene whose recorded ego (id 9999) is in none of its frames.
    scene = generate_scene(settings, seed=99)
    with SceneWriter(folder / "sub" / "no_ego.mcap", scene.map, frame_period_s=0.1) as w:
        for frame in scene.frames:
            w.add_frame(frame, ego_id=9999)
    return folder


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    folder = tmp_path_factory.mktemp("batch") / "in"
    (folder / "sub").mkdir(parents=True)
    return _write_dataset(folder)


@pytest.fixture(scope="module")
def settings() -> B.BatchSettings:
    return B.BatchSettings(cascade=CascadeConfig.default())


@pytest.fixture(scope="module")
def local_run(dataset: pathlib.Path, settings: B.BatchSettings, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out-local"
    report = B.run_batch([dataset], out, settings, engine="local", workers=2, progress=False)
    return out, report, _summary_without_times(out)


def _summary_without_times(out: pathlib.Path) -> dict:
    """summary.json without wall-clock times (they differ from run to run)."""
    summary = json.loads((out / "stats" / "summary.json").read_text())
    assert summary["cascade"]["timing_available"]  # times were collected by the workers
    summary["cascade"].pop("compute")
    return _drop_times(summary)


def _drop_times(value):
    if isinstance(value, dict):
        return {k: _drop_times(v) for k, v in value.items() if not k.endswith("time_s")}
    if isinstance(value, list):
        return [_drop_times(v) for v in value]
    return value


# ---------------------------------------------------------------------- discovery
def test_discover_walks_folders_excludes_output_and_names_uniquely(tmp_path: pathlib.Path):
    for rel in ("a/x.mcap", "b/x.mcap", "b/deep/y.mcap", "b/notes.txt", "out/scenes/z.mcap",
                "c/Q.mcap", "c/q.mcap"):  # fmt: skip
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    found = B.discover([tmp_path], exclude=tmp_path / "out")
    names = {f.path.relative_to(tmp_path).as_posix(): f.name for f in found}
    assert set(names) == {"a/x.mcap", "b/x.mcap", "b/deep/y.mcap", "c/Q.mcap", "c/q.mcap"}
    # Names keep the folders below the input folder (one output folder per dataset).
    assert names["a/x.mcap"] == "a/x" and names["b/x.mcap"] == "b/x"
    assert names["b/deep/y.mcap"] == "b/deep/y"
    # Names that still collide (by case) get a hash of their path, and differ.
    assert names["c/Q.mcap"].startswith("c/Q-") and names["c/q.mcap"].startswith("c/q-")
    assert names["c/Q.mcap"] != names["c/q.mcap"]
    # Stable: the same inputs give the same names.
    assert B.discover([tmp_path], exclude=tmp_path / "out") == found


def test_discover_names_below_the_deepest_input_folder_and_files_given_alone(
    tmp_path: pathlib.Path,
):
    for rel in ("data/sind/s1.mcap", "data/ind/deep/s2.mcap", "alone/s3.mcap"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    found = B.discover(
        [tmp_path / "data", tmp_path / "data" / "ind", tmp_path / "alone" / "s3.mcap"]
    )
    names = {f.path.relative_to(tmp_path).as_posix(): f.name for f in found}
    assert len(found) == 3  # s2, found through two inputs, is one input
    assert names == {
        "data/sind/s1.mcap": "sind/s1",
        "data/ind/deep/s2.mcap": "deep/s2",  # under the deepest input folder, data/ind
        "alone/s3.mcap": "s3",  # a file given by itself
    }


def test_discover_raw_files_and_waymo_shard_names(tmp_path: pathlib.Path):
    for name in ("training.tfrecord-00000-of-01000", "training.tfrecord-00001-of-01000", "a.mcap"):
        (tmp_path / name).write_bytes(b"")
    found = B.discover([tmp_path], convert="waymo")
    assert [f.name for f in found] == ["training-00000-of-01000", "training-00001-of-01000"]


def test_discover_errors(tmp_path: pathlib.Path):
    with pytest.raises(ReplayError, match="no such file or folder"):
        B.discover([tmp_path / "missing"])
    (tmp_path / "x.xml").write_text("<a/>")
    with pytest.raises(ReplayError, match=r"no input files \(.*\*\.mcap.*1 file\(s\) no converter"):
        B.discover([tmp_path])


# ---------------------------------------------------------------------- one task
def _task(dataset: pathlib.Path, out: pathlib.Path, name: str, scene: str, rrd: bool = False):
    s = B.BatchSettings(cascade=CascadeConfig.default(), rrd=rrd)
    run = _Run(B.Layout(out), s)
    return run.replay_task(name, str(dataset / scene), dataset / scene)


def test_replay_one_writes_tables_then_marker(dataset: pathlib.Path, tmp_path: pathlib.Path):
    task = _task(dataset, tmp_path, "scene_1", "scene_1.mcap")
    outcome = B.replay_one(task)
    assert outcome.failure is None and outcome.done is not None
    agents = pl.read_parquet(task.table)
    frames = pl.read_parquet(task.frames_table)
    assert outcome.done.frames == frames.height == 10  # 1 s at 10 Hz
    assert agents["scene"].unique().to_list() == ["scene_1"]
    assert agents.height == frames["n_others"].sum() > 0
    marker = json.loads(pathlib.Path(task.marker).read_text())
    assert marker["outputs"]["table"]["size"] == os.path.getsize(task.table)
    # Complete now; and a different cascade (settings digest) makes it incomplete.
    scene = dataset / "scene_1.mcap"
    assert B.completed_scene(pathlib.Path(task.marker), scene, task.digest, rrd=False)
    assert B.completed_scene(pathlib.Path(task.marker), scene, "other", rrd=False) is None
    # Asking for a recording that the marker does not list: incomplete.
    assert B.completed_scene(pathlib.Path(task.marker), scene, task.digest, rrd=True) is None


def test_completeness_follows_input_and_outputs(dataset: pathlib.Path, tmp_path: pathlib.Path):
    scene = tmp_path / "copy.mcap"
    scene.write_bytes((dataset / "scene_2.mcap").read_bytes())
    s = B.BatchSettings(cascade=CascadeConfig.default())
    task = _Run(B.Layout(tmp_path / "out"), s).replay_task("copy", str(scene), scene)
    assert B.replay_one(task).failure is None
    marker = pathlib.Path(task.marker)
    assert B.completed_scene(marker, scene, task.digest, rrd=False) is not None
    # The input changed (new modification time): recompute.
    st = scene.stat()
    os.utime(scene, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert B.completed_scene(marker, scene, task.digest, rrd=False) is None
    os.utime(scene, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert B.completed_scene(marker, scene, task.digest, rrd=False) is not None
    # An output lost or truncated: recompute.
    pathlib.Path(task.frames_table).write_bytes(b"x")
    assert B.completed_scene(marker, scene, task.digest, rrd=False) is None
    # A damaged marker: recompute.
    assert B.replay_one(task).failure is None
    marker.write_text("{not json")
    assert B.completed_scene(marker, scene, task.digest, rrd=False) is None


def test_conversion_complete_until_input_map_or_scene_changes(tmp_path: pathlib.Path):
    from replay.batch.markers import write_convert_marker

    src, osm, scene = tmp_path / "tracks.csv", tmp_path / "map.osm", tmp_path / "s.mcap"
    for f in (src, osm, scene):
        f.write_text(f.name)
    task = B.ConvertTask(str(src), "tracks", "interaction", "map", None, str(tmp_path),
                         str(tmp_path / "m.json"), "d1")  # fmt: skip
    failure = B.Failure(str(src), "", "convert", "ConversionError", "row 7: bad speed")
    write_convert_marker(task, [("tracks", str(scene))], [failure], [osm])
    marker = pathlib.Path(task.marker)
    assert B.completed_conversion(marker, src, "d1") == ([("tracks", str(scene))], [failure])
    assert B.completed_conversion(marker, src, "d2") is None  # other settings
    for changed in (src, osm, scene):
        st = changed.stat()
        os.utime(changed, ns=(st.st_atime_ns, st.st_mtime_ns + 1000))
        assert B.completed_conversion(marker, src, "d1") is None, changed.name
        os.utime(changed, ns=(st.st_atime_ns, st.st_mtime_ns))
    scene.unlink()
    assert B.completed_conversion(marker, src, "d1") is None


def test_replay_one_reports_failures_by_stage(
    dataset: pathlib.Path, tmp_path: pathlib.Path, monkeypatch: pytest.MonkeyPatch
):
    broken = B.replay_one(_task(dataset, tmp_path, "broken", "broken.mcap"))
    assert broken.done is None
    assert (broken.failure.stage, broken.failure.error_type) == ("read", "SceneFormatError")
    assert "\n" not in broken.failure.reason and "broken.mcap" in broken.failure.reason

    no_ego = B.replay_one(_task(dataset, tmp_path, "no_ego", "sub/no_ego.mcap"))
    assert (no_ego.failure.stage, no_ego.failure.error_type) == ("replay", "ReplayError")
    assert "9999" in no_ego.failure.reason

    # A crash inside a model: an unexpected exception names where it happened.
    import risk

    def crash(*args, **kwargs):
        raise ZeroDivisionError("model blew up")

    monkeypatch.setattr(risk, "evaluate", crash)
    task = _task(dataset, tmp_path, "scene_3", "scene_3.mcap")
    crashed = B.replay_one(task)
    assert (crashed.failure.stage, crashed.failure.error_type) == ("replay", "ZeroDivisionError")
    assert crashed.failure.reason.startswith("model blew up (at test_batch.py:")
    assert not pathlib.Path(task.table).exists() and not pathlib.Path(task.marker).exists()


def test_failures_csv_round_trip(tmp_path: pathlib.Path):
    rows = [
        B.Failure("/d/a,b.mcap", "a_b", "read", "SceneFormatError", 'quote " and, comma'),
        B.Failure("/d/c.tfrecord", "", "convert", "ConversionError", "record 3: CRC mismatch"),
    ]
    B.write_failures(tmp_path / "failures.csv", rows)
    assert B.read_failures(tmp_path / "failures.csv") == rows
    B.write_failures(tmp_path / "none.csv", [])
    assert (tmp_path / "none.csv").read_text() == ",".join(B.FAILURE_COLUMNS) + "\n"


# ---------------------------------------------------------------------- engines
def _double_or_die(x: int) -> int:
    """A task for the engine tests: kills its worker process for x < 0."""
    if x < 0:
        os._exit(3)
    return 2 * x


@pytest.mark.slow
def test_local_engine_isolates_a_task_that_kills_its_worker():
    engine = B.LocalEngine(workers=2)
    try:
        for x in (1, 2, -1, 3, 4):
            engine.submit(_double_or_die, x)
        results = {}
        while engine.pending:
            for task, outcome in engine.results():
                results[task] = outcome
    finally:
        engine.close()
    assert isinstance(results.pop(-1), B.WorkerDied)
    assert results == {1: 2, 2: 4, 3: 6, 4: 8}


@pytest.mark.slow
def test_local_engine_replaces_a_pool_whose_idle_worker_was_killed():
    import multiprocessing
    import signal
    import time

    engine = B.LocalEngine(workers=2)
    try:
        engine.submit(_double_or_die, 1)
        assert engine.results() == [(1, 2)]
        victim = multiprocessing.active_children()[0]  # a pool worker, idle now
        os.kill(victim.pid, signal.SIGKILL)
        time.sleep(0.5)  # the pool notices and marks itself broken
        for x in (5, 6, 7):
            engine.submit(_double_or_die, x)
        results = {}
        while engine.pending:
            results.update(engine.results())
    finally:
        engine.close()
    assert results == {5: 10, 6: 12, 7: 14}


def test_ray_missing_is_one_line_error(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ReplayError) as info:
        B.make_engine("ray", workers=1)
    assert str(info.value) == (
        "Ray is not installed; install it with: pip install 'riskreplay[ray]'"
    )


def test_unreachable_ray_address_fails_at_once():
    pytest.importorskip("ray", reason="ray is not installed (pip install 'riskreplay[ray]')")
    with pytest.raises(ReplayError, match=r"cannot reach the Ray cluster at ray://127.0.0.1:1 "):
        B.make_engine("ray", address="ray://127.0.0.1:1")


def test_engine_argument_errors():
    with pytest.raises(ReplayError, match="--ray-address needs --engine ray"):
        B.make_engine("local", address="auto")
    with pytest.raises(ReplayError, match="unknown engine 'spark'"):
        B.make_engine("spark")


# ---------------------------------------------------------------------- whole runs
@pytest.mark.slow
def test_local_run_isolates_the_bad_scenes(local_run):
    out, report, _ = local_run
    assert report.engine == "local" and report.workers == 2
    assert [s.name for s in report.scenes] == [f"scene_{i}" for i in range(N_GOOD)]
    assert report.replayed == N_GOOD and report.skipped == 0
    failures = B.read_failures(out / "failures.csv")
    assert [(f.scene, f.stage, f.error_type) for f in failures] == [
        ("broken", "read", "SceneFormatError"),
        ("sub/no_ego", "replay", "ReplayError"),
    ]
    scenes = pl.read_csv(out / "scenes.csv")
    status = dict(zip(scenes["scene"].to_list(), scenes["status"].to_list(), strict=True))
    assert status == {"broken": "failed", "sub/no_ego": "failed"} | {
        f"scene_{i}": "replayed" for i in range(N_GOOD)
    }


@pytest.mark.slow
def test_local_run_statistics_cover_every_good_scene(local_run):
    out, _, _ = local_run
    tables = sorted((out / "tables").glob("*.parquet"))
    assert [t.stem for t in tables] == [f"scene_{i}" for i in range(N_GOOD)]
    rows = sum(pl.read_parquet(t).height for t in tables)
    frames = sum(pl.read_parquet(t).height for t in (out / "frames").glob("*.parquet"))
    summary = json.loads((out / "stats" / "summary.json").read_text())
    assert summary["baseline"]["agent_frames"] == rows
    assert summary["situations"]["total"] == frames == N_GOOD * 10
    per_scene = pl.read_csv(out / "stats" / "per_scene.csv")
    assert per_scene["scene"].to_list() == [f"scene_{i}" for i in range(N_GOOD)]
    assert (out / "stats" / "roc.parquet").is_file()
    # Streamed one scene at a time, the statistics equal the whole-table computation's
    # (the oracle) in every exact figure: the baseline, the funnel and the per-scene table.
    from replay.analysis.stats import DEFAULT_ERRORS_MODEL, concat_agents
    from replay.analysis.stats.compute import compute_stats

    cascade = CascadeConfig.default()
    oracle = compute_stats(
        concat_agents([pl.read_parquet(t) for t in tables]),
        pl.concat([pl.read_parquet(t) for t in sorted((out / "frames").glob("*.parquet"))],
                  how="vertical_relaxed"),
        models=None, errors_model=DEFAULT_ERRORS_MODEL, stage_names=cascade.stage_names,
        tier_names=[t.name for t in cascade.tiers],
        baseline_threshold=cascade.baseline_threshold, inputs=[],
    )  # fmt: skip
    assert summary["baseline"]["agent_frames"] == oracle.summary["baseline"]["agent_frames"]
    assert summary["situations"] == _drop_times(
        json.loads(json.dumps(oracle.summary["situations"]))
    )
    assert per_scene.height == oracle.per_scene.height


@pytest.mark.slow
def test_resumed_run_recomputes_nothing_but_the_failures(local_run, dataset, settings):
    out, _, summary = local_run
    before = {p: p.stat().st_mtime_ns for p in (out / "tables").glob("*.parquet")}
    again = B.run_batch([dataset], out, settings, engine=_InlineEngine(), progress=False)
    assert again.replayed == 0 and again.skipped == N_GOOD
    # Only the two failed scenes were tried again, and they fail again.
    assert [(f.scene, f.stage) for f in again.failures] == [
        ("broken", "read"),
        ("sub/no_ego", "replay"),
    ]
    assert {p: p.stat().st_mtime_ns for p in (out / "tables").glob("*.parquet")} == before
    assert _summary_without_times(out) == summary


@pytest.mark.slow
def test_a_changed_input_is_replayed_again(dataset, settings, tmp_path):
    inputs = tmp_path / "in"
    inputs.mkdir()
    for i in range(2):
        (inputs / f"s{i}.mcap").write_bytes((dataset / f"scene_{i}.mcap").read_bytes())
    out = tmp_path / "out"
    first = B.run_batch([inputs], out, settings, engine=_InlineEngine(), progress=False)
    assert first.replayed == 2
    x_before = pl.read_parquet(out / "tables" / "s1.parquet")["x_m"]
    s0_mtime = (out / "tables" / "s0.parquet").stat().st_mtime_ns
    (inputs / "s1.mcap").write_bytes((dataset / "scene_5.mcap").read_bytes())
    engine = _InlineEngine()
    second = B.run_batch([inputs], out, settings, engine=engine, progress=False)
    assert (second.replayed, second.skipped) == (1, 1)
    assert [t.name for t in engine.ran] == ["s1"]
    assert not pl.read_parquet(out / "tables" / "s1.parquet")["x_m"].equals(x_before)
    assert (out / "tables" / "s0.parquet").stat().st_mtime_ns == s0_mtime
    # Nothing left to do: no engine is needed at all.
    third = B.run_batch([inputs], out, settings, engine=_NoEngineAllowed(), progress=False)
    assert (third.replayed, third.skipped) == (0, 2)


class _NoEngineAllowed:
    name = "none"
    workers = 0

    def submit(self, fn, task):
        raise AssertionError("a complete run must not submit anything")


class _InlineEngine:
    """An in-process engine (no pool) that records what it ran."""

    name = "inline"
    workers = 1

    def __init__(self):
        self._queue = []
        self.ran = []

    @property
    def pending(self):
        return len(self._queue)

    def submit(self, fn, task):
        self._queue.append((fn, task))

    def results(self):
        fn, task = self._queue.pop(0)
        self.ran.append(task)
        return [(task, fn(task))]

    def close(self, *, cancel=False):
        self._queue.clear()


@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'riskreplay[ray]')")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_gives_the_same_statistics_as_local(
    ray_instance, local_run, dataset, settings, tmp_path
):
    out_local, _, summary_local = local_run
    out = tmp_path / "out-ray"
    report = B.run_batch([dataset], out, settings, engine="ray", progress=False)
    assert report.engine == "ray" and report.workers == 2
    assert report.replayed == N_GOOD
    assert [(f.scene, f.stage) for f in report.failures] == [
        ("broken", "read"),
        ("sub/no_ego", "replay"),
    ]
    assert _summary_without_times(out) == summary_local
    for table in (out_local / "tables").glob("*.parquet"):
        assert pl.read_parquet(out / "tables" / table.name).equals(pl.read_parquet(table))
    assert ray_instance.is_initialized()  # an instance we did not start is left running
    resumed = B.run_batch([dataset], out, settings, engine="ray", progress=False)
    assert (resumed.replayed, resumed.skipped) == (0, N_GOOD)


@pytest.mark.parametrize(
    ("kind", "name", "scenario", "expected"),
    [
        # an AV2 Sensor log folder is its own scenario: no LOG/LOG, also under a folder
        ("av2-sensor", "av2-sensor/LOG1", "LOG1", "av2-sensor/LOG1"),
        ("av2-sensor", "LOG1", "LOG1", "LOG1"),
        # a Waymo shard holds many scenarios: one sub-folder per shard
        ("waymo", "womd/shard-0", "abc", "womd/shard-0/abc"),
    ],
)
def test_scene_names_of_multi_scene_inputs(kind, name, scenario, expected):
    task = B.ConvertTask(
        input="x", name=name, kind=kind, paths="map", map_osm=None, scenes_dir="s",
        marker="m", digest="d",
    )  # fmt: skip
    scene = SimpleNamespace(metadata={"scenario_id": scenario})
    assert _scene_name(task, scene, f"{name}/record-0", set()) == expected
