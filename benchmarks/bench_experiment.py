"""Benchmark: ``replay experiment`` (500 situations) end to end, and its stages.

Target (issue 5): the 500-situation experiment end to end in at most 3 minutes on the
2-core machine, using both cores.

Each repeat runs the command as a user does, in a fresh process (interpreter start,
imports, worker start-up, report included), and records

- the wall time, and the CPU time of the command and its worker processes (CPU / wall
  above 1 means more than one core was busy);
- the per-stage wall times the command prints (``Time: ...``).

The machine is shared with other work, so medians over the repeats are reported.

Usage::

    .venv/bin/python benchmarks/bench_experiment.py [--repeat 3] [--situations 500]
        [--workers N]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
TARGET_S = 180.0


def run_once(situations: int, workers: int | None, out: pathlib.Path) -> dict[str, float]:
    """One end-to-end run; returns wall, cpu and the printed stage times (s)."""
    replay = pathlib.Path(sys.executable).with_name("replay")
    cmd = [
        str(replay),
        "experiment",
        "--situations",
        str(situations),
        "-o",
        str(out),
        "--no-progress",
    ]
    if workers:
        cmd += ["--workers", str(workers)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"replay experiment failed:\n{proc.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    times = {"end to end (wall)": wall, "CPU, all processes": cpu}
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("Time: "))
    for name, value in re.findall(r"([a-z+()/ ]+?) ([\d.]+) s", line.removeprefix("Time: ")):
        times[name.strip().lstrip(", ")] = float(value)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--situations", type=int, default=500)
    parser.add_argument("--workers", type=int, default=None, help="default: CPU count")
    args = parser.parse_args()
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeat):
            runs.append(run_once(args.situations, args.workers, pathlib.Path(tmp) / f"r{k}"))
            print(f"run {k + 1}: {runs[-1]['end to end (wall)']:.1f} s", file=sys.stderr)
    keys = list(runs[0])
    print(
        f"replay experiment --situations {args.situations} "
        f"(workers: {args.workers or os.cpu_count()}), {args.repeat} runs; median [min, max] s"
    )
    for key in keys:
        values = [r[key] for r in runs if key in r]
        print(
            f"  {key:<38}{statistics.median(values):8.1f}  [{min(values):.1f}, {max(values):.1f}]"
        )
    wall = statistics.median(r["end to end (wall)"] for r in runs)
    cpu = statistics.median(r["CPU, all processes"] for r in runs)
    print(f"  CPU / wall: {cpu / wall:.2f} (above 1: more than one core busy)")
    verdict = "meets" if wall <= TARGET_S else "MISSES"
    print(f"Target: <= {TARGET_S:.0f} s end to end: {verdict} ({wall:.1f} s median)")


if __name__ == "__main__":
    main()
