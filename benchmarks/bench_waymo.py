"""Benchmark: converting the Waymo Open Motion sample to an MCAP scene.

Target (issue 6): the sample (one Scenario: 83 agents, 91 frames, 199 lanes) converts in
under 2 s end to end, i.e. what ``replay convert waymo FILE -o OUT`` does after start-up:
read and CRC-check the TFRecord, decode the Scenario, build the tracks, match agents to
lanes and cut their forward paths, build the frames, write the MCAP.

Each run starts from a fresh ``LaneGraph`` (no cache survives between runs). The stages
are timed separately and in total; the machine is shared, so medians over ``--repeat``
runs are reported. The CLI itself is timed as a subprocess too (that includes the Python
start-up and imports).

Usage::

    .venv/bin/python benchmarks/bench_waymo.py [--repeat 7] [--paths map|hindsight]
                                                 [--file PATH]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters.lanegraph import PathSettings  # noqa: E402
from converters.scene.writer import write_scene  # noqa: E402
from converters.tfrecord import read_records  # noqa: E402
from converters.waymo import decode_scenario, scenario_to_scene  # noqa: E402

SAMPLE = ROOT.parent / "shared" / "data" / "waymo" / "womd_637f20cafde22ff8.tfrecord"


def one_run(path: Path, paths: str, out_dir: Path) -> dict[str, float]:
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    records = [r for r in read_records(path)]  # framing + CRC of every record
    t1 = time.perf_counter()
    messages = [decode_scenario(r, path) for r in records]
    t2 = time.perf_counter()
    scenes = [
        scenario_to_scene(m, source=path, record=r.index, paths=paths, settings=PathSettings())
        for m, r in zip(messages, records, strict=True)
    ]
    t3 = time.perf_counter()
    for i, scene in enumerate(scenes):
        write_scene(out_dir / f"s{i}.mcap", scene)
    t4 = time.perf_counter()
    times["read+crc"] = t1 - t0
    times["decode"] = t2 - t1
    times["tracks+paths+frames"] = t3 - t2
    times["write mcap"] = t4 - t3
    times["total"] = t4 - t0
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--paths", choices=("map", "hindsight"), default="map")
    parser.add_argument("--file", type=Path, default=SAMPLE)
    args = parser.parse_args()
    if not args.file.is_file():
        sys.exit(f"sample not found: {args.file}")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        one_run(args.file, args.paths, Path(tmp))  # warm-up: imports, page cache
        for _ in range(args.repeat):
            runs.append(one_run(args.file, args.paths, Path(tmp)))
        cli = []
        for _ in range(max(3, args.repeat // 2)):
            t0 = time.perf_counter()
            subprocess.run(
                [sys.executable, "-m", "replay", "convert", "waymo", str(args.file),
                 "-o", str(Path(tmp) / "cli"), "--paths", args.paths],
                check=True, capture_output=True, cwd=ROOT,
            )  # fmt: skip
            cli.append(time.perf_counter() - t0)
    print(f"Waymo sample {args.file.name}, --paths {args.paths}, {args.repeat} runs (median, min):")
    for stage in runs[0]:
        values = [r[stage] for r in runs]
        print(f"  {stage:22s} {statistics.median(values):7.3f} s  {min(values):7.3f} s")
    print(f"  {'CLI (new process)':22s} {statistics.median(cli):7.3f} s  {min(cli):7.3f} s")


if __name__ == "__main__":
    main()
