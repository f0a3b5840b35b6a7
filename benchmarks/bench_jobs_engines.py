"""Benchmark: ``replay evaluate`` on a corpus with the local engine against a local Ray
instance (issue 38's goal for the corpus commands: Ray within 1.25x of local processes).

Each run is ``python -m replay evaluate SCENES -o OUT --engine E --workers W`` into a
fresh folder, in a fresh process; the engines take turns in every repeat, and medians
are reported. ``replay / read`` (from ``summary.json``) is the job runner's part: starting
the engine (for Ray: starting a local instance and its workers), replaying every scene
into its parts, and reading them back; ``whole`` is the command's wall time.

Usage::

    python benchmarks/bench_jobs_engines.py --scenes DIR --work DIR [--workers 2]
        [--repeat 3] [--bootstrap 200]
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import statistics
import subprocess
import sys
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=pathlib.Path, required=True)
    ap.add_argument("--work", type=pathlib.Path, required=True)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--bootstrap", type=int, default=200)
    args = ap.parse_args()
    env = {**os.environ, "PYTHONPATH": str(pathlib.Path(__file__).resolve().parents[1])}
    times: dict[str, list[tuple[float, float]]] = {"local": [], "ray": []}
    n = len(list(args.scenes.glob("*.mcap")))
    for rep in range(args.repeat):
        for engine in ("local", "ray"):
            out = args.work / f"{engine}-{rep}"
            shutil.rmtree(out, ignore_errors=True)
            cmd = [
                sys.executable, "-m", "replay", "evaluate", str(args.scenes), "-o", str(out),
                "--engine", engine, "--workers", str(args.workers), "--bootstrap",
                str(args.bootstrap), "--no-plots", "--no-progress",
            ]  # fmt: skip
            load = os.getloadavg()[0]
            start = time.perf_counter()
            done = subprocess.run(cmd, env=env, capture_output=True, text=True)
            whole = time.perf_counter() - start
            if done.returncode:
                sys.exit(done.stderr[-2000:] + done.stdout[-2000:])
            read = json.loads((out / "summary.json").read_text())["time_s"]["replay / read"]
            times[engine].append((read, whole))
            print(
                f"run {rep} {engine:5}: replay / read {read:6.1f} s, whole {whole:6.1f} s "
                f"(1-min load before: {load:.1f})",
                flush=True,
            )
    med = {e: (statistics.median(r for r, _ in t), statistics.median(w for _, w in t))
           for e, t in times.items()}  # fmt: skip
    for e, (r, w) in med.items():
        print(f"{e:5}: {n} scenes, median replay / read {r:.1f} s, whole {w:.1f} s")
    print(
        f"ray / local: replay / read {med['ray'][0] / med['local'][0]:.2f}x, "
        f"whole {med['ray'][1] / med['local'][1]:.2f}x"
    )


if __name__ == "__main__":
    main()
