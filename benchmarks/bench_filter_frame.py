"""``risk.filter_frame`` per call on real frames: its wall time against the filter's own.

Usage::

    .venv/bin/python benchmarks/bench_filter_frame.py            # 2 scenes, 5 rounds
    .venv/bin/python benchmarks/bench_filter_frame.py --rounds 2

The scenes: two NGSIM Lankershim scenes of ../shared/data/recorded (an urban arterial
with up to 73 agents), converted with ``python -m replay convert commonroad FILE -o
x.mcap`` into a temporary folder; every moving vehicle as the ego, one frame per second.

Each frame is filtered in turns by the shipped cascade as ``filter_frame`` runs it
(``CascadeFilter``: no survival on all agents), as ``replay plan``'s planners get it
(``tiers=False``: no survival of the survivors either) and with the comparison
(``CascadeFilter(baseline=True)``, what ``filter_frame`` did before), round after round,
so that the shared machine's slow spells fall on both alike. The table gives medians of
the call's wall time, of the filter's own time (``FilterResult.time_ms``: the corridor,
the bound, the stages and the tier sort) of each, and of the agents kept, by agent
count. Results
are appended, dated, to ``benchmarks/results/filter_frame.md``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import pathlib
import platform
import statistics
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from recorded_scenes import RECORDED, converted, moving_vehicles  # noqa: E402

from replay.analysis.planner_eval.open_loop import ego_frames  # noqa: E402
from replay.core.engine import Stride  # noqa: E402
from risk import CascadeConfig, Frame  # noqa: E402
from risk.filtering import CascadeFilter  # noqa: E402

SCENES = (
    RECORDED / "ngsim" / "USA_Lanker-1_1_T-1.xml",
    RECORDED / "ngsim" / "USA_Lanker-2_13_T-1.xml",
)
RESULTS = ROOT / "benchmarks" / "results" / "filter_frame.md"
BINS = ((0, 9), (10, 24), (25, 49), (50, 1000))


def frames(folder: pathlib.Path) -> list[Frame]:
    found: list[Frame] = []
    for _, scene in converted(SCENES, folder):
        egos = moving_vehicles(scene)
        found += [frame for _, _, frame in ego_frames(scene, egos, Stride(seconds=1.0))]
    return found


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        found = frames(pathlib.Path(tmp))
    if not found:
        print("Error: no scene found under ../shared/data/recorded/ngsim", file=sys.stderr)
        return 1
    config = CascadeConfig.default()
    filters = {
        "filter_frame": CascadeFilter(config),
        "without tiers": CascadeFilter(config, tiers=False),
        "with baseline": CascadeFilter(config, baseline=True),
    }
    for f in filters.values():  # warm-up: compiled kernels, parsed settings
        for frame in found[:5]:
            f.apply(frame)
    wall: dict[str, list[list[float]]] = {name: [[] for _ in found] for name in filters}
    own: dict[str, list[list[float]]] = {name: [[] for _ in found] for name in filters}
    kept = [0] * len(found)
    for _ in range(args.rounds):
        for i, frame in enumerate(found):
            for name, f in filters.items():
                start = time.perf_counter()
                answer = f.apply(frame)
                wall[name][i].append((time.perf_counter() - start) * 1e3)
                own[name][i].append(answer.time_ms)
                kept[i] = answer.n_kept
    n_others = [int(frame.others.sum()) for frame in found]

    def median_of(values: list[list[float]], rows: list[int]) -> float:
        return statistics.median(statistics.median(values[i]) for i in rows)

    lines = [
        "",
        f"## {datetime.date.today().isoformat()}",
        "",
        f"`python benchmarks/bench_filter_frame.py --rounds {args.rounds}` ({platform.machine()}, "
        f"{os.cpu_count()} CPUs shared with other work, load {os.getloadavg()[0]:.1f}, Python "
        f"{platform.python_version()}); {len(found)} ego-frames of {len(SCENES)} NGSIM "
        "Lankershim scenes. Medians per frame over the rounds, then over the frames, ms.",
        "",
        "| others | ego-frames | kept | filter_frame wall | own time | without tiers wall | "
        "own time | with baseline wall | own time |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for lo, hi in (*BINS, (0, 1000)):
        rows = [i for i, n in enumerate(n_others) if lo <= n <= hi]
        if not rows:
            continue
        label = "all" if (lo, hi) == (0, 1000) else f"{lo}-{hi}" if hi < 1000 else f"{lo}+"
        lines.append(
            f"| {label} | {len(rows)} | {statistics.median(kept[i] for i in rows):.0f} | "
            + " | ".join(
                f"{median_of(times[name], rows):.3f}" for name in filters for times in (wall, own)
            )
            + " |"
        )
    text = "\n".join(lines) + "\n"
    print(text)
    if not RESULTS.exists():
        RESULTS.write_text("# `filter_frame` per call on real frames\n")
    with RESULTS.open("a") as out:
        out.write(text)
    print(f"Appended to {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
