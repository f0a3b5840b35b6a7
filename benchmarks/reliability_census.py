"""Census of the reliability cases: every generated bad input, run through the CLI.

Counts, over all cases of ``tests/reliability_cases.py``: clean errors (non-zero exit,
one ``Error:`` line, no traceback, inputs unchanged, nothing left behind, no surviving
process), tracebacks, hangs (killed at the time limit), exit 0 on bad input, changed
inputs and leftovers. Run from the repository root::

    .venv/bin/python benchmarks/reliability_census.py [--jobs 2] [--verbose] [--generated 300]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import pathlib
import sys
import tempfile
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))

from reliability_cases import Outcome, cases, run_case


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--time-limit", type=float, default=120.0)
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument(
        "--generated", type=int, default=300, help="generated hostile pickles among the cases"
    )
    ns = parser.parse_args()
    all_cases = cases(ns.generated)
    start = time.monotonic()
    with (
        tempfile.TemporaryDirectory(prefix="reliability-") as root,
        cf.ThreadPoolExecutor(ns.jobs) as pool,
    ):
        outcomes: list[Outcome] = list(
            pool.map(lambda c: run_case(c, pathlib.Path(root, c.name), ns.time_limit), all_cases)
        )
    wall = time.monotonic() - start
    rows = {
        "cases tried": len(outcomes),
        "clean errors": sum(o.clean_error for o in outcomes),
        "tracebacks": sum(o.traceback for o in outcomes),
        "hangs": sum(o.hung for o in outcomes),
        "exit 0 on bad input": sum(o.returncode == 0 for o in outcomes),
        "inputs changed": sum(bool(o.inputs_changed) for o in outcomes),
        "leftovers": sum(bool(o.leftovers) for o in outcomes),
        "surviving processes": sum(bool(o.survivors) for o in outcomes),
        "not one Error: line": sum(len(o.error_lines) != 1 for o in outcomes),
    }
    kinds = sorted({o.kind for o in outcomes})
    print("cases by kind: " + ", ".join(f"{k} {sum(o.kind == k for o in outcomes)}" for k in kinds))
    for name, value in rows.items():
        print(f"{name:<22}{value:>5}")
    slowest = max(outcomes, key=lambda o: o.seconds)
    print(f"wall time {wall:.1f} s with {ns.jobs} jobs; slowest case {slowest.case}"
          f" {slowest.seconds:.1f} s")  # fmt: skip
    bad = [o for o in outcomes if not o.clean_error]
    for o in bad if ns.verbose or bad else []:
        last = (o.error_lines or o.stderr.strip().splitlines() or ["(no output)"])[-1]
        print(
            f"  NOT CLEAN {o.case}: exit {o.returncode}, {o.seconds:.1f} s, leftovers"
            f" {o.leftovers}, changed {o.inputs_changed}: {last[:160]}"
        )


if __name__ == "__main__":
    main()
