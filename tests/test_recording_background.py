"""The recording written in a second process (recordings.background): the same file as in
process, errors that say what happened, nothing left behind, and the CLI's early start."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest
from click.testing import CliRunner
from test_recordings import make_results, read_rrd

from recordings import SceneRecorder, background, writer
from recordings.errors import RecordingError
from replay.cli import _will_record, main

needs_background = pytest.mark.skipif(
    not background.can_write_in_background(),
    reason="no second CPU or no fork here: recordings are written in process",
)


def record(out: pathlib.Path, *, background: bool) -> SceneRecorder:
    info, results = make_results()
    rec = SceneRecorder(out, background=background)
    rec.begin(info)
    for r in results:
        rec.add(r)
    return rec


def leftovers(folder: pathlib.Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


@needs_background
def test_background_writes_what_the_process_itself_writes(tmp_path):
    inline, behind = tmp_path / "inline.rrd", tmp_path / "background.rrd"
    record(inline, background=False).close()
    rec = record(behind, background=True)
    assert rec._writer is not None  # the process was started by begin()
    rec.close()
    a, b = read_rrd(inline), read_rrd(behind)
    a = {k: v for k, v in a.items() if not k.startswith("/__properties")}
    b = {k: v for k, v in b.items() if not k.startswith("/__properties")}
    assert a.keys() == b.keys() and len(a) > 20
    for path in a:
        # repr: NaN risks compare equal as text
        assert repr(a[path].static) == repr(b[path].static), path
        assert sorted(map(repr, a[path].rows)) == sorted(map(repr, b[path].rows)), path
    assert leftovers(tmp_path) == ["background.rrd", "inline.rrd"]


@needs_background
def test_a_failed_write_raises_its_error_and_leaves_nothing(tmp_path, monkeypatch):
    def full_disk(output, tmp, info, frames, options):
        tmp.write_bytes(b"partial")
        raise RecordingError(f"could not write {output}: No space left on device")

    # The process is forked at begin(), so it inherits the patched writer.
    monkeypatch.setattr(writer, "write_file", full_disk)
    rec = record(tmp_path / "a.rrd", background=True)
    with pytest.raises(RecordingError, match="No space left on device"):
        rec.close()
    assert leftovers(tmp_path) == []


@needs_background
def test_a_bug_in_the_writer_keeps_its_type_and_traceback(tmp_path, monkeypatch):
    def bug(output, tmp, info, frames, options):
        raise ValueError("a bug in the writer")

    monkeypatch.setattr(writer, "write_file", bug)
    rec = record(tmp_path / "b.rrd", background=True)
    with pytest.raises(ValueError, match="a bug in the writer") as caught:
        rec.close()
    assert any("in the recording process" in note for note in caught.value.__notes__)
    assert leftovers(tmp_path) == []


@needs_background
def test_a_writer_process_that_dies_is_reported(tmp_path, monkeypatch):
    def killed(output, tmp, info, frames, options):
        tmp.write_bytes(b"partial")
        os._exit(9)

    monkeypatch.setattr(writer, "write_file", killed)
    rec = record(tmp_path / "c.rrd", background=True)
    with pytest.raises(RecordingError, match=r"exit code 9.*RISKREPLAY_RECORD_INLINE"):
        rec.close()
    assert leftovers(tmp_path) == []  # the parent removes the temporary file it named


@needs_background
def test_abort_stops_the_process(tmp_path):
    rec = record(tmp_path / "d.rrd", background=True)
    process = rec._writer._process  # type: ignore[union-attr]
    rec.abort()
    assert not process.is_alive() and leftovers(tmp_path) == []


def test_inline_variable_switches_the_background_off(monkeypatch, tmp_path):
    monkeypatch.setenv(background.INLINE_VARIABLE, "1")
    assert not background.can_write_in_background()
    rec = record(tmp_path / "e.rrd", background=True)
    assert rec._writer is None
    rec.close()
    assert leftovers(tmp_path) == ["e.rrd"]


@pytest.mark.parametrize(
    ("args", "records"),
    [
        (["run", "s.mcap"], True),
        (["demo"], True),
        (["run", "s.mcap", "--no-rrd"], False),
        (["run", "s.mcap", "--ego", "all"], False),
        (["run", "s.mcap", "--ego=all"], False),
        (["run", "s.mcap", "--ego", "7"], True),
        (["run", "--help"], False),
        (["stats", "s.mcap"], False),
    ],
)
def test_which_commands_start_the_writer_early(args, records):
    assert _will_record(args) is records


@needs_background
def test_run_adopts_the_early_writer_and_bad_input_stops_it(tmp_path):
    scene = tmp_path / "s.mcap"
    runner = CliRunner()
    made = runner.invoke(main, ["convert", "synthetic", "-o", str(scene), "--agents", "6",
                               "--duration", "1"])  # fmt: skip
    assert made.exit_code == 0, made.output
    ran = runner.invoke(main, ["run", str(scene), "-o", str(tmp_path / "s.rrd"), "--no-progress"])
    assert ran.exit_code == 0, ran.output
    assert (tmp_path / "s.rrd").stat().st_size > 0
    assert background._early is None
    # An unknown ego fails before recording: the early process is stopped, not leaked.
    bad = runner.invoke(main, ["run", str(scene), "-o", str(tmp_path / "t.rrd"), "--ego", "999"])
    assert bad.exit_code == 1 and "Error:" in bad.output
    assert background._early is None and not (tmp_path / "t.rrd").exists()


def test_the_replay_process_itself_does_not_import_rerun(tmp_path):
    """With the writer in the background, `replay run` never imports rerun itself (the
    second process does); without a second CPU it does, in process."""
    scene = tmp_path / "s.mcap"
    code = (
        "import sys; from replay.cli import main; "
        f"main.main(['convert', 'synthetic', '-o', {str(scene)!r}, '--agents', '5', "
        "'--duration', '1'], standalone_mode=False); "
        f"main.main(['run', {str(scene)!r}, '--no-progress'], standalone_mode=False); "
        "print('rerun' in sys.modules)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split()[-1] == str(not background.can_write_in_background())
    assert scene.with_suffix(".rrd").stat().st_size > 0
