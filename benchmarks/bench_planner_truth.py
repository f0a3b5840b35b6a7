"""Planner truth over the recorded corpus: every moving agent as the ego at 1 Hz, the
default planner (idm), every scene's agents table with planner_label (issue 28's speed
target: at most 15 minutes on 2 cores, with progress bars).

Usage::

    .venv/bin/python benchmarks/bench_planner_truth.py SCENES_DIR -o TABLES_DIR
    .venv/bin/python benchmarks/bench_planner_truth.py SCENES_DIR -o TABLES_DIR --scenes 3

``SCENES_DIR`` holds one folder per dataset of converted scenes (``replay batch ... -o OUT``
makes ``OUT/scenes/<dataset>/*.mcap``). ``--scenes K`` takes every K-th scene of each
folder: a documented subset, its time scaled up by the situations it covers (labelled as
such in the result). Each scene's agents table goes to ``TABLES_DIR/<dataset>/<scene>.parquet``
(``replay evaluate TABLES_DIR/*`` evaluates them as they are). The replay is the one
``replay evaluate --planner idm --ego all --every 1s`` runs (the same worker, the same
annotator); the result, with the date and the machine, goes to
``benchmarks/results/planner_truth.md``.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from replay.analysis.stats.collect import planner_annotators
from replay.core.engine import Stride
from replay.core.pool import parallel_map
from replay.core.worker import SceneJob, replay_job
from risk.cascade import CascadeConfig

RESULTS = Path(__file__).resolve().parent / "results" / "planner_truth.md"
TARGET_S = 15 * 60


def _job(job: SceneJob, out: Path) -> tuple[str, int, int, float, float]:
    """Replay one scene with planner truth; write its table; (name, rows, situations,
    wall s, CPU s of this worker)."""
    start = time.perf_counter()
    cpu = time.process_time()
    agents, frames = replay_job(job)
    target = out / job.path.parent.name / f"{job.name}.parquet"
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_suffix(".tmp")
    agents.write_parquet(tmp, compression="zstd")
    tmp.replace(target)
    return (
        job.name,
        agents.height,
        frames.height,
        time.perf_counter() - start,
        time.process_time() - cpu,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", type=Path, help="folder of <dataset>/*.mcap")
    parser.add_argument("-o", "--out", type=Path, required=True, help="folder for the tables")
    parser.add_argument("--planner", default="idm")
    parser.add_argument("--scenes", dest="every_scene", type=int, default=1,
                        help="every K-th scene of each dataset folder (1: all)")  # fmt: skip
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-write", action="store_true", help="do not write the result file")
    args = parser.parse_args()
    folders = sorted(p for p in args.scenes.iterdir() if p.is_dir())
    files = [f for d in folders for f in sorted(d.glob("*.mcap"))[:: args.every_scene]]
    all_files = [f for d in folders for f in sorted(d.glob("*.mcap"))]
    cascade = CascadeConfig.default()
    make = functools.partial(planner_annotators, args.planner)
    jobs = [
        SceneJob(
            f,
            f.name.removesuffix(".mcap"),
            cascade,
            None,
            "all",
            Stride(seconds=1.0),
            annotators=make,
        )
        for f in files
    ]
    start = time.perf_counter()
    results = parallel_map(
        functools.partial(_job, out=args.out), jobs, workers=args.workers, progress=True,
        desc=f"planner truth ({args.planner})", unit="scene",
    )  # fmt: skip
    wall = time.perf_counter() - start
    rows = sum(r[1] for r in results)
    situations = sum(r[2] for r in results)
    share = len(files) / max(1, len(all_files))
    scaled = wall / share
    # The machine is shared: the workers' CPU time over the two cores is what the run
    # would take on two free cores (the wall time includes waiting for other work).
    cpu = sum(r[4] for r in results)
    cpu_wall = cpu / args.workers / share
    slowest = sorted(results, key=lambda r: -r[3])[:5]
    print(
        f"{len(files)} of {len(all_files)} scenes, {situations} situations, {rows} agent-rows: "
        f"{wall:.0f} s wall on {args.workers} workers, {cpu:.0f} s CPU in the workers"
        + (f" (scaled by scenes to the corpus: {scaled:.0f} s)" if share < 1 else "")
    )
    if args.no_write:
        return
    when = datetime.datetime.now(datetime.UTC)
    verdict = "within" if scaled <= TARGET_S else "over"
    cpu_verdict = "within" if cpu_wall <= TARGET_S else "over"
    text = f"""# Planner truth over the recorded corpus

Written by `benchmarks/bench_planner_truth.py` on {when:%Y-%m-%d %H:%M} UTC ({platform.machine()}, \
{os.cpu_count()} CPUs shared with other work, load average \
{", ".join(f"{x:.1f}" for x in os.getloadavg())} at the end, Python \
{platform.python_version()}). Command: `python {" ".join(sys.argv)}`.

Every moving agent as the ego at 1 Hz (`--ego all --every 1s`), planner `{args.planner}` with
planner truth (one plan with all agents, then one without each agent that alone sets a
step of that plan: `replay.planning.truth`), the hindsight truth and every model, each scene's agents table written
as Parquet; {args.workers} worker processes.

| scenes | of | situations | agent-rows | wall s | wall scaled to the corpus s | CPU s in the workers | CPU / workers, scaled s | target s |
|---:|---:|---:|---:|---:|---:|---:|---:|---:|
| {len(files)} | {len(all_files)} | {situations} | {rows} | {wall:.0f} | {scaled:.0f} | {cpu:.0f} | {cpu_wall:.0f} | {TARGET_S} |

The machine was shared with other work (see the load average): the wall time includes
waiting for the cores; the workers' CPU time divided by the workers is what the run
would take on {args.workers} free cores (without the start-up of the pool).

{"A subset (every " + str(args.every_scene) + "-th scene of each dataset), scaled up by the share of scenes: an estimate, not a measurement of the whole corpus. " if share < 1 else ""}\
By wall time the run is {verdict} the 15-minute target; by CPU time on {args.workers} cores it is {cpu_verdict} it.

Slowest scenes (wall): {", ".join(f"{n} {s:.0f} s" for n, _, _, s, _ in slowest)}.
"""
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(text, encoding="utf-8")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
