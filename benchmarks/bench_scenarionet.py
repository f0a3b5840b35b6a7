"""Benchmark: converting one ScenarioNet scene (goal: at most 2 s for 20 s and 226 tracks).

The input is nuScenes ``scene-0061`` of the format's test data (191 steps at 10 Hz,
226 tracks, 460 lanes without successor links), converted in process as
``replay convert scenarionet`` does: safe load, checks, tracks, lane chaining, map paths
(with the recorded-future fallback), frames and the MCAP write. Medians over
``--repeat`` runs after one warm-up run (imports and first-call costs are not counted);
the load alone and the conversion without the write are timed too, and the process's
CPU time (what the wall time would be on an idle core) with the load average beside it.

Usage::

    .venv/bin/python benchmarks/bench_scenarionet.py [--repeat 7] [FILE.pkl]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import safe_pickle, scenarionet  # noqa: E402
from converters.scene.writer import write_scene  # noqa: E402

DEFAULT = (
    Path(os.environ.get("RISKREPLAY_SHARED_DATA") or ROOT.parent / "shared" / "data")
    / "scenarionet/nuscenes_0/sd_nuscenes_v1.0-mini_scene-0061.pkl"
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file", nargs="?", type=Path, default=DEFAULT)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    if not args.file.is_file():
        sys.exit(f"{args.file}: not found (the shared ScenarioNet samples are needed)")
    load, build, total, cpu = [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "scene.mcap"
        for k in range(args.repeat + 1):
            c0 = time.process_time()
            t0 = time.perf_counter()
            sd = scenarionet.read_scenario(args.file)
            t1 = time.perf_counter()
            scene = scenarionet.scenario_to_scene(sd, source=args.file)
            t2 = time.perf_counter()
            write_scene(out, scene)
            t3 = time.perf_counter()
            c3 = time.process_time()
            if k:  # the first run pays imports and first calls
                load.append(t1 - t0)
                build.append(t2 - t1)
                total.append(t3 - t0)
                cpu.append(c3 - c0)
        size = out.stat().st_size
    safe_pickle.load(args.file)  # the loader alone, for the record below
    f = scene.frames[0]
    print(
        f"{args.file.name}: {len(scene.frames)} frames, {f.n_agents} tracks, "
        f"{len(scene.map.lanes)} lanes; {size / 1024:.0f} KiB written"
    )
    print(f"runs: {args.repeat} (after one warm-up)")
    print(f"  safe load + checks : median {statistics.median(load):.3f} s")
    print(f"  tracks, map, paths : median {statistics.median(build):.3f} s")
    print(f"  total with write   : median {statistics.median(total):.3f} s  (goal <= 2 s)")
    print(f"  total, all runs    : {', '.join(f'{t:.2f}' for t in total)}")
    print(f"  CPU time (process) : median {statistics.median(cpu):.3f} s")
    print(f"  load average       : {', '.join(f'{v:.1f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
