"""Benchmark: converting a 100-agent, 15 s recorded scene (goal: at most 1 s).

Two inputs, each converted in process (read, tracks, moving ego, map paths, frames, MCAP
write), medians over ``--repeat`` runs:

- a generated CommonRoad file: 100 vehicles on a 4-lane, 600 m road of 20 m lanelets
  (120 lanelets with successor links), 150 steps at 10 Hz (15 s), each vehicle present
  for the whole scene at 5-30 m/s: what the corpus's highD and exiD files look like, at
  the size of the goal;
- the largest MONA file of the shared corpus (89 vehicles, 16 s at 5 Hz), when present;
- the INTERACTION recording with both track CSVs (97 tracks, 300 s), when present.

Usage::

    .venv/bin/python benchmarks/bench_convert_scene.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters.scene.writer import write_scene  # noqa: E402
from converters.sources import SOURCES, ReadOptions, SourceInput  # noqa: E402
from converters.tracks import Skipped  # noqa: E402

CORPUS = (
    Path(os.environ.get("RISKREPLAY_SHARED_DATA") or ROOT.parent / "shared" / "data") / "recorded"
)


def _pts(*xy: tuple[float, float]) -> str:
    return "".join(f"<point><x>{x:.3f}</x><y>{y:.3f}</y></point>" for x, y in xy)


def commonroad_xml(n_agents: int = 100, steps: int = 150, dt: float = 0.1) -> str:
    """A CommonRoad 2020a scenario: ``n_agents`` vehicles on a straight 4-lane road."""
    rng = np.random.default_rng(0)
    parts = [f'<commonRoad timeStepSize="{dt}" commonRoadVersion="2020a" benchmarkID="B-1">']
    seg, n_seg, width = 20.0, 30, 3.5
    for lane in range(4):
        y0 = lane * width
        for k in range(n_seg):
            lid = 1000 * (lane + 1) + k
            x0, x1 = k * seg, (k + 1) * seg
            succ = f'<successor ref="{lid + 1}"/>' if k + 1 < n_seg else ""
            parts.append(
                f'<lanelet id="{lid}"><leftBound>{_pts((x0, y0 + width), (x1, y0 + width))}'
                f"</leftBound><rightBound>{_pts((x0, y0), (x1, y0))}</rightBound>{succ}"
                "</lanelet>"
            )
    for i in range(n_agents):
        lane = i % 4
        v = rng.uniform(5, 30)
        x0 = rng.uniform(0, 150)
        y = lane * width + width / 2
        states = "".join(
            f"<state><position><point><x>{x0 + v * t * dt:.3f}</x><y>{y:.3f}</y></point>"
            f"</position><orientation><exact>0</exact></orientation><time><exact>{t}</exact>"
            f"</time><velocity><exact>{v:.3f}</exact></velocity></state>"
            for t in range(1, steps)
        )
        parts.append(
            f'<dynamicObstacle id="{10000 + i}"><type>car</type><shape><rectangle>'
            "<length>4.5</length><width>1.9</width></rectangle></shape><initialState>"
            f"<position><point><x>{x0:.3f}</x><y>{y:.3f}</y></point></position>"
            "<orientation><exact>0</exact></orientation><time><exact>0</exact></time>"
            f"<velocity><exact>{v:.3f}</exact></velocity></initialState>"
            f"<trajectory>{states}</trajectory></dynamicObstacle>"
        )
    parts.append("</commonRoad>")
    return "\n".join(parts)


def time_input(inp: SourceInput, repeat: int, out: Path) -> tuple[list[float], list[float], str]:
    """Wall-clock and CPU seconds (this process) per run: on a shared machine the CPU
    time says what the conversion costs, the wall time what a user waits."""
    spec = SOURCES[inp.source]
    times, cpu = [], []
    what = ""
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        [(_, build)] = list(spec.scenes(inp, ReadOptions(), Skipped()))
        scene = build()
        write_scene(out / "s.mcap", scene)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        f = scene.frames
        span = f[-1].t - f[0].t
        what = f"{f[0].n_agents} agents, {len(f)} frames ({span:.1f} s)"
    return times, cpu, what


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        xml = out / "generated_100.xml"
        xml.write_text(commonroad_xml())
        cases = [("generated CommonRoad", SourceInput(source="commonroad", path=xml))]
        mona = CORPUS / "mona" / "C-DEU_MONAEast-2_320_T-399.xml"
        if mona.is_file():
            cases.append(("MONA (corpus)", SourceInput(source="commonroad", path=mona)))
        inter = CORPUS / "interaction"
        if inter.is_dir():
            cases.append(
                (
                    "INTERACTION, 2 CSVs (corpus)",
                    SourceInput(
                        source="interaction",
                        path=inter / "vehicle_tracks_000.csv",
                        extra=(inter / "pedestrian_tracks_000.csv",),
                        map=inter / "I_INTERACTION_0_USA.osm",
                    ),
                )
            )
        for name, inp in cases:
            times, cpu, what = time_input(inp, args.repeat, out)
            print(
                f"{name:30s} {what:40s} median {statistics.median(times):.3f} s wall "
                f"(min {min(times):.3f}), {statistics.median(cpu):.3f} s CPU, "
                f"{args.repeat} runs"
            )


if __name__ == "__main__":
    main()
