"""Two trees of the project compared in turns (before, after, after, before, ...), so that
a shared machine's slow phases fall on both alike.

Usage (each tree with its own venv in ``TREE/.venv`` and kernel cache folder, the
ahead-of-time kernel built there first)::

    python benchmarks/bench_turns.py models BEFORE_TREE BEFORE_CACHE AFTER_TREE AFTER_CACHE [--turns 5] [--jit]
    python benchmarks/bench_turns.py commands BEFORE_TREE BEFORE_CACHE AFTER_TREE AFTER_CACHE [--turns 5]

``models``: per turn a new process in the tree measures the CPU-time median of
``evaluate(frame, [model])`` for each model and all nine at N = 100 and 1000 (the random
frames of ``bench_kernel.py``, seed 7, 3 frames x 7 calls) and the cascade's CPU ratio
(``bench_kernel.cascade_medians``). ``commands``: ``replay run`` on the converted Waymo
sample and ``replay demo`` with ``RISKREPLAY_OUTPUT_PROCESS`` on and off; wall time, and
CPU time of the command and its children (the output process too: this process adopts
orphans). Prints a Markdown table of the medians over the turns (min-max).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WAYMO = os.path.join(
    os.path.dirname(ROOT), "shared", "data", "waymo", "womd_637f20cafde22ff8.tfrecord"
)

#: Run in the tree (its working directory) by the tree's Python: prints one JSON line.
MODELS_CHILD = """
import json, os, statistics, sys, time
sys.path[:0] = [os.getcwd(), os.path.join(os.getcwd(), "benchmarks")]
import numpy as np
from bench_kernel import cascade_medians, far_scene
from bench_models import random_frame
from risk import MODELS, evaluate, kernel
assert kernel.IMPLEMENTATION == os.environ["WANT_KERNEL"], kernel.IMPLEMENTATION
rng = np.random.default_rng(7)
frames = {n: [random_frame(n, rng) for _ in range(3)] for n in (100, 1000)}
def med(fn, fr, repeat=7):
    cpu = []
    for f in fr:
        fn(f)
        for _ in range(repeat):
            c = time.process_time(); fn(f); cpu.append(time.process_time() - c)
    return statistics.median(cpu)
out = {}
for n in (100, 1000):
    out[f"all nine, N={n}"] = med(lambda f: evaluate(f), frames[n])
    for name in MODELS:
        out[f"{name}, N={n}"] = med(lambda f, name=name: evaluate(f, [name]), frames[n])
m = cascade_medians(frames[100], 5)
out["cascade/survival N=100"] = m["cascade_cpu"] / m["survival_cpu"]
m = cascade_medians([far_scene(1000, rng) for _ in range(3)], 5)
out["cascade/survival N=1000 far"] = m["cascade_cpu"] / m["survival_cpu"]
print(json.dumps(out))
"""


def adopt_orphans() -> bool:
    import ctypes

    return ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0) == 0  # SUBREAPER


def reap() -> None:
    while True:
        try:
            os.wait4(-1, 0)
        except ChildProcessError:
            return


def models(trees: dict[str, tuple[str, str]], turns: int, jit: bool) -> None:
    res: dict[str, list[dict[str, float]]] = {k: [] for k in trees}
    for t in range(turns):
        for name in list(trees) if t % 2 == 0 else list(trees)[::-1]:
            tree, cache = trees[name]
            env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": "",
                   "WANT_KERNEL": "jit" if jit else "aot"}  # fmt: skip
            if jit:
                env["RISKREPLAY_KERNEL"] = "jit"
            run = subprocess.run([f"{tree}/.venv/bin/python", "-c", MODELS_CHILD], cwd=tree,
                                 capture_output=True, text=True, env=env, check=True)  # fmt: skip
            res[name].append(json.loads(run.stdout.splitlines()[-1]))
        print(f"turn {t}: load {os.getloadavg()[0]:.1f}", file=sys.stderr, flush=True)
    before, after = res.values()
    print(f"| row | before (median of {turns} turns; min-max) | after | after / before |")
    print("|---|---:|---:|---:|")
    for row in before[0]:
        b, a = [x[row] for x in before], [x[row] for x in after]

        def fmt(v: float, row: str = row) -> str:
            return f"{v:.2f}x" if "cascade" in row else f"{1e3 * v:.3f} ms"

        mb, ma = statistics.median(b), statistics.median(a)
        print(f"| {row} | {fmt(mb)} ({fmt(min(b))}-{fmt(max(b))}) | "
              f"{fmt(ma)} ({fmt(min(a))}-{fmt(max(a))}) | {ma / mb:.2f} |")  # fmt: skip


def commands(trees: dict[str, tuple[str, str]], turns: int) -> None:
    print(f"subreaper: {adopt_orphans()}")
    tmp = tempfile.mkdtemp(prefix="bench-turns-")
    scene = os.path.join(tmp, "waymo.mcap")
    first = next(iter(trees.values()))[0]
    subprocess.run([f"{first}/.venv/bin/replay", "convert", "waymo", WAYMO, "-o", scene],
                   check=True, capture_output=True)  # fmt: skip
    cmds = {
        "run Waymo": ["run", scene, "-o", os.path.join(tmp, "w.rrd"), "--no-progress"],
        "demo": ["demo", "-o", os.path.join(tmp, "demo"), "--no-progress"],
    }
    res: dict[tuple[str, str, str], list[tuple[float, float]]] = {}
    for t in range(turns):
        for name in list(trees) if t % 2 == 0 else list(trees)[::-1]:
            tree, cache = trees[name]
            for mode in ("on", "off") if t % 2 == 0 else ("off", "on"):
                env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": "",
                       "RISKREPLAY_OUTPUT_PROCESS": mode}  # fmt: skip
                for label, cmd in cmds.items():
                    before = resource.getrusage(resource.RUSAGE_CHILDREN)
                    w = time.perf_counter()
                    subprocess.run([f"{tree}/.venv/bin/replay", *cmd], env=env, check=True,
                                   capture_output=True)  # fmt: skip
                    wall = time.perf_counter() - w
                    reap()
                    after = resource.getrusage(resource.RUSAGE_CHILDREN)
                    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
                    res.setdefault((label, name, mode), []).append((wall, cpu))
        print(f"turn {t}: load {os.getloadavg()[0]:.1f}", file=sys.stderr, flush=True)
    print("| command | tree | output process | wall median (min-max) | CPU median |")
    print("|---|---|---|---:|---:|")
    for (label, name, mode), v in sorted(res.items()):
        w, c = [x[0] for x in v], [x[1] for x in v]
        print(f"| {label} | {name} | {mode} | {statistics.median(w):.2f} s "
              f"({min(w):.2f}-{max(w):.2f}) | {statistics.median(c):.2f} s |")  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("models", "commands"))
    ap.add_argument("before_tree")
    ap.add_argument("before_cache")
    ap.add_argument("after_tree")
    ap.add_argument("after_cache")
    ap.add_argument("--turns", type=int, default=5)
    ap.add_argument("--jit", action="store_true", help="models: the just-in-time kernel")
    args = ap.parse_args()
    trees = {"before": (args.before_tree, args.before_cache),
             "after": (args.after_tree, args.after_cache)}  # fmt: skip
    if args.what == "models":
        models(trees, args.turns, args.jit)
    else:
        commands(trees, args.turns)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
