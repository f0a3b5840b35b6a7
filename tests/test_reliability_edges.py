"""Reliability, round 3 (issue 31): what the generated cases of ``reliability_cases.py``
cannot express. Outputs onto device nodes and standard output, signals, giant inputs
simulated by a low memory limit, valid inputs that were refused, and the rough edges a
new user hit (the hindsight line, usage errors, progress bars in pipes, AUC notes).

Device nodes are private copies made with ``mknod`` in the test's folder (a /dev/null
and a /dev/full), never the machine's own: a wrong rename onto them would break
nothing. Tests that need them skip where ``mknod`` is not allowed.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import stat
import subprocess
import threading
import time

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from reliability_cases import REPLAY, scene, session_members, table, without_statistics

from converters.scene.reader import read_scene
from converters.scene.writer import write_scene
from outputs.memory import LIMIT_ENV
from replay.cli.app import main
from risk.frame import Frame, Scene


# ---------------------------------------------------------------------- helpers
def _device(folder: pathlib.Path, name: str, minor: int) -> pathlib.Path:
    """A private character device like /dev/null (minor 3) or /dev/full (minor 7)."""
    path = folder / name
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, minor))
    except (PermissionError, OSError) as exc:
        pytest.skip(f"cannot make a device node here: {exc}")
    return path


def _is_device(path: pathlib.Path) -> bool:
    return stat.S_ISCHR(os.stat(path).st_mode)


def _clean_error(result, *names: object) -> str:
    """The one Error line of a failed CliRunner result (asserting it is one, names the
    given paths and comes without a traceback)."""
    assert result.exit_code not in (0, None), result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.output
    for name in names:
        assert str(name) in errors[0], errors[0]
    return errors[0]


def _leftovers(folder: pathlib.Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


def _crowd(path: pathlib.Path, n: int, frames: int = 2, path_points: int = 2) -> pathlib.Path:
    """A scene of ``n`` agents on a grid, 8 m apart, each with one path."""
    side = int(np.ceil(np.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n] * 8.0
    out = []
    for k in range(frames):
        xy = grid + np.array([k * 1.0, 0.0])
        ahead = np.linspace(0.0, 20.0, path_points)[:, None] * [1.0, 0.0]
        paths = [p + ahead for p in xy]
        out.append(Frame.from_arrays(xy, np.zeros(n), np.full(n, 10.0), np.full(n, 4.0),
                                     np.full(n, 1.8), paths, 0, t=0.1 * k))  # fmt: skip
    good = read_scene(scene(path.parent, ".map.mcap"))
    (path.parent / ".map.mcap").unlink()
    return write_scene(path, Scene(frames=tuple(out), map=good.map, frame_period_s=0.1,
                                   metadata={"converter": "test"}))  # fmt: skip


# ---------------------------------------------------------------------- devices
@pytest.mark.parametrize("option", ["-o", "--table"])
def test_an_output_onto_a_null_device_writes_through_and_keeps_the_node(tmp_path, option):
    s = scene(tmp_path)
    null = _device(tmp_path, "null", 3)
    args = ["run", str(s), option, str(null), "--no-progress"]
    if option == "--table":
        args.insert(2, "--no-rrd")
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert _is_device(null), "the device node was replaced by a file"
    assert _leftovers(tmp_path, {"s.mcap", "null"}) == []


def test_convert_synthetic_onto_a_null_device_keeps_the_node(tmp_path):
    null = _device(tmp_path, "null", 3)
    result = CliRunner().invoke(main, ["convert", "synthetic", "--agents", "6",
                                       "--duration", "1", "-o", str(null)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert _is_device(null)


@pytest.mark.parametrize("option", ["-o", "--table"])
def test_an_output_onto_a_full_device_fails_and_keeps_the_node(tmp_path, option):
    s = scene(tmp_path)
    full = _device(tmp_path, "full", 7)
    args = ["run", str(s), option, str(full), "--no-progress"]
    if option == "--table":
        args.insert(2, "--no-rrd")
    line = _clean_error(CliRunner().invoke(main, args), full)
    assert "No space left on device" in line
    assert _is_device(full)
    assert _leftovers(tmp_path, {"s.mcap", "full"}) == []


def test_a_full_stdout_is_named_in_the_error():
    with open("/dev/full", "wb") as full:
        done = subprocess.run([*REPLAY, "models"], stdout=full, stderr=subprocess.PIPE, text=True)
    assert done.returncode == 1, done.stderr
    assert done.stderr.strip() == (
        "Error: cannot write to standard output: No space left on device"
    ), done.stderr


def test_models_with_stdout_closed_exits_non_zero():
    done = subprocess.run(
        ["/bin/sh", "-c", " ".join(REPLAY) + " models >&-"], capture_output=True, text=True
    )
    assert done.returncode == 1, done.stderr
    assert "standard output is closed" in done.stderr and "Traceback" not in done.stderr


# ---------------------------------------------------------------------- signals
def _default_hangup() -> None:
    """In the child: SIGHUP back to its default action. A test session started under
    ``nohup`` ignores SIGHUP, every child inherits that, and the command rightly keeps
    an inherited "ignore": the hang-up case would then test nothing."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def _replay_until_started(args: list[str], cwd: pathlib.Path, marker: str):
    """Start ``replay ARGS`` in its own session; return it once ``marker`` is on stderr."""
    proc = subprocess.Popen(
        [*REPLAY, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, preexec_fn=_default_hangup,
    )  # fmt: skip
    err: list[str] = []
    seen = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            err.append(line)
            if marker in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    assert seen.wait(120), "".join(err)
    return proc, err, reader


@pytest.fixture(scope="module")
def long_scene(tmp_path_factory) -> pathlib.Path:
    """A scene whose replay with a recording takes a few seconds."""
    from converters.synthetic import SyntheticSettings, generate_scene

    path = tmp_path_factory.mktemp("long") / "long.mcap"
    settings = SyntheticSettings(n_agents=120, duration_s=60.0, frame_period_s=0.05)
    return write_scene(path, generate_scene(settings, seed=2))


@pytest.mark.parametrize(
    ("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129), (signal.SIGINT, 130)]
)
def test_a_signal_stops_run_cleanly_with_its_status(tmp_path, long_scene, sig, status):
    args = ["run", str(long_scene), "-o", "o.rrd", "--table", "t.parquet", "--no-progress"]
    proc, err, reader = _replay_until_started(args, tmp_path, "Ego:")
    time.sleep(0.5)
    os.killpg(proc.pid, sig)  # the whole group, as a terminal does
    proc.wait(60)
    reader.join(10)
    text = "".join(err)
    assert proc.returncode == status, text
    name = signal.Signals(sig).name
    assert f"Stopped by {name}: nothing was written" in text
    assert "Traceback" not in text and "leaked" not in text
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "partial or temporary files left"
    assert session_members(proc.pid) == []


def test_sigterm_stops_stats_workers_without_leaked_semaphores(tmp_path, long_scene):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for k in range(4):  # copies: links to one file are one scene (replay.jobs.scenes)
        shutil.copyfile(long_scene, scenes / f"s{k}.mcap")
    args = ["stats", str(scenes), "-o", "st", "--workers", "2", "--no-plots", "--no-progress"]
    proc = subprocess.Popen([*REPLAY, *args], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(session_members(proc.pid)) < 4:
        time.sleep(0.1)  # the driver, the resource tracker and two workers
    time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "Stopped by SIGTERM" in err
    assert "Traceback" not in err and "leaked" not in err, err
    # Only the parts of scenes complete before the signal may stay (a rerun skips them);
    # no statistics, no temporary file.
    left = [f.relative_to(tmp_path).as_posix() for f in tmp_path.rglob("*") if f.is_file()]
    assert all(f.startswith(("scenes/", "st/parts/")) and not f.endswith(".tmp") for f in left)
    time.sleep(0.5)
    assert session_members(proc.pid) == []


# ---------------------------------------------------------------------- giant inputs
def test_a_path_that_would_not_fit_in_memory_is_refused_naming_the_limit(tmp_path, monkeypatch):
    """Stands in for one 2,000,000-point path among 3,000 agents (44.7 GiB of padding):
    the same check, against a memory limit set low."""
    s = _crowd(tmp_path / "long_paths.mcap", 12, path_points=20_000)
    monkeypatch.setenv(LIMIT_ENV, "0.001")
    result = CliRunner().invoke(main, ["run", str(s), "--no-rrd", "--table",
                                       str(tmp_path / "t.parquet"), "--no-progress"])  # fmt: skip
    line = _clean_error(result, s)
    assert "padded to the longest (20000 points)" in line and LIMIT_ENV in line
    assert not (tmp_path / "t.parquet").exists()


def test_a_huge_truth_horizon_costs_no_more_than_the_scene(tmp_path):
    s = scene(tmp_path)
    start = time.monotonic()
    result = CliRunner().invoke(main, ["evaluate", str(s), "-o", str(tmp_path / "ev"),
                                       "--truth-horizon", "1e9", "--bootstrap", "0",
                                       "--no-plots", "--no-progress"])  # fmt: skip
    assert result.exit_code == 0, result.output  # (7 TiB of padding before issue 31)
    assert "shorter than the 1e+09 s horizon" in result.output
    assert time.monotonic() - start < 60


def test_a_recording_of_too_many_agents_is_refused_with_the_limit(tmp_path):
    from recordings.frames import MAX_RECORDED_AGENTS

    s = _crowd(tmp_path / "crowd.mcap", MAX_RECORDED_AGENTS + 2, frames=1)
    start = time.monotonic()
    result = CliRunner().invoke(main, ["run", str(s), "-o", str(tmp_path / "c.rrd"),
                                       "--no-progress"])  # fmt: skip
    line = _clean_error(result, "c.rrd")
    assert f"more than the {MAX_RECORDED_AGENTS}" in line and "--table" in line
    assert "Cascade" not in result.output  # refused before the replay, not after it
    assert time.monotonic() - start < 60
    assert _leftovers(tmp_path, {"crowd.mcap"}) == []


# ---------------------------------------------------------------------- valid inputs
def test_a_249_character_output_name_is_written(tmp_path):
    s = scene(tmp_path)
    name = "r" * 245 + ".rrd"
    assert len(name) == 249
    result = CliRunner().invoke(main, ["run", str(s), "-o", str(tmp_path / name),
                                       "--no-progress"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert _leftovers(tmp_path, {"s.mcap", name}) == []


def test_an_mcap_without_statistics_is_read(tmp_path):
    s = without_statistics(scene(tmp_path), tmp_path / "nostat.mcap")
    runner = CliRunner()
    inspected = runner.invoke(main, ["inspect", str(s)])
    assert inspected.exit_code == 0, inspected.output
    assert "frames          10 at 0.1 s" in inspected.output
    ran = runner.invoke(main, ["run", str(s), "--no-rrd", "--table", str(tmp_path / "t.csv"),
                               "--no-progress"])  # fmt: skip
    assert ran.exit_code == 0, ran.output
    assert "10 frames" in ran.output


def test_stats_into_its_own_input_folder_twice_reads_no_output_back(tmp_path):
    folder = tmp_path / "d"
    folder.mkdir()
    table(folder, "t.parquet")
    (folder / "sub").mkdir()
    scene(folder / "sub", "a.mcap")  # found in a sub-folder, as batch would
    runner = CliRunner()
    summaries = []
    for _ in range(2):
        result = runner.invoke(main, ["stats", str(folder), "-o", str(folder), "--no-plots",
                                      "--no-progress"])  # fmt: skip
        assert result.exit_code == 0, result.output
        summaries.append(json.loads((folder / "summary.json").read_text()))
    assert summaries[0]["situations"] == summaries[1]["situations"]
    assert summaries[0]["situations"]["total"] > 0


def test_evaluate_report_onto_its_own_summary_is_refused(tmp_path):
    s = scene(tmp_path)
    out = tmp_path / "ev"
    result = CliRunner().invoke(main, ["evaluate", str(s), "-o", str(out), "--report",
                                       str(out / "summary.json"), "--bootstrap", "0",
                                       "--no-plots", "--no-progress"])  # fmt: skip
    line = _clean_error(result, out / "summary.json")
    assert "lies in the output folder" in line  # refused before the evaluation (issue 36)
    assert not out.exists()


# ---------------------------------------------------------------------- rough edges
def test_run_prints_what_hindsight_found(tmp_path):
    s = scene(tmp_path)
    t = tmp_path / "t.parquet"
    result = CliRunner().invoke(main, ["run", str(s), "--no-rrd", "--table", str(t),
                                       "--no-progress"])  # fmt: skip
    assert result.exit_code == 0, result.output
    df = pl.read_parquet(t)
    close = df.filter(pl.col("truth_label").fill_null(False))
    pairs = close.select("ego_id", "agent_id").unique().height
    dropped = close.filter(pl.col("dropped_by").is_not_null())
    line = next(x for x in result.output.splitlines() if x.startswith("Hindsight:"))
    if pairs:
        assert f"{pairs} agent(s) really came close" in line, line
        assert f"in {close.height} agent-frames" in line
        assert f"the cascade dropped {dropped.select('agent_id').n_unique()} of them" in line
    else:
        assert "no agent really came close" in line


def test_no_rrd_without_a_table_is_a_usage_error(tmp_path):
    s = scene(tmp_path)
    result = CliRunner().invoke(main, ["run", str(s), "--no-rrd", "--no-progress"])
    assert result.exit_code == 2
    assert "--no-rrd without --table would write nothing" in result.output


def test_no_progress_bar_goes_into_a_pipe(tmp_path):
    s = scene(tmp_path)
    done = subprocess.run([*REPLAY, "run", str(s), "--no-rrd", "--table", "t.parquet"],
                          cwd=tmp_path, capture_output=True, text=True)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "\r" not in done.stderr and "frame/s" not in done.stderr, done.stderr


def test_stats_and_evaluate_say_how_their_auc_is_computed(tmp_path):
    t = table(tmp_path)
    runner = CliRunner()
    stats = runner.invoke(main, ["stats", str(t), "-o", str(tmp_path / "st"), "--no-plots",
                                 "--no-progress"])  # fmt: skip
    assert stats.exit_code == 0, stats.output
    assert "mean of the per-situation ROC curves" in stats.output
    assert "'replay evaluate' pools" in stats.output
    summary = json.loads((tmp_path / "st" / "summary.json").read_text())
    assert summary["auc_method"].startswith("mean of the per-situation ROC curves")
    s = scene(tmp_path)
    ev = runner.invoke(main, ["evaluate", str(s), "-o", str(tmp_path / "ev"), "--bootstrap",
                              "0", "--no-plots", "--no-progress"])  # fmt: skip
    assert ev.exit_code == 0, ev.output  # (this scene has hindsight positives)
    assert "pooled over every agent-frame" in ev.output
    assert "'replay stats' averages per-situation curves" in ev.output
    summary = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert summary["auc_method"] == "one ROC curve pooled over every agent-frame"


def test_batch_with_ray_missing_leaves_nothing(tmp_path):
    import importlib.util

    if importlib.util.find_spec("ray") is not None:
        pytest.skip("Ray is installed here")
    s = scene(tmp_path)
    result = CliRunner().invoke(main, ["batch", str(s), "-o", str(tmp_path / "out"),
                                       "--engine", "ray", "--no-progress"])  # fmt: skip
    _clean_error(result)
    assert not (tmp_path / "out").exists()


def test_time_line_names_what_was_written_not_classes(tmp_path):
    s = scene(tmp_path)
    result = CliRunner().invoke(main, ["run", str(s), "--no-rrd", "--table",
                                       str(tmp_path / "t.parquet"), "--no-progress"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "writing the table" in result.output
    assert "TableSink" not in result.output and "SceneRecorder" not in result.output


def test_sensitivity_plot_takes_an_interval_that_misses_its_estimate(tmp_path):
    """Issue 31: on two recorded scenes a bootstrap interval lay above its AUC and
    matplotlib raised "'yerr' must not contain negative values"."""
    from replay.analysis.evaluation.plots import plot_sensitivity

    rows = pl.DataFrame({
        "group": ["defaults", "tau"], "variant": ["-", "0.8"],
        "reference": ["hindsight", "hindsight"], "model": ["gaussian", "gaussian"],
        "auc": [0.60, 0.70], "ci_lo": [0.65, 0.50], "ci_hi": [0.80, 0.68],
    })  # fmt: skip
    out = plot_sensitivity(rows, tmp_path / "sensitivity.png")
    assert out.is_file() and out.stat().st_size > 0


#: Put on a child's path: a spawned pool worker (and only one) announces itself and waits
#: at start-up, before anything of the project is imported, until the test lets it go.
_HOLD_WORKERS = """
import os, pathlib, time
_cmd = pathlib.Path("/proc/self/cmdline").read_bytes()
_gate = os.environ.get("RISKREPLAY_TEST_GATE")
if _gate and b"spawn_main" in _cmd:
    pathlib.Path(_gate, f"started-{os.getpid()}").touch()
    _deadline = time.monotonic() + 60
    while not pathlib.Path(_gate, "go").exists() and time.monotonic() < _deadline:
        time.sleep(0.01)
"""


def test_ctrl_c_while_batch_workers_start_prints_no_traceback(tmp_path, long_scene):
    """Issue 31: Ctrl-C early in ``batch --workers 2`` made the starting workers print
    KeyboardInterrupt tracebacks (they now start with SIGINT blocked). Not left to timing
    (issue 36): both workers are held at start-up (a ``sitecustomize`` on their path) until
    the signal has been sent, so it always lands while they start."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for k in range(3):  # copies: links of one file are one scene (read once)
        shutil.copyfile(long_scene, scenes / f"s{k}.mcap")
    hook, gate = tmp_path / "hook", tmp_path / "gate"
    hook.mkdir()
    gate.mkdir()
    (hook / "sitecustomize.py").write_text(_HOLD_WORKERS)
    path = os.pathsep.join(filter(None, [str(hook), os.environ.get("PYTHONPATH", "")]))
    env = {**os.environ, "PYTHONPATH": path, "RISKREPLAY_TEST_GATE": str(gate)}
    proc = subprocess.Popen(
        [*REPLAY, "batch", str(scenes), "-o", "out", "--workers", "2", "--no-progress"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, env=env,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list(gate.glob("started-*"))) < 2:
        time.sleep(0.02)
    assert len(list(gate.glob("started-*"))) == 2, "the workers never started"
    os.killpg(proc.pid, signal.SIGINT)  # both workers are inside their start-up now
    time.sleep(0.5)  # (the signal is delivered; then let the workers go on)
    (gate / "go").touch()
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "Stopped by SIGINT: complete scenes are kept" in err


def test_sigterm_during_convert_situations_leaves_nothing(tmp_path):
    # (many situations: the signal must land while it writes, also on a fast machine)
    args = ["convert", "synthetic", "--situations", "20000", "-o", "sit", "--no-progress"]
    proc = subprocess.Popen([*REPLAY, *args], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)  # fmt: skip
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not any((tmp_path / "sit").glob(".*.tmp")):
        time.sleep(0.02)  # until the first situations are being written
    os.killpg(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "Stopped by SIGTERM" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [], "partial or temporary files left"


def test_risk_tabs_have_a_legend_naming_their_agents(tmp_path):
    from test_recordings import read_rrd

    from recordings import layout as L

    s = scene(tmp_path)
    rrd = tmp_path / "s.rrd"
    result = CliRunner().invoke(main, ["run", str(s), "-o", str(rrd), "--no-progress"])
    assert result.exit_code == 0, result.output
    ents = read_rrd(rrd)
    named = {p: e.static["names"] for p, e in ents.items() if "/risk" in p and "names" in e.static}
    assert named, "no risk timeline carries a series name"
    for path, names in named.items():
        agent = path.removeprefix(L.AGENTS + "/").split("/")[0]
        assert names == [f"agent {agent}"], (path, names)


def test_the_agent_directly_ahead_of_the_ego_is_found_per_frame():
    """Hand-made rows: frame 0 with the ego heading east, frame 1 heading north."""
    from types import SimpleNamespace

    from recordings.labels import lead_rows

    xy = np.array([
        [0, 0], [10, 0.5], [5, 3], [-3, 0], [20, 0],  # frame 0: ego east; lead: (10, 0.5)
        [0, 0], [1, 8], [0, 30], [0, -4],  # frame 1: ego north; lead: (1, 8)
    ], dtype=float)  # fmt: skip
    heading = np.array([0.0] * 5 + [np.pi / 2] * 4)
    is_ego = np.array([1, 0, 0, 0, 0, 1, 0, 0, 0], dtype=bool)
    scene_rows = SimpleNamespace(
        rows={"xy": xy, "heading": heading, "is_ego": is_ego},
        frame_of=np.array([0] * 5 + [1] * 4), times_s=np.array([0.0, 0.1]),
    )  # fmt: skip
    assert np.flatnonzero(lead_rows(scene_rows)).tolist() == [1, 6]


def test_evaluate_exits_non_zero_when_no_reference_has_a_positive(tmp_path):
    """Nothing came close and nothing is survival-important: every rate is undefined, so
    the command fails with one line and writes nothing. With survival positives left,
    the hindsight reference is reported as having none (issue 28), and the run succeeds."""
    s = _crowd(tmp_path / "apart.mcap", 3, frames=30)  # 8 m apart, all driving east
    out = tmp_path / "ev"
    args = ["evaluate", str(s), "-o", str(out), "--truth-gap", "0", "--truth-pet", "0",
            "--bootstrap", "0", "--no-plots", "--no-progress"]  # fmt: skip
    result = CliRunner().invoke(main, [*args, "--baseline-threshold", "1.0"])  # R_S < 1 here
    line = _clean_error(result)
    assert "no agent came close in hindsight" in line
    # No result is written; the scene's parts stay for the next run (replay.jobs).
    assert sorted(p.name for p in out.iterdir()) == ["failures.csv", "parts"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "Reference hindsight: no positive" in result.output


def test_two_outputs_onto_one_null_device_are_both_discarded(tmp_path):
    s = scene(tmp_path)
    null = _device(tmp_path, "null", 3)
    result = CliRunner().invoke(main, ["run", str(s), "-o", str(null), "--table", str(null),
                                       "--no-progress"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert _is_device(null)
    assert _leftovers(tmp_path, {"s.mcap", "null"}) == []


def test_risk_timelines_are_bounded_to_the_agents_that_matter(tmp_path, monkeypatch):
    """Issue 31: 20,000 agents' timelines kept rerun encoding for minutes. At most
    MAX_TIMELINE_AGENTS agents get their own timelines (here lowered to 3)."""
    from test_recordings import read_rrd

    from recordings import layout as L
    from recordings import timelines

    monkeypatch.setenv("RISKREPLAY_OUTPUT_PROCESS", "off")  # (the limit patched here)
    monkeypatch.setattr(timelines, "MAX_TIMELINE_AGENTS", 3)
    s = scene(tmp_path)
    rrd = tmp_path / "s.rrd"
    result = CliRunner().invoke(main, ["run", str(s), "-o", str(rrd), "--no-progress"])
    assert result.exit_code == 0, result.output
    ents = read_rrd(rrd)
    with_timeline = {
        p.removeprefix(L.AGENTS + "/").split("/")[0]
        for p, e in ents.items()
        if p.startswith(L.AGENTS + "/") and "/risk" in p and e.rows
    }
    bodies = {p for p in ents if p.startswith(L.AGENTS + "/") and p.endswith("/body")}
    assert len(bodies) > 3  # every agent is still drawn
    assert 0 < len(with_timeline) <= 3, with_timeline
