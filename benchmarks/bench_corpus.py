"""Benchmark: converting the whole recorded corpus (``../shared/data/recorded``).

Every input the source registry detects in the folder tree (converters.sources.discover)
is converted in this process, one after the other, and written to MCAP in a temporary
folder: what ``replay batch CORPUS -o OUT`` does before replaying, on one core. Reports
the scenes, agents and frames converted, failures (one line each), the seconds per
source and in total (median over ``--repeat`` runs), and the slowest inputs.

Usage::

    .venv/bin/python benchmarks/bench_corpus.py [--repeat 3] [--corpus PATH] [--paths map]
"""

from __future__ import annotations

import argparse
import collections
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters.lanegraph import PathSettings  # noqa: E402
from converters.scene.writer import write_scene  # noqa: E402
from converters.sources import SOURCES, ReadOptions, discover  # noqa: E402
from converters.tracks import Skipped  # noqa: E402

CORPUS = (
    Path(os.environ.get("RISKREPLAY_SHARED_DATA") or ROOT.parent / "shared" / "data") / "recorded"
)


def one_run(corpus: Path, paths: str, out: Path) -> dict:
    found = discover([corpus])
    per_source: dict[str, float] = collections.defaultdict(float)
    per_input: list[tuple[float, str]] = []
    scenes = agents = frames = 0
    failures: list[str] = []
    options = ReadOptions(paths=paths, settings=PathSettings())
    t_all, c_all = time.perf_counter(), time.process_time()
    for k, inp in enumerate(found.inputs):
        t0 = time.perf_counter()
        try:
            for j, (_, build) in enumerate(SOURCES[inp.source].scenes(inp, options, Skipped())):
                scene = build()
                write_scene(out / f"{k}-{j}.mcap", scene)
                scenes += 1
                agents += scene.frames[0].n_agents
                frames += len(scene.frames)
        except Exception as exc:
            failures.append(f"{inp.path}: {type(exc).__name__}: {exc}".splitlines()[0])
        dt = time.perf_counter() - t0
        per_source[inp.source] += dt
        per_input.append((dt, str(inp.path.relative_to(corpus))))
    total = time.perf_counter() - t_all
    cpu = time.process_time() - c_all
    return {
        "inputs": len(found.inputs),
        "unreadable": [str(p) for p in found.unreadable],
        "scenes": scenes,
        "agents": agents,
        "frames": frames,
        "failures": failures,
        "per_source": dict(per_source),
        "slowest": sorted(per_input, reverse=True)[:5],
        "total": total,
        "cpu": cpu,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--corpus", type=Path, default=CORPUS)
    parser.add_argument("--paths", default="map", choices=("map", "hindsight"))
    args = parser.parse_args()
    runs = []
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            runs.append(one_run(args.corpus, args.paths, Path(tmp)))
    last = runs[-1]
    print(f"corpus {args.corpus} ({args.paths} paths), {args.repeat} run(s), medians:")
    print(
        f"  {last['inputs']} inputs -> {last['scenes']} scenes, {last['agents']} agents, "
        f"{last['frames']} frames; {len(last['failures'])} failed, "
        f"{len(last['unreadable'])} files no converter reads"
    )
    for line in last["failures"] + last["unreadable"]:
        print(f"  FAILED {line}")
    for source in sorted(last["per_source"]):
        med = statistics.median(r["per_source"][source] for r in runs)
        print(f"  {source:12s} {med:7.2f} s")
    med_total = statistics.median(r["total"] for r in runs)
    med_cpu = statistics.median(r["cpu"] for r in runs)
    print(
        f"  {'total':12s} {med_total:7.2f} s wall ({last['scenes'] / med_total:.1f} scenes/s), "
        f"{med_cpu:.2f} s CPU (this process)"
    )
    print("  slowest inputs (last run):")
    for dt, name in last["slowest"]:
        print(f"    {dt:6.2f} s  {name}")


if __name__ == "__main__":
    main()
