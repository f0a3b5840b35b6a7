"""The goals of issue 13 (one compiled kernel): medians of CPU and wall time on this machine.

Usage::

    .venv/bin/python benchmarks/bench_kernel.py              # every row (5-10 min)
    .venv/bin/python benchmarks/bench_kernel.py --skip-cold  # without the cold compile
    .venv/bin/python benchmarks/bench_kernel.py --no-settle  # no waiting for the fast state

The last column is the machine's speed just before and after each group of rows
(:class:`MachineSpeed`: this shared machine has slow phases, about 1.7 times slower);
by default the benchmark first probes it for 30 s and then waits (up to ``--max-wait``
seconds) before each group until it runs at its fast speed.

Rows:

- all nine models per frame at N = 100 and N = 1000 (``evaluate(frame)``), the growth;
- the cascade (reachability bound + stages + tier sort) against survival analysis on
  all agents, at N = 100 on the intersection frames of ``bench_models.py`` and at
  N = 1000 on a Waymo-like scene with far agents (a 3 km x 3 km road grid, ego in the
  middle). The cascade's CPU time is the CPU time of ``run_cascade`` minus that of the
  survival-on-all reference it computes for its report, measured separately;
- ``replay run`` on the converted Waymo sample and ``replay demo``, end to end in new
  processes with a warm kernel cache, on the ahead-of-time kernel (``risk.kernel_aot``,
  built first when missing) and on numba's just-in-time one (``RISKREPLAY_KERNEL=jit``),
  with the output process (``outputs.process``) on and off, all four in turns (``--no-rrd`` is not used: the recording is part of
  the job); start-up = ``replay run --help`` / ``replay demo --help`` in a new process
  (the CLI and that one subcommand's imports; ``replay --help`` imports every
  subcommand, which no real command does). That start-up leaves out the libraries the
  command itself loads: rerun in the output process and polars for the table, so
  "minus ``--help``" counts their imports as the command's work;
- ``replay demo`` beyond its start-up with its libraries: the start-up is a new process
  pair that starts as ``replay demo`` does (the output process importing the recording's
  writer) and imports every module the demo imports, then ends
  (:func:`demo_beyond_startup`). Everything after the imports counts: the first kernel
  call's load, the first use of each library, the work. Beside it, the demo's work in one
  process whose modules are imported, the output process off (all in turn, one CPU);
- the cold compile (a new process with an empty ``NUMBA_CACHE_DIR``: wall time and the
  child's CPU time; just in time), then the ahead-of-time build in that folder, and the
  warm import + first call (a new process, warm cache) on either kernel;
- peak RSS (``ru_maxrss``) of a process that evaluates all nine models at N = 1000, and
  of one that only imports risk and evaluates N = 2.

Frames: ``--frames`` random frames per size, each timed ``--repeat`` times; the medians
are over all of those runs.
"""

from __future__ import annotations

import argparse
import compileall
import contextlib
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_models import SPACING_M, _resample, random_frame  # noqa: E402

from risk import Frame, evaluate  # noqa: E402
from risk.cascade import CascadeConfig, run_cascade  # noqa: E402

WAYMO = ROOT.parent / "shared" / "data" / "waymo" / "womd_637f20cafde22ff8.tfrecord"
REPLAY = str(Path(sys.executable).with_name("replay"))


def far_scene(n_agents: int, rng: np.random.Generator) -> Frame:
    """A Waymo-like scene with far agents: straight two-way roads every 250 m on a
    3 km x 3 km grid, agents on lanes with 150 m forward paths (1.5 m spacing), speeds
    0-20 m/s (one in five standing), the ego at the centre."""
    half, lane = 1500.0, 1.75
    roads = np.arange(-half, half + 1, 250.0)
    lanes = []
    for c in roads:
        for off, sign in ((-lane, 1.0), (lane, -1.0)):
            lanes.append(np.array([[-half * sign, c + off], [half * sign, c + off]]))
            lanes.append(np.array([[c - off, -half * sign], [c - off, half * sign]]))
    lanes = [_resample(x, SPACING_M) for x in lanes]
    n_pts = int(150.0 / SPACING_M) + 1
    xy, heading, paths = [], [], []
    for i in range(n_agents):
        lane_pts = lanes[rng.integers(len(lanes))]
        if i == 0:  # the ego near the centre
            j = int(np.argmin(np.hypot(*lane_pts.T)))
            j = min(j, len(lane_pts) - n_pts)
        else:
            j = int(rng.integers(0, len(lane_pts) - n_pts))
        path = lane_pts[j : j + n_pts]
        d = path[1] - path[0]
        xy.append(path[0])
        heading.append(np.arctan2(d[1], d[0]))
        paths.append(path)
    speed = rng.uniform(0, 20, n_agents) * (rng.random(n_agents) > 0.2)
    return Frame.from_arrays(
        np.array(xy), np.array(heading), speed, np.full(n_agents, 4.5),
        np.full(n_agents, 1.9), paths, ego=0,
    )  # fmt: skip


def timed(fn: Callable[[], object], repeat: int) -> tuple[list[float], list[float]]:
    wall, cpu = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return wall, cpu


def medians(frames: list[Frame], fn: Callable[[Frame], object], repeat: int) -> tuple[float, float]:
    wall, cpu = [], []
    for f in frames:
        fn(f)  # warm (page-in, caches)
        w, c = timed(lambda f=f: fn(f), repeat)
        wall += w
        cpu += c
    return statistics.median(wall), statistics.median(cpu)


#: (kernel, output process): the ahead-of-time kernel or numba's just-in-time one
#: (``RISKREPLAY_KERNEL``), the output process (outputs.process) on or off.
MODES = (("aot", "on"), ("aot", "off"), ("jit", "on"), ("jit", "off"))


class MachineSpeed:
    """How fast this machine runs just now, from a fixed workload (a Python loop and a
    numpy sort; the median of 3, in ms).

    This shared virtual machine alternates between a fast state and one about 1.7 times
    slower, for seconds to minutes at a time: on 2026-11-23 the workload took 24-26 ms or
    39-42 ms, and all nine models at N = 100 0.85-0.89 ms or 1.4-1.7 ms, in step. Each
    group of rows records the workload's time just before and just after it. With
    ``settle`` the benchmark waits before each group (up to ``max_wait_s``) until the
    workload runs within 20 % of the fastest it has seen (first probed for
    ``calibrate_s``), so that runs compare."""

    def __init__(self, settle: bool, max_wait_s: float = 120.0, calibrate_s: float = 30.0):
        self.settle = settle
        self.max_wait_s = max_wait_s
        self.best = math.inf
        self.waited_s = 0.0
        self._data = np.random.default_rng(1).random(200_000)
        # The fastest state: probed for a while first (a slow phase lasts up to about a
        # minute here), and kept up to date by every later probe.
        end = time.perf_counter() + (calibrate_s if settle else 0.0)
        self.probe()
        while time.perf_counter() < end:
            time.sleep(0.5)
            self.probe()

    def probe(self) -> float:
        times = []
        for _ in range(3):
            c = time.process_time()
            total = 0
            for i in range(300_000):
                total += i
            np.sort(self._data)
            times.append(1e3 * (time.process_time() - c))
        ms = statistics.median(times)
        self.best = min(self.best, ms)
        return ms

    def ready(self) -> float:
        """The workload's time now, after waiting for the fast state when settling."""
        ms = self.probe()
        start = time.perf_counter()
        while self.settle and ms > 1.2 * self.best:
            if time.perf_counter() - start > self.max_wait_s:
                break
            time.sleep(1.0)
            ms = self.probe()
        self.waited_s += time.perf_counter() - start
        return ms


def mode_env(kernel_form: str, output: str | None = None) -> dict[str, str]:
    env = {**os.environ, "RISKREPLAY_KERNEL": "auto" if kernel_form == "aot" else "jit"}
    if output is not None:
        env["RISKREPLAY_OUTPUT_PROCESS"] = output
    return env


def command_modes(
    args: list[str], repeat: int, machine: MachineSpeed | None = None
) -> dict[tuple[str, str], tuple[float, float]]:
    """:func:`command` in every mode of :data:`MODES`, in turns (so that the machine's
    load hits them alike); each round starts when ``machine`` is ready."""
    runs: dict[tuple[str, str], list[tuple[float, float]]] = {m: [] for m in MODES}
    for _ in range(repeat):
        if machine is not None:
            machine.ready()
        for mode in MODES:
            runs[mode].append(command(args, 1, mode_env(*mode)))
    return {
        m: (statistics.median(r[0] for r in v), statistics.median(r[1] for r in v))
        for m, v in runs.items()
    }


def cascade_medians(frames: list[Frame], repeat: int) -> dict[str, float]:
    """Medians of the cascade (bound + stages + sort) and of survival on all agents."""
    config = CascadeConfig.default()
    casc_wall, surv_wall, casc_cpu, surv_cpu, dropped = [], [], [], [], []
    for f in frames:
        run_cascade(f, config)
        for _ in range(repeat):
            c = time.process_time()
            res = run_cascade(f, config)
            total_cpu = time.process_time() - c
            c = time.process_time()
            evaluate(f, ["survival"])
            s_cpu = time.process_time() - c
            casc_wall.append(res.reach_time_s + res.stage_time_s.sum() + res.sort_time_s)
            surv_wall.append(res.survival_all_time_s)
            casc_cpu.append(max(total_cpu - s_cpu, 0.0))
            surv_cpu.append(s_cpu)
            dropped.append(int(res.unreachable.sum()))
    return {
        "cascade_wall": statistics.median(casc_wall),
        "survival_wall": statistics.median(surv_wall),
        "cascade_cpu": statistics.median(casc_cpu),
        "survival_cpu": statistics.median(surv_cpu),
        "unreachable": statistics.median(dropped),
        "n_others": float(frames[0].others.sum()),
    }


def child(code: str, env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """Wall and CPU time (s) of a new Python process running ``code``, and its stdout."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    w = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    wall = time.perf_counter() - w
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, out.stdout


def adopt_orphans() -> bool:
    """Make this process the reaper of its descendants' orphans (Linux
    ``PR_SET_CHILD_SUBREAPER``): the output process outlives the command by its own
    interpreter shutdown (the command does not wait for it), and its CPU time counts in
    ``RUSAGE_CHILDREN`` only when somebody reaps it."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(36, 1, 0, 0, 0) == 0  # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        return False


def reap_orphans() -> None:
    """Wait for the adopted orphans (see :func:`adopt_orphans`) to end."""
    while True:
        try:
            os.wait4(-1, 0)
        except ChildProcessError:
            return


def command(args: list[str], repeat: int, env: dict[str, str] | None = None) -> tuple[float, float]:
    """Median wall and CPU time (s) of a command in a new process. The wall time ends when
    the command's output has closed (so after its output process has closed it too); the
    CPU time includes the output process's when :func:`adopt_orphans` succeeded."""
    wall, cpu = [], []
    for _ in range(repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        w = time.perf_counter()
        subprocess.run(args, check=True, capture_output=True, env=env)
        wall.append(time.perf_counter() - w)
        reap_orphans()
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime))
    return statistics.median(wall), statistics.median(cpu)


FIRST_CALL = """
import time
t0 = time.perf_counter(); c0 = time.process_time()
import numpy as np
from risk import Frame, evaluate
f = Frame.from_arrays(np.array([[0.0, 0.0], [5.0, 0.0]]), np.zeros(2), np.ones(2), np.ones(2),
    np.ones(2), [np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([[5.0, 0.0], [6.0, 0.0]])], ego=0)
evaluate(f)
print(time.perf_counter() - t0, time.process_time() - c0)
"""

WARM_UP = """
from risk import kernel
kernel.warm_up()
"""

AOT_BUILD = """
from risk import kernel_aot_build
kernel_aot_build.main([])
"""

#: Every module ``replay demo`` imports in the replay's process, one name per line
#: (with the output process on, rerun is imported there instead).
DEMO_MODULES = """
import contextlib, io, os, sys
os.environ["RISKREPLAY_OUTPUT_PROCESS"] = {output!r}
from replay.__main__ import main
sys.argv = ["replay", "demo", "-o", {out!r}, "--no-progress"]
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        main()
    except SystemExit:
        pass
print("\\n".join(sorted(m for m in sys.modules if not m.startswith("__"))))
"""

#: The start-up of ``replay demo`` with its libraries, and nothing else: the output
#: process starts as the command starts it (importing the recording's writer: rerun),
#: the replay's process imports every module of DEMO_MODULES (polars and the CLI
#: included), then waits until the output process has its imports and lets it go.
DEMO_STARTUP = """
import importlib
from outputs import process as background
from replay.cli.output_prestart import start_for
process = start_for(["demo"])
try:
    for name in open({modules!r}).read().split():
        try:
            importlib.import_module(name)
        except Exception:  # (modules a library made up at run time)
            pass
    if process is not None:
        process.run("os:getpid")
finally:
    background.release(process)
"""

#: ``replay demo``'s work alone: the modules of DEMO_MODULES imported first, then one
#: demo in this process, the output process off (everything in turn, on one CPU).
DEMO_AFTER_IMPORTS = """
import contextlib, importlib, io, os, time
os.environ["RISKREPLAY_OUTPUT_PROCESS"] = "off"
for name in open({modules!r}).read().split():
    try:
        importlib.import_module(name)
    except Exception:
        pass
from replay.cli.app import main
w, c = time.perf_counter(), time.process_time()
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    try:
        main(["demo", "-o", {out!r}, "--no-progress"])
    except SystemExit:
        pass
print(time.perf_counter() - w, time.process_time() - c)
"""

RSS = """
import resource, sys
sys.path.insert(0, {bench!r})
import numpy as np
from bench_models import random_frame
from risk import evaluate
n = {n}
f = random_frame(n, np.random.default_rng(3))
evaluate(f)
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
"""


def startup(rows: list[tuple[str, ...]], subcommand: str) -> tuple[float, float]:
    """``replay SUBCOMMAND --help`` in a new process (the CLI and that subcommand's
    imports): its row, and its median wall and CPU time."""
    wall, cpu = command([REPLAY, subcommand, "--help"], 3)
    label = f"start-up of `replay {subcommand}` (`replay {subcommand} --help`)"
    rows.append((label, f"{cpu:.2f} s", f"{wall:.2f} s", ""))
    return wall, cpu


def demo_beyond_startup(
    tmp: Path, whole: tuple[float, float], repeat: int
) -> list[tuple[str, str, str, str]]:
    """The rows of ``replay demo`` beyond its start-up (ahead-of-time kernel).

    Start-up = a new process pair that starts as ``replay demo`` does and imports every
    module it imports, then ends (:data:`DEMO_STARTUP`); beyond start-up = the demo's
    whole time (output process on) minus that. Then the demo's work in one process after
    its imports, everything in turn (:data:`DEMO_AFTER_IMPORTS`)."""
    modules = {}
    for output in ("on", "off"):
        modules[output] = tmp / f"demo_modules_{output}.txt"
        code = DEMO_MODULES.format(output=output, out=str(tmp / "demo_modules"))
        modules[output].write_text(child(code, mode_env("aot", output))[2])
    start = command(
        [sys.executable, "-c", DEMO_STARTUP.format(modules=str(modules["on"]))],
        repeat,
        mode_env("aot", "on"),
    )
    after = []
    for _ in range(repeat):
        code = DEMO_AFTER_IMPORTS.format(modules=str(modules["off"]), out=str(tmp / "demo_after"))
        after.append(tuple(map(float, child(code, mode_env("aot", "off"))[2].split())))
    n_modules = len(modules["on"].read_text().split())
    return [
        (
            f"start-up of `replay demo` with its libraries (its {n_modules} modules "
            "imported, the output process's rerun too; no work)",
            f"{start[1]:.2f} s", f"{start[0]:.2f} s", "",
        ),
        (
            "`replay demo`, beyond that start-up, aot kernel, output process on",
            f"{whole[1] - start[1]:.2f} s", f"{whole[0] - start[0]:.2f} s", "≤ 1 s",
        ),
        (
            "`replay demo`'s work in one process after its imports (output process off: "
            "scene, replay, recording and table in turn), aot kernel",
            f"{statistics.median(c for _, c in after):.2f} s",
            f"{statistics.median(w for w, _ in after):.2f} s", "",
        ),
    ]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--skip-cold", action="store_true", help="skip the cold compile row")
    ap.add_argument(
        "--max-wait", type=float, default=60.0,
        help="seconds to wait at most for the fast state before each group (default 60)",
    )  # fmt: skip
    ap.add_argument(
        "--no-settle", action="store_true",
        help="do not wait for the machine's fast state before each group (MachineSpeed)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    from risk import kernel, kernel_aot_build

    if kernel.IMPLEMENTATION != "aot":  # built once, so that the rows measure what they say
        print(f"  building the ahead-of-time kernel: {kernel_aot_build.build(kernel.CACHE_DIR)}",
              file=sys.stderr)  # fmt: skip
        os.execv(sys.executable, [sys.executable, *sys.argv])  # again, on the built kernel
    print(f"  in-process rows: the {kernel.IMPLEMENTATION} kernel", file=sys.stderr)
    # The project's bytecode written once, as an installed package has it: with
    # PYTHONDONTWRITEBYTECODE set (as on this machine) every new process would otherwise
    # compile each module changed since its .pyc from source.
    for package in ("base", "converters", "recordings", "replay", "risk"):
        compileall.compile_dir(ROOT / package, quiet=1)
    if not adopt_orphans():
        print("  (no subreaper: the output process's CPU time is not counted)", file=sys.stderr)
    rng = np.random.default_rng(7)
    rows: list[tuple[str, ...]] = []
    load = [os.getloadavg()[0]]
    machine = MachineSpeed(settle=not args.no_settle, max_wait_s=args.max_wait)

    @contextlib.contextmanager
    def group() -> Iterator[None]:
        """The rows added inside get the machine's speed just before and after them."""
        start, before = len(rows), machine.ready()
        yield
        after = machine.probe()
        for k in range(start, len(rows)):
            rows[k] = (*rows[k], f"{before:.0f} → {after:.0f}")

    frames = {n: [random_frame(n, rng) for _ in range(args.frames)] for n in (100, 1000)}
    with group():
        nine = {n: medians(frames[n], evaluate, args.repeat) for n in (100, 1000)}
        for n in (100, 1000):
            goal = "≤ 1 ms" if n == 100 else "≤ 10 ms"
            w, c = nine[n]
            rows.append(
                (f"all nine models, N = {n}", f"{1e3 * c:.2f} ms", f"{1e3 * w:.2f} ms", goal)
            )
        rows.append(
            (
                "growth N = 100 → 1000",
                f"{nine[1000][1] / nine[100][1]:.1f}x",
                f"{nine[1000][0] / nine[100][0]:.1f}x",
                "≤ 11x",
            )
        )
    print("  measured evaluate", file=sys.stderr)

    for label, fr, goal in (
        ("cascade vs survival on all, N = 100 (intersection)", frames[100], "≤ 1.0x"),
        (
            "cascade vs survival on all, N = 1000 (far agents)",
            [far_scene(1000, rng) for _ in range(args.frames)],
            "≤ 0.6x",
        ),
    ):
        with group():
            m = cascade_medians(fr, args.repeat)
            rows.append(
                (
                    label,
                    f"{m['cascade_cpu'] / m['survival_cpu']:.2f}x "
                    f"({1e3 * m['cascade_cpu']:.2f} / {1e3 * m['survival_cpu']:.2f} ms)",
                    f"{m['cascade_wall'] / m['survival_wall']:.2f}x "
                    f"({1e3 * m['cascade_wall']:.2f} / {1e3 * m['survival_wall']:.2f} ms); "
                    f"bound drops {m['unreachable']:.0f} of {m['n_others']:.0f}",
                    goal,
                )
            )
    print("  measured cascade", file=sys.stderr)

    with tempfile.TemporaryDirectory() as tmp:
        tmp_p = Path(tmp)
        # Start-up = what the command itself pays before its work: a new process that
        # imports the CLI and only that subcommand (``replay CMD --help``). ``replay
        # --help`` imports every subcommand (scipy.stats, matplotlib, ...), which neither
        # ``run`` nor ``demo`` does.
        with group():
            startup(rows, "run")
        if WAYMO.is_file():
            scene = tmp_p / "waymo.mcap"
            subprocess.run(
                [REPLAY, "convert", "waymo", str(WAYMO), "-o", str(scene)],
                check=True,
                capture_output=True,
            )
            with group():
                runs = command_modes(
                    [REPLAY, "run", str(scene), "--no-progress"], args.repeat, machine
                )
                for mode, run in runs.items():
                    rows.append(
                        (
                            f"`replay run`, Waymo sample (83 agents, 91 frames), new process, "
                            f"{mode[0]} kernel, output process {mode[1]}",
                            f"{run[1]:.2f} s",
                            f"{run[0]:.2f} s",
                            "≤ 2 s wall",
                        )
                    )
        with group():
            demo_start = startup(rows, "demo")
        with group():
            demos = command_modes(
                [REPLAY, "demo", "-o", str(tmp_p / "demo"), "--no-progress"], args.repeat,
                machine,
            )  # fmt: skip
            for mode, demo in demos.items():
                rows.append(
                    (f"`replay demo` (100 agents, 100 frames), whole, {mode[0]} kernel, "
                     f"output process {mode[1]}",
                     f"{demo[1]:.2f} s", f"{demo[0]:.2f} s", "")
                )  # fmt: skip
                rows.append(
                    (
                        f"`replay demo` minus `replay demo --help` (importing rerun and "
                        f"polars counted as work), {mode[0]} kernel, output process {mode[1]}",
                        f"{demo[1] - demo_start[1]:.2f} s",
                        f"{demo[0] - demo_start[0]:.2f} s",
                        "",
                    )
                )
        with group():
            rows += demo_beyond_startup(tmp_p, demos[("aot", "on")], args.repeat)
    print("  measured commands", file=sys.stderr)

    for form in ("aot", "jit"):
        with group():
            first = [child(FIRST_CALL, mode_env(form)) for _ in range(5)]
            inside = sorted(tuple(map(float, out.split())) for _, _, out in first)[2]
            whole = statistics.median(w for w, _, _ in first)
            rows.append(
                (
                    f"warm import + first call (inside the process; whole process), {form} kernel",
                    f"{inside[1]:.2f} s",
                    f"{inside[0]:.2f} s; {whole:.2f} s",
                    "≤ 1 s",
                )
            )
    if not args.skip_cold:
        with tempfile.TemporaryDirectory() as cache, group():
            env = {**mode_env("jit"), "NUMBA_CACHE_DIR": cache}
            wall, cpu, _ = child(FIRST_CALL, env)
            rows.append(
                ("compile from cold, once: first `evaluate` (whole process; just in time)",
                 f"{cpu:.1f} s", f"{wall:.1f} s", "≤ 30 s")
            )  # fmt: skip
        with tempfile.TemporaryDirectory() as cache:
            env = {**mode_env("jit"), "NUMBA_CACHE_DIR": cache}
            with group():
                wall, cpu, _ = child(WARM_UP, env)
                rows.append(
                    ("compile from cold, once: every kernel (`kernel.warm_up()`, what `replay "
                     "run` pays the first time; CPU includes the second compiling process)",
                     f"{cpu:.1f} s", f"{wall:.1f} s", "≤ 30 s")
                )  # fmt: skip
            with group():
                wall, cpu, _ = child(AOT_BUILD, env)
                rows.append(
                    ("then the ahead-of-time build, once (in the background)", f"{cpu:.1f} s",
                     f"{wall:.1f} s", "")
                )  # fmt: skip
    for n in (2, 1000):
        _, _, out = child(RSS.format(bench=str(ROOT / "benchmarks"), n=n))
        rows.append((f"peak RSS, all nine at N = {n}", f"{float(out):.0f} MB", "", "", ""))
    load.append(os.getloadavg()[0])

    print(
        f"Load average (1 min) on this {os.cpu_count()}-core machine: "
        f"{load[0]:.1f} before, {load[1]:.1f} after. Medians of {args.repeat} runs x "
        f"{args.frames} frames; T = 12 s, dt = 0.1 s. Machine speed (MachineSpeed): a "
        f"fixed workload's ms just before and after each group of rows, fastest "
        f"{machine.best:.1f} ms; "
        + (f"waited {machine.waited_s:.0f} s in all for the fast state (within 20 %)."
           if machine.settle else "no waiting (--no-settle).")
    )  # fmt: skip
    print()
    print("| figure | CPU | wall | goal | machine (ms) |")
    print("|---|---:|---:|---|---:|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
