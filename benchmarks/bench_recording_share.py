"""Measure: the recording's share of ``replay run`` (issue 15: at most 10 %).

Each scene is replayed ``--repeat`` times in this process exactly as ``replay run`` does
(``run_scene`` with a ``SceneRecorder`` sink; reading, all nine models, the cascade),
alternating with nothing else. The recorder's time is the engine's own per-sink timing
(``RunSummary.sink_time_s``); the run's time is the wall time of ``run_scene``. The machine
is shared, so the medians of the per-run shares are reported, with the range.

Usage::

    .venv/bin/python benchmarks/bench_recording_share.py SCENE.mcap [...] [--repeat 5]
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import tempfile
import time

from recordings import SceneRecorder
from replay.engine import run_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=pathlib.Path)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.scenes:
            shares, recs, runs, size = [], [], [], 0
            for k in range(args.repeat):
                out = pathlib.Path(tmp) / f"{k}.rrd"
                start = time.perf_counter()
                summary = run_scene(path, sinks=[SceneRecorder(out)], progress=False)
                run_s = time.perf_counter() - start
                rec_s = summary.sink_time_s["SceneRecorder"]
                shares.append(rec_s / run_s)
                recs.append(rec_s)
                runs.append(run_s)
                size = out.stat().st_size
            print(
                f"{path}: recording {statistics.median(recs):.2f} s of "
                f"{statistics.median(runs):.2f} s per run; share median "
                f"{100 * statistics.median(shares):.1f} % [{100 * min(shares):.1f}-"
                f"{100 * max(shares):.1f} %] over {args.repeat} runs; .rrd {size / 1e6:.1f} MB"
            )


if __name__ == "__main__":
    main()
