"""Measure: the recording's share of ``replay run`` (issue 15: at most 10 %).

Two shares per scene, each over ``--repeat`` runs (medians, with the range):

- **in process**: the scene replayed exactly as ``replay run`` does (``run_scene`` with a
  ``SceneRecorder`` sink: reading, all nine models, the cascade); the recorder's time is
  the engine's own per-sink timing (``RunSummary.sink_time_s``), the run's time the wall
  time of ``run_scene``. Start-up is left out, so this is the stricter share.
- **end to end**: ``replay run SCENE -o OUT.rrd --no-progress`` in a new process (warm
  kernel cache); the recorder's time is the one the command prints, the run's time the
  process's wall time, start-up and imports included: what a user waits for. With the
  output process (``outputs.process``) the printed time is the replay's wait for the
  process to finish the file, after its frames;
- **added by recording**: the wall time of that command minus the same command with
  ``--no-rrd`` (runs in turns), against the former: what writing the recording adds to
  the user's wait, rerun's import included wherever it happens.

Usage::

    .venv/bin/python benchmarks/bench_recording_share.py SCENE.mcap [...] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import statistics
import subprocess
import sys
import tempfile
import time

from recordings import SceneRecorder
from replay.core.engine import run_scene

REPLAY = str(pathlib.Path(sys.executable).with_name("replay"))
PRINTED = re.compile(r"SceneRecorder ([0-9.]+) s")


def summary(label: str, recs: list[float], runs: list[float]) -> str:
    shares = [r / w for r, w in zip(recs, runs, strict=True)]
    return (
        f"  {label}: recording {statistics.median(recs):.2f} s of "
        f"{statistics.median(runs):.2f} s per run; share median "
        f"{100 * statistics.median(shares):.1f} % [{100 * min(shares):.1f}-"
        f"{100 * max(shares):.1f} %]"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=pathlib.Path)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.scenes:
            recs, runs, size = [], [], 0
            out = pathlib.Path(tmp) / "scene.rrd"
            for _ in range(args.repeat):
                start = time.perf_counter()
                result = run_scene(path, sinks=[SceneRecorder(out)], progress=False)
                runs.append(time.perf_counter() - start)
                recs.append(result.sink_time_s["SceneRecorder"])
                size = out.stat().st_size
            cli_recs, cli_runs, bare_runs = [], [], []
            for _ in range(args.repeat):
                start = time.perf_counter()
                done = subprocess.run(
                    [REPLAY, "run", str(path), "-o", str(out), "--no-progress"],
                    capture_output=True, text=True, check=True,
                )  # fmt: skip
                cli_runs.append(time.perf_counter() - start)
                cli_recs.append(float(PRINTED.findall(done.stdout + done.stderr)[-1]))
                start = time.perf_counter()
                subprocess.run(
                    [REPLAY, "run", str(path), "--no-rrd", "--no-progress"],
                    capture_output=True, text=True, check=True,
                )  # fmt: skip
                bare_runs.append(time.perf_counter() - start)
            added = [max(w - b, 0.0) for w, b in zip(cli_runs, bare_runs, strict=True)]
            print(f"{path} (.rrd {size / 1e6:.1f} MB):")
            print(summary("in process", recs, runs))
            print(summary("end to end (`replay run`, new process)", cli_recs, cli_runs))
            print(summary("added by recording (run minus run --no-rrd)", added, cli_runs))
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
