"""Benchmark: ``replay plan`` on local processes against a local Ray instance (issue 38's
goal: Ray on a local two-CPU instance within 1.25x of the local-process time, on at least
20 scenes).

Each run is ``python -m replay plan SCENES -o OUT --engine E --workers W ...`` into a
fresh folder, in a fresh process (so Ray's start and stop are counted); the engines take
turns in every repeat and the medians of the wall times are compared. The figures go to
``benchmarks/results/plan_engines.md`` (dated, with the machine's load).

Usage::

    nice -n 10 python benchmarks/bench_plan_engines.py --scenes /work/runs/final/heldout \\
        --work /tmp/bench-plan [--workers 2] [--repeat 3] [--every 1s] [--ego all]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import time

from results_log import recorded

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=pathlib.Path, required=True)
    ap.add_argument("--work", type=pathlib.Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--every", default="1s")
    ap.add_argument("--ego", default="all")
    ap.add_argument("--planner", default="idm")
    ap.add_argument("--warmup", type=int, default=1, help="untimed local runs first")
    args = ap.parse_args()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    n = len(list(args.scenes.rglob("*.mcap")))
    study = [
        "--ego", args.ego, "--every", args.every, "--planner", args.planner,
        "--filter", "cascade", "--filter", "nearest:match", "--workers", str(args.workers),
        "--no-plots", "--no-progress",
    ]  # fmt: skip
    print(
        f"replay plan {args.scenes} ({n} scenes) {' '.join(study)}; engines in turns, "
        f"{args.repeat} repeats"
    )

    def run(engine: str, out: pathlib.Path) -> float:
        shutil.rmtree(out, ignore_errors=True)
        cmd = [sys.executable, "-m", "replay", "plan", str(args.scenes), "-o", str(out),
               "--engine", engine, *study]  # fmt: skip
        start = time.perf_counter()
        done = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if done.returncode:
            sys.exit(done.stderr[-2000:] + done.stdout[-2000:])
        return time.perf_counter() - start

    for k in range(args.warmup):
        print(f"warm-up local: {run('local', args.work / f'warmup-{k}'):6.1f} s (not counted)")
    times: dict[str, list[float]] = {"local": [], "ray": []}
    for rep in range(args.repeat):
        for engine in ("local", "ray"):
            load = os.getloadavg()[0]
            whole = run(engine, args.work / f"{engine}-{rep}")
            times[engine].append(whole)
            print(f"run {rep} {engine:5}: {whole:6.1f} s (1-min load before: {load:.1f})")
    med = {e: statistics.median(t) for e, t in times.items()}
    for e, m in med.items():
        print(f"{e:5}: median {m:.1f} s")
    print(f"ray / local: {med['ray'] / med['local']:.2f}x (goal: at most 1.25x)")


if __name__ == "__main__":
    with recorded("plan_engines", "`replay plan` on local processes against a local Ray instance"):
        main()
