"""The closed loop's wall time: ``replay plan --closed-loop`` on a corpus sample, two source
trees in turns, and whether their ``closed_loop.parquet`` rows are identical.

Usage::

    python benchmarks/bench_closed_loop.py CORPUS --sample 40 --workers 2 \\
        --tree main=/path/to/main/checkout --tree new=.        # in turns, --repeats R

Each run is the command of issue 35's goal (400 runs x 2 filters with ``pdm`` in at most
15 minutes) on ``--sample`` egos::

    replay plan CORPUS --ego all --every 1000s --planner pdm --filter cascade \\
        --closed-loop --closed-loop-sample N --workers W -o OUT

run with ``nice -n 10`` and each tree first on ``PYTHONPATH``. The trees alternate
(a, b, a, b, ...) so that the shared machine's slow spells fall on both; the figure is
the ratio of the medians. Before the timed runs each tree runs a one-ego sample (numba
compiles its kernels once per tree). The rows of every tree's last run are compared
with the first tree's, timing columns aside. Results go to
``benchmarks/results/closed_loop.md`` (:mod:`results_log`).
"""

from __future__ import annotations

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
import polars as pl

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

from results_log import recorded

#: Columns that are wall times: they differ from run to run.
TIMING = ("plan_ms_median", "plan_ms_p95", "filter_ms_median")


def _load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def run_once(
    tree: pathlib.Path, corpus: str, sample: int, workers: int, out: pathlib.Path
) -> float:
    """Wall time (s) of one ``replay plan --closed-loop`` run of ``tree``."""
    command = [
        "nice", "-n", "10", sys.executable, "-m", "replay", "plan", corpus, "--ego", "all",
        "--every", "1000s", "--planner", "pdm", "--filter", "cascade", "--closed-loop",
        "--closed-loop-sample", str(sample), "--workers", str(workers), "--no-progress",
        "-o", str(out),
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(tree)}
    start = time.perf_counter()
    subprocess.run(command, env=env, cwd=tree, check=True, capture_output=True)
    return time.perf_counter() - start


def differences(a: pl.DataFrame, b: pl.DataFrame) -> int:
    """How many values differ between the two tables' rows (timing columns aside)."""
    if a.columns != b.columns or a.height != b.height:
        return max(a.height, b.height, 1)
    key = ["scene", "ego_id", "filter"]
    cols = [c for c in a.columns if c not in TIMING]
    a, b = a.select(cols).sort(key), b.select(cols).sort(key)
    bad = 0
    for c in cols:
        x, y = a[c], b[c]
        same = (x == y) | (x.is_null() & y.is_null())
        if x.dtype.is_float():
            same = same | (x.is_nan() & y.is_nan())
        bad += int((~same.fill_null(False)).sum())
    return bad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("corpus")
    parser.add_argument("--sample", type=int, default=40)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--tree", action="append", default=[], metavar="NAME=PATH")
    parser.add_argument(
        "--no-warm-up", dest="warm_up", action="store_false",
        help="Skip the untimed one-ego runs (the trees' numba caches are already built).",
    )  # fmt: skip
    args = parser.parse_args()
    trees = [(t.split("=", 1)[0], pathlib.Path(t.split("=", 1)[1]).resolve()) for t in args.tree]
    if not trees:
        trees = [("this", pathlib.Path(__file__).resolve().parents[1])]
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        for name, tree in trees if args.warm_up else []:  # numba compiles once per tree
            run_once(tree, args.corpus, 1, 1, work / f"warm-{name}")
        walls: dict[str, list[float]] = {name: [] for name, _ in trees}
        loads: list[str] = []
        for r in range(args.repeats):
            for name, tree in trees:
                loads.append(_load())
                walls[name].append(
                    run_once(tree, args.corpus, args.sample, args.workers, work / f"{name}-{r}")
                )
        tables = {
            name: pl.read_parquet(work / f"{name}-{args.repeats - 1}" / "closed_loop.parquet")
            for name, _ in trees
        }
    first = trees[0][0]
    runs = tables[first].height
    print(
        f"replay plan --closed-loop, pdm, filters none + cascade, reactive agents, lqr "
        f"tracker: {args.sample} egos ({runs} runs), --workers {args.workers}, nice -n 10, "
        f"{args.repeats} turn(s); load average (1/5/15 min) before each run: {', '.join(loads)}"
    )
    for name, tree in trees:
        wall = float(np.median(walls[name]))
        per_run = wall / max(tables[name].height, 1)
        print(
            f"- {name} ({tree}): wall {', '.join(f'{w:.0f}' for w in walls[name])} s, "
            f"median {wall:.0f} s, {per_run:.2f} s per run; 800 runs at that rate: "
            f"{800 * per_run / 60:.1f} min"
        )
    for name, _ in trees[1:]:
        ratio = float(np.median(walls[first])) / float(np.median(walls[name]))
        bad = differences(tables[first], tables[name])
        print(
            f"- {first} / {name}: {ratio:.2f}x; rows "
            f"{'identical' if bad == 0 else f'DIFFER ({bad} values)'} (timing columns aside)"
        )


if __name__ == "__main__":
    with recorded("closed_loop", "The closed loop's wall time (issue 35)"):
        main()
