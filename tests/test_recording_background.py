"""Outputs written by the output process (outputs.process): the same files as in process,
errors that say what happened, nothing left behind, and the one place that starts the process (a sink that begins)."""

from __future__ import annotations

import dataclasses
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from test_recordings import make_results, read_rrd

from outputs import process as background
from recordings import SceneRecorder, recorder
from recordings.errors import RecordingError
from replay.cli.app import main
from replay.core import tables
from replay.core.tables import TableSink


@pytest.fixture(autouse=True)
def output_process_on(monkeypatch):
    """Test the output process whatever the machine's load (the default, ``auto``, skips
    it when no CPU is idle, e.g. under ``pytest -n 2``)."""
    monkeypatch.setenv(background.MODE_VARIABLE, "on")


def fill(sink, results_from=make_results):
    info, results = results_from()
    sink.begin(info)
    for r in results:
        sink.add(r)
    return sink


def leftovers(folder: pathlib.Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name != "fakes")


def fake_writer(monkeypatch, tmp_path: pathlib.Path, module, body: str) -> None:
    """Make ``module`` (recordings.recorder or replay.core.tables) write with a ``write_temp``
    whose body is ``body``: a module in a folder on sys.path, which the output process
    (a new interpreter, started with the parent's sys.path) imports."""
    folder = tmp_path / "fakes"
    folder.mkdir(exist_ok=True)
    name = f"fake_{module.__name__.replace('.', '_')}"
    (folder / f"{name}.py").write_text(
        "import os\nfrom recordings.errors import RecordingError\n"
        "from replay.errors import ReplayError\n\n"
        f"def write_temp(*args):\n    tmp = args[1]\n    {body}\n"
    )
    monkeypatch.syspath_prepend(str(folder))
    monkeypatch.setattr(module, "WRITER" if module is recorder else "TABLE_WRITER", name)


@pytest.fixture(autouse=True)
def no_process_left():
    yield
    assert background._shared is None, "an output process was left running"


def test_background_recording_is_the_recording_written_in_process(tmp_path):
    inline, behind = tmp_path / "inline.rrd", tmp_path / "background.rrd"
    fill(SceneRecorder(inline)).close()
    rec = fill(SceneRecorder(behind, background=True))
    assert rec._process is not None and rec._process.alive()
    rec.close()
    a, b = read_rrd(inline), read_rrd(behind)
    a = {k: v for k, v in a.items() if not k.startswith("/__properties")}
    b = {k: v for k, v in b.items() if not k.startswith("/__properties")}
    assert a.keys() == b.keys() and len(a) > 20
    for path in a:  # repr: NaN risks compare equal as text
        assert repr(a[path].static) == repr(b[path].static), path
        assert sorted(map(repr, a[path].rows)) == sorted(map(repr, b[path].rows)), path
    assert leftovers(tmp_path) == ["background.rrd", "inline.rrd"]


def test_packed_frames_unpack_to_the_same_frames():
    """The form the frames travel in to the output process gives every field back with
    its values, dtype and shape (lists and dicts included)."""
    rec = fill(SceneRecorder(pathlib.Path("unused.rrd"), paths=True))
    frames = rec._frames
    rec.abort()
    assert any(f.survivor_paths.size for f in frames) and any(f.ego_paths for f in frames)
    back = recorder.PackedFrames.pack(frames).unpack()
    assert len(back) == len(frames)

    def same(a, b) -> bool:
        if isinstance(a, dict):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        if isinstance(a, list):
            return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
        if isinstance(a, np.ndarray):
            return a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        if isinstance(a, float) and a != a:  # NaN (no planner's time): NaN again
            return isinstance(b, float) and b != b
        return type(a) is type(b) and a == b

    for f, g in zip(frames, back, strict=True):
        for field in dataclasses.fields(f):
            assert same(getattr(f, field.name), getattr(g, field.name)), field.name
    assert recorder.PackedFrames.pack([]).unpack() == []


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_background_table_is_the_table_written_in_process(tmp_path, suffix):
    inline, behind = tmp_path / f"inline{suffix}", tmp_path / f"background{suffix}"
    fill(TableSink(inline)).close()
    fill(TableSink(behind, background=True)).close()
    read = pl.read_parquet if suffix == ".parquet" else pl.read_csv
    a, b = read(inline), read(behind)
    assert a.height > 0 and a.equals(b, null_equal=True)


def test_a_failed_write_raises_its_error_and_leaves_nothing(tmp_path, monkeypatch):
    fake_writer(monkeypatch, tmp_path, recorder, "tmp.write_bytes(b'partial'); "
                "raise RecordingError('could not write a.rrd: No space left on device')")  # fmt: skip
    rec = fill(SceneRecorder(tmp_path / "a.rrd", background=True))
    with pytest.raises(RecordingError, match="No space left on device") as caught:
        rec.close()
    assert not getattr(caught.value, "__notes__", None)  # a user error: no traceback
    assert leftovers(tmp_path) == []


def test_an_abort_after_start_close_waits_for_the_file_then_removes_it(tmp_path, monkeypatch):
    """start_close() sends the recording and returns while the process writes; an abort
    then (another sink failed) waits for the process's file before removing it, so that
    nothing is left behind, and the process can take the next job."""
    fake_writer(monkeypatch, tmp_path, recorder,
                "import time; time.sleep(0.5); tmp.write_bytes(b'written late')")  # fmt: skip
    rec = fill(SceneRecorder(tmp_path / "f.rrd", background=True))
    started = time.perf_counter()
    rec.start_close()
    assert time.perf_counter() - started < 0.4  # did not wait for the write
    rec.abort()
    time.sleep(0.8)  # (a write the abort had not waited for would land by now)
    assert leftovers(tmp_path) == []
    again = fill(SceneRecorder(tmp_path / "g.rrd", background=True))
    again.start_close()
    again.close()
    assert leftovers(tmp_path) == ["g.rrd"]


def test_releasing_a_busy_process_ends_it_before_returning():
    """A job abandoned (an error elsewhere, Ctrl-C) leaves the process busy: its release
    waits for it or ends it, so that it cannot write after its user cleaned up; an idle
    one is only told to leave."""
    process = background.acquire()
    assert process is not None
    process.submit("time:sleep", 0.5)  # (its reply is never read)
    background.release(process)
    assert not process.alive()


def test_a_bug_in_the_writer_keeps_its_type_and_traceback(tmp_path, monkeypatch):
    fake_writer(monkeypatch, tmp_path, tables, "raise ValueError('a bug in the writer')")
    table = fill(TableSink(tmp_path / "b.parquet", background=True))
    with pytest.raises(ValueError, match="a bug in the writer") as caught:
        table.close()
    assert any("in the output process" in note for note in caught.value.__notes__)
    assert leftovers(tmp_path) == []


def test_an_output_process_that_dies_is_reported(tmp_path, monkeypatch):
    fake_writer(monkeypatch, tmp_path, recorder, "tmp.write_bytes(b'partial'); os._exit(9)")
    rec = fill(SceneRecorder(tmp_path / "c.rrd", background=True))
    with pytest.raises(background.OutputProcessError, match=r"exit code 9.*OUTPUT_PROCESS=off"):
        rec.close()
    assert leftovers(tmp_path) == []  # the parent removes the temporary file it named


def test_outputs_share_one_process_which_ends_with_its_last_user(tmp_path):
    rec = fill(SceneRecorder(tmp_path / "d.rrd", background=True))
    table = fill(TableSink(tmp_path / "d.parquet", background=True))
    process = rec._process
    assert process is table._process and process is not None and process.users == 2
    rec.abort()
    assert process.alive() and process.users == 1
    table.close()
    assert leftovers(tmp_path) == ["d.parquet"]
    deadline = time.monotonic() + 10.0  # (told to leave; its exit is not waited for)
    while process.alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not process.alive()


def test_the_mode_variable_and_the_load_decide(monkeypatch, tmp_path):
    monkeypatch.setenv(background.MODE_VARIABLE, "auto")
    monkeypatch.setattr(background.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr(background.os, "getloadavg", lambda: (0.4, 0.0, 0.0))
    assert background.available()  # two CPUs, one idle
    monkeypatch.setattr(background.os, "getloadavg", lambda: (1.6, 0.0, 0.0))
    assert not background.available()  # a neighbour keeps a CPU busy
    monkeypatch.setattr(background.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    monkeypatch.setattr(background.os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    assert not background.available()  # one CPU
    monkeypatch.setenv(background.MODE_VARIABLE, "on")
    assert background.available()
    monkeypatch.setenv(background.MODE_VARIABLE, "off")
    assert not background.available() and background.acquire(("json",)) is None
    rec = fill(SceneRecorder(tmp_path / "e.rrd", background=True))
    assert rec._process is None
    rec.close()
    assert leftovers(tmp_path) == ["e.rrd"]


def test_only_the_outputs_start_the_output_process(tmp_path, monkeypatch):
    """One place starts it: a sink that begins (the recording here); a command that
    writes no recording or table starts none, whatever its command line says."""
    started: list[tuple[str, ...]] = []
    real = background.OutputProcess

    class Counting(real):  # type: ignore[misc,valid-type]
        def __init__(self, preload) -> None:
            started.append(tuple(preload))
            super().__init__(preload)

    monkeypatch.setattr(background, "OutputProcess", Counting)
    scene = tmp_path / "s.mcap"
    runner = CliRunner()
    made = runner.invoke(main, ["convert", "synthetic", "-o", str(scene), "--agents", "4",
                                "--duration", "1"])  # fmt: skip
    assert made.exit_code == 0, made.output
    assert started == []
    keep = tmp_path / "keep.jsonl"  # an output written in this process
    ran = runner.invoke(main, ["run", str(scene), "--no-rrd", "--keep-lists", str(keep),
                               "--no-progress"])  # fmt: skip
    assert ran.exit_code == 0, ran.output
    assert started == []
    ran = runner.invoke(main, ["run", str(scene), "-o", str(tmp_path / "s.rrd"), "--no-progress"])
    assert ran.exit_code == 0, ran.output
    assert started == [(recorder.WRITER,)]
    assert background._shared is None


def test_run_uses_the_output_process_and_bad_input_stops_it(tmp_path):
    scene = tmp_path / "s.mcap"
    runner = CliRunner()
    made = runner.invoke(main, ["convert", "synthetic", "-o", str(scene), "--agents", "6",
                                "--duration", "1"])  # fmt: skip
    assert made.exit_code == 0, made.output
    ran = runner.invoke(main, ["run", str(scene), "-o", str(tmp_path / "s.rrd"),
                               "--table", str(tmp_path / "s.csv"), "--no-progress"])  # fmt: skip
    assert ran.exit_code == 0, ran.output
    assert (tmp_path / "s.rrd").stat().st_size > 0 and (tmp_path / "s.csv").stat().st_size > 0
    assert background._shared is None
    # An unknown ego fails before anything is written: the output process is stopped.
    bad = runner.invoke(main, ["run", str(scene), "-o", str(tmp_path / "t.rrd"), "--ego", "99"])
    assert bad.exit_code == 1 and "Error:" in bad.output
    assert background._shared is None and not (tmp_path / "t.rrd").exists()


def test_demo_outputs_appear_together_or_not_at_all(tmp_path, monkeypatch):
    """The output process (the recording) and the replay's process (the table) write
    temporary files only; the command's OutputGuard renames them together, so a table
    that fails takes the recording with it."""

    fake_writer(monkeypatch, tmp_path, tables,
                "raise ReplayError('could not write the table: No space left on device')")  # fmt: skip
    out = tmp_path / "demo"
    ran = CliRunner().invoke(main, ["demo", "-o", str(out), "--agents", "5", "--no-progress"])
    assert ran.exit_code == 1 and "No space left on device" in ran.output
    assert not out.exists() and leftovers(tmp_path) == []


def test_the_replay_process_imports_no_rerun_with_the_output_process(tmp_path):
    """With the output process, `replay demo` imports rerun only there (and polars for the
    table itself: it is idle by then); without it, both itself."""
    for mode, imported in (("on", ["False", "True"]), ("off", ["True", "True"])):
        code = (
            "import sys; from replay.cli.app import main; "
            f"main.main(['demo', '-o', {str(tmp_path / mode)!r}, '--agents', '5', "
            "'--no-progress'], standalone_mode=False); "
            "print('rerun' in sys.modules, 'polars' in sys.modules)"
        )
        env = {**os.environ, background.MODE_VARIABLE: mode}
        run = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
        )
        assert run.returncode == 0, run.stderr
        assert run.stdout.split()[-2:] == imported, mode
        assert (tmp_path / mode / "intersection.rrd").stat().st_size > 0
        assert (tmp_path / mode / "intersection.parquet").stat().st_size > 0


def test_the_output_process_runs_neither_the_main_script_nor_the_cli():
    """A new interpreter that imports only what its jobs need: multiprocessing's spawn
    ran the parent's main script again (for ``replay``, click and the CLI; for pytest,
    pytest) and started a resource tracker before it."""
    process = background.acquire()
    assert process is not None
    try:
        loaded = process.run(
            "builtins:eval",
            "sorted(m for m in ('pytest', 'click', 'replay.cli.app', 'multiprocessing.resource_tracker')"
            " if m in __import__('sys').modules)",
        )
    finally:
        background.release(process)
    assert loaded == []
