"""Reliability: every command under bad input, full disks, concurrent writers and kills.

Each generated case of ``reliability_cases.py`` runs the real CLI in a subprocess and must
end with a non-zero exit, exactly one ``Error:`` line naming the file, no traceback, the
inputs byte-identical, nothing left in the case's folder, and no surviving process. The
other tests cover what needs more set-up: the output guard itself, a second writer, stale
temporary files, a stalled save, a full disk (a 1 MiB tmpfs; skipped where it cannot be
mounted), a kill mid-write, batch workers after their driver dies, a broken pipe, and
``inspect`` rejecting what ``run`` rejects.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import signal
import subprocess
import time

import pytest
from click.testing import CliRunner
from reliability_cases import (
    REPLAY,
    cases,
    run_case,
    run_case_in_process,
    run_cli,
    scene,
    session_members,
)

from converters.scene import schema as sf
from converters.scene.reader import read_scene
from converters.scene.writer import SceneWriter, encode_frame
from outputs import atomic
from outputs.transaction import OutputError, OutputGuard, run_with_stall_timeout, same_file
from replay.cli.app import main


@pytest.mark.parametrize("case", cases(), ids=lambda c: c.name)
def test_bad_input_gives_one_clean_error(case, tmp_path):
    out = run_case_in_process(case, tmp_path / "case")
    assert not out.traceback, out.stderr
    assert out.returncode != 0, f"exit 0 on bad input: {out.stderr[-500:]}"
    assert len(out.error_lines) == 1, out.stderr
    assert not out.inputs_changed, f"input changed: {out.inputs_changed}"
    assert not out.leftovers, f"left behind: {out.leftovers}"
    if case.names_file:
        line = out.error_lines[0]
        assert str(tmp_path / "case") in line or "case/" in line, line


@pytest.mark.slow
@pytest.mark.parametrize(
    "name", ["corrupted-run-0", "same-path-run-output-is-scene", "nonfinite-av2-position_x",
             "out-of-range-convert-synthetic-period-1e-9"],
)  # fmt: skip
def test_bad_input_in_a_real_process_hangs_not_and_leaves_no_process(name, tmp_path):
    """A few cases as a user runs them: a fresh process, in its own session, with a time
    limit (benchmarks/reliability_census.py runs all of them this way)."""
    case = next(c for c in cases() if c.name == name)
    out = run_case(case, tmp_path / "case", time_limit_s=120)
    assert out.clean_error, (out.returncode, out.stderr[-800:], out.leftovers)


# ---------------------------------------------------------------------- the guard itself
def test_same_file_sees_symlinks_hardlinks_and_dotdot(tmp_path):
    a = tmp_path / "a.mcap"
    a.write_bytes(b"x")
    (tmp_path / "sym").symlink_to(a)
    os.link(a, tmp_path / "hard")
    (tmp_path / "sub").mkdir()
    assert same_file(a, tmp_path / "sym")
    assert same_file(a, tmp_path / "hard")
    assert same_file(a, tmp_path / "sub" / ".." / "a.mcap")
    assert same_file(tmp_path / "new", tmp_path / "sub" / ".." / "new")  # neither exists
    assert not same_file(a, tmp_path / "b.mcap")


def test_guard_commits_all_outputs_together_or_none(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    b.write_text("old")
    with pytest.raises(RuntimeError), OutputGuard(files=(a, b)):
        atomic.write_text(a, "new a")
        atomic.write_text(b, "new b")
        assert not a.exists() and b.read_text() == "old"  # nothing moved yet
        raise RuntimeError("late failure")
    assert not a.exists() and b.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]  # no temp, no lock
    with OutputGuard(files=(a, b)):
        atomic.write_text(a, "new a")
        atomic.write_text(b, "new b")
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]


def test_guard_commit_now_is_rolled_back_on_failure(tmp_path):
    a = tmp_path / "a.txt"
    a.write_text("old")
    with pytest.raises(KeyboardInterrupt), OutputGuard(files=(a,)) as guard:
        atomic.write_text(a, "new")
        guard.commit_now(a)
        assert a.read_text() == "new"
        raise KeyboardInterrupt
    assert a.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_guard_removes_the_folders_it_created_on_failure(tmp_path):
    out = tmp_path / "x" / "y"
    with pytest.raises(ValueError), OutputGuard(folders=(out,)):
        atomic.write_text(out / "f.txt", "data")
        raise ValueError
    assert list(tmp_path.iterdir()) == []


def test_guard_refuses_a_second_writer_and_names_the_holder(tmp_path):
    target = tmp_path / "o.rrd"
    with (
        OutputGuard(files=(target,)),
        pytest.raises(OutputError, match=f"process {os.getpid()}"),
        OutputGuard(files=(target,)),
    ):
        pass
    with OutputGuard(files=(target,)):  # released: free again
        pass


def test_stalled_save_times_out_with_a_clear_error(tmp_path, monkeypatch):
    from outputs import transaction as guard

    watch = tmp_path / ".o.rrd.0123456789ab.tmp"
    watch.write_bytes(b"")
    monkeypatch.setattr(guard, "free_bytes", lambda folder: 4096)  # a full disk
    start = time.monotonic()
    with pytest.raises(OutputError, match=r"could not write .*o\.rrd: the save made no progress"):
        run_with_stall_timeout(
            lambda: time.sleep(30), watch=watch, target=tmp_path / "o.rrd", stall_s=0.5
        )
    assert time.monotonic() - start < 5


def test_a_stall_with_room_on_the_disk_is_not_called_a_full_disk(tmp_path, monkeypatch):
    """Issue 31: 20,000 agents kept rerun encoding for minutes before it wrote a byte,
    and the save was reported as "disk full or stalled" with 74 GiB free."""
    from outputs import transaction as guard

    watch = tmp_path / ".o.rrd.0123456789ab.tmp"
    watch.write_bytes(b"")
    monkeypatch.setattr(guard, "free_bytes", lambda folder: 80 * 2**30)
    with pytest.raises(OutputError) as err:
        run_with_stall_timeout(
            lambda: time.sleep(30), watch=watch, target=tmp_path / "o.rrd", stall_s=0.5
        )
    text = str(err.value)
    assert "the writer made no progress for 0.5 s although 80.0 GiB are free" in text
    assert "disk full" not in text and "RISKREPLAY_STALL_TIMEOUT_S" in text


def test_stall_watch_passes_errors_of_the_work_through(tmp_path):
    def fail() -> None:
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"):
        run_with_stall_timeout(fail, watch=tmp_path / "w", target=tmp_path / "o", stall_s=5)


# ---------------------------------------------------------------------- CLI-level behaviour
def test_concurrent_run_into_the_same_outputs_is_refused(tmp_path):
    s = scene(tmp_path)
    with OutputGuard(files=(tmp_path / "out.rrd",)):  # another writer holds the output
        code, _, err, _, _ = run_cli(["run", str(s), "-o", "out.rrd", "--no-progress"], tmp_path)
    assert code == 1
    assert err.strip().splitlines()[-1].startswith("Error: ")
    assert "another replay command" in err and "out.rrd" in err
    assert not (tmp_path / "out.rrd").exists()


def test_stale_temporary_files_are_named_and_removed_by_the_next_run(tmp_path):
    s = scene(tmp_path)
    stale = [tmp_path / ".out.rrd.0123456789ab.tmp", tmp_path / ".t.parquet.abcdefabcdef.tmp"]
    for p in stale:
        p.write_bytes(b"\0" * 1000)
    keep = tmp_path / ".other.0123456789ab.tmp"  # not ours to remove: another target
    keep.write_bytes(b"x")
    result = CliRunner().invoke(
        main, ["run", str(s), "-o", str(tmp_path / "out.rrd"), "--table",
               str(tmp_path / "t.parquet"), "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert not any(p.exists() for p in stale)
    assert keep.exists()
    assert result.output.count("Removed a stale temporary file") == 2
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == [".other.0123456789ab.tmp", "out.rrd", "s.mcap", "t.parquet"]


def test_broken_pipe_on_stdout_ends_quietly_with_status_0():
    check = subprocess.run(
        ["/bin/bash", "-c", f"{' '.join(REPLAY)} models | head -c 10 >/dev/null;"
         " echo ${PIPESTATUS[0]}"], capture_output=True, text=True,
    )  # fmt: skip
    assert check.stdout.strip() == "0", check.stderr
    assert check.stderr == ""


def _tamper_scene(path: pathlib.Path, tamper) -> pathlib.Path:
    """A copy of the small scene written frame by frame with ``tamper(agents, paths, k)``
    applied to each frame's messages (returns False to leave out the /paths message)."""
    good = read_scene(scene(path.parent, ".good.mcap"))
    (path.parent / ".good.mcap").unlink()
    w = SceneWriter(path, good.map, frame_period_s=good.frame_period_s,
                    metadata={"converter": "test"})  # fmt: skip
    for k, frame in enumerate(good.frames):
        agents, paths = encode_frame(frame, k)
        keep_paths = tamper(agents, paths, k) is not False
        t = int(1e9 * frame.t)
        w._write(sf.TOPIC_AGENTS, agents, t)
        if keep_paths:
            w._write(sf.TOPIC_PATHS, paths, t)
        w._n_frames += 1
    w.close()
    return path


def _nan_time(agents, paths, k):
    if k == 3:
        agents.t_s = float("nan")


def _negative_speed(agents, paths, k):
    agents.speed_mmps[1] = -5000


def _duplicate_ids(agents, paths, k):
    agents.ids[2] = agents.ids[1]


def _beyond_2_53(agents, paths, k):
    agents.x_mm[1] = 2**60


def _unpaired(agents, paths, k):
    return k != 4


@pytest.mark.parametrize(
    "tamper", [_nan_time, _negative_speed, _duplicate_ids, _beyond_2_53, _unpaired],
    ids=["nan-time", "negative-speed", "duplicate-ids", "beyond-2^53-mm", "unpaired-frame"],
)  # fmt: skip
def test_inspect_rejects_what_run_rejects(tamper, tmp_path):
    bad = _tamper_scene(tmp_path / "bad.mcap", tamper)
    runner = CliRunner()
    ran = runner.invoke(
        main, ["run", str(bad), "--no-rrd", "--table", str(tmp_path / "t.parquet"), "--no-progress"]
    )
    inspected = runner.invoke(main, ["inspect", str(bad)])
    assert ran.exit_code == 1, ran.output
    assert inspected.exit_code == 1, inspected.output
    assert inspected.output.startswith(f"Error: {bad}")
    assert ran.output.strip().splitlines()[-1] == inspected.output.strip()


# ---------------------------------------------------------------------- bad values: --skip-bad
def test_nonfinite_states_are_dropped_counted_and_recorded_with_skip_bad(tmp_path):
    from test_convert_interaction import osm_text, vehicle_csv

    csv, osm = tmp_path / "t.csv", tmp_path / "m.osm"
    lines = vehicle_csv().splitlines()
    for row in (2, 3):
        cells = lines[row].split(",")
        cells[4] = "inf" if row == 2 else "nan"
        lines[row] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    osm.write_text(osm_text())
    out = tmp_path / "o.mcap"
    runner = CliRunner()
    stop = runner.invoke(main, ["convert", "interaction", str(csv), "--map", str(osm),
                                "-o", str(out)])  # fmt: skip
    assert stop.exit_code == 1
    assert "track 1 at t=" in stop.output and "position is not finite" in stop.output
    assert str(csv) in stop.output and not out.exists()
    skip = runner.invoke(main, ["convert", "interaction", str(csv), "--map", str(osm),
                                "-o", str(out), "--skip-bad"])  # fmt: skip
    assert skip.exit_code == 0, skip.output
    assert "dropped 2 state(s) with non-finite or out-of-range values" in skip.output
    assert read_scene(out).metadata["bad_states_dropped"] == "2"


# ---------------------------------------------------------------------- full disk (tmpfs)
@pytest.fixture
def tiny_disk(tmp_path):
    """A 1 MiB tmpfs, filled to the last few KiB; skipped where mounting is not allowed."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root and mount(8)")
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        with contextlib.suppress(OSError), open(mount / ".filler", "wb") as f:
            f.write(b"\0" * (1024 * 1024 - 48 * 1024))
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def test_unwritable_output_folder_fails_before_the_replay(tmp_path):
    """A read-only file system (root ignores permission bits, not ``ro`` mounts)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a read-only tmpfs needs root and mount(8)")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)],
                          capture_output=True)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        s = scene(tmp_path)
        result = CliRunner().invoke(
            main, ["run", str(s), "--table", str(ro / "t.parquet"), "-o", str(tmp_path / "o.rrd"),
                   "--no-progress"],
        )  # fmt: skip
    finally:
        subprocess.run(["umount", "-l", str(ro)], check=False)
    assert result.exit_code == 1
    assert result.output.startswith(f"Error: {ro / 't.parquet'}: cannot write in folder {ro}")
    assert "Read-only file system" in result.output
    assert not (tmp_path / "o.rrd").exists()


def _assert_clean_failure(code, err, disk: pathlib.Path, seconds: float) -> None:
    assert code not in (0, None), err
    assert "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, err
    assert str(disk) in errors[0] and ".tmp" not in errors[0], errors[0]
    assert sorted(p.name for p in disk.iterdir() if p.name != ".filler") == []
    assert seconds < 90


@pytest.mark.slow
def test_run_on_a_full_disk_fails_fast_and_leaves_nothing(tiny_disk, tmp_path):
    from converters.scene.writer import write_scene
    from converters.synthetic import SyntheticSettings, generate_scene

    big = tmp_path / "big.mcap"
    write_scene(big, generate_scene(SyntheticSettings(n_agents=60, duration_s=4.0), seed=1))
    env_args = ["run", str(big), "-o", str(tiny_disk / "o.rrd"), "--table",
                str(tiny_disk / "o.parquet"), "--no-progress"]  # fmt: skip
    os.environ["RISKREPLAY_STALL_TIMEOUT_S"] = "10"
    try:
        code, _, err, seconds, survivors = run_cli(env_args, tmp_path, time_limit_s=120)
    finally:
        del os.environ["RISKREPLAY_STALL_TIMEOUT_S"]
    _assert_clean_failure(code, err, tiny_disk, seconds)
    assert not survivors


@pytest.mark.slow
def test_demo_and_situations_on_a_full_disk_leave_nothing(tiny_disk, tmp_path):
    code, _, err, seconds, _ = run_cli(
        ["demo", "-o", str(tiny_disk / "demo"), "--agents", "40", "--no-progress"], tmp_path
    )
    _assert_clean_failure(code, err, tiny_disk, seconds)
    code, _, err, seconds, _ = run_cli(
        ["convert", "synthetic", "--situations", "60", "-o", str(tiny_disk / "sit"),
         "--no-progress"], tmp_path,
    )  # fmt: skip
    _assert_clean_failure(code, err, tiny_disk, seconds)


# ---------------------------------------------------------------------- kills
def _start(args: list[str], cwd: pathlib.Path) -> subprocess.Popen:
    return subprocess.Popen(
        [*REPLAY, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, start_new_session=True,
    )  # fmt: skip


@pytest.mark.slow
def test_killed_mid_write_leaves_no_output_and_the_next_run_cleans_up(tmp_path):
    out = tmp_path / "sit"
    args = ["convert", "synthetic", "--situations", "400", "-o", str(out), "--no-progress"]
    proc = _start(args, tmp_path)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(out.glob(".*.tmp")):
        time.sleep(0.05)
    assert any(out.glob(".*.tmp")), "the conversion never started writing"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not list(out.glob("*.mcap")), "a killed run must not leave finished outputs"
    left = sorted(out.glob(".*.tmp"))
    assert left  # only temporary files of the killed run remain
    code, _, err, _, _ = run_cli([*args[:3], "3", *args[4:]], tmp_path)
    assert code == 0, err
    assert f"Removed a stale temporary file left by an interrupted run: {left[0]}" in err
    assert sorted(p.name for p in out.iterdir()) == [f"situation_{k:04d}.mcap" for k in range(3)]
    assert not (tmp_path / ".sit.lock").exists()


def _children_of(pid: int) -> list[int]:
    kids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError), open(f"/proc/{entry}/stat") as f:
                stat = f.read()
                if int(stat[stat.rindex(")") + 2 :].split()[1]) == pid:
                    kids.append(int(entry))
    return kids


@pytest.mark.slow
@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGTERM])
def test_batch_leaves_no_orphans_when_its_driver_dies(how, tmp_path):
    from converters.scene.writer import write_scene
    from converters.synthetic import SyntheticSettings, generate_scene

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    settings = SyntheticSettings(n_agents=40, duration_s=3.0)
    for k in range(6):
        write_scene(scenes / f"s{k}.mcap", generate_scene(settings, seed=k))
    proc = _start(["batch", str(scenes), "-o", str(tmp_path / "out"), "--workers", "2",
                   "--no-progress"], tmp_path)  # fmt: skip
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(_children_of(proc.pid)) < 2:
        time.sleep(0.1)
    assert len(_children_of(proc.pid)) >= 2, "no workers started"
    time.sleep(1.0)
    os.kill(proc.pid, how)  # the driver only, not its process group
    proc.wait(timeout=60)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and session_members(proc.pid):
        time.sleep(0.2)
    left = session_members(proc.pid)
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert left == [], f"processes outlived the driver: {left}"
    assert proc.returncode != 0


def test_seeds_and_workers_bounds_are_usage_errors():
    runner = CliRunner()
    for args in (["demo", "--seed", "-1"], ["stats", "x", "--workers", str(10**20)]):
        result = runner.invoke(main, args)
        assert result.exit_code == 2
        assert "Traceback" not in result.output
        assert "Error: Invalid value for" in result.output
