"""Measure: the Lanelet2 map reader against Lanelet2's own routing graph and against the
hand-written OSM parser it replaced (taken from git history, commit 2788c9a).

For each map: lanelets read, the largest centre-line difference (m), how many lanelets'
successor sets differ from ``RoutingGraph.following`` (Germany, vehicle rules), and the
reading time (median of ``--repeat``).

Usage::

    .venv/bin/python benchmarks/lanelet2_vs_parser.py [MAP.osm ...] [--repeat 7]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import lanelet2
import numpy as np
from lanelet2.io import Origin
from lanelet2.projection import UtmProjector

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import interaction  # noqa: E402

DATA = Path(os.environ.get("RISKREPLAY_SHARED_DATA") or ROOT.parent / "shared" / "data")
MAPS = (
    DATA / "recorded" / "interaction" / "I_INTERACTION_0_USA.osm",
    DATA / "interaction" / "TestScenarioForScripts.osm",
)
OLD_COMMIT = "2788c9a"


def old_parser():
    """converters/interaction.py as it was before lanelet2 (its read_lane_map)."""
    text = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{OLD_COMMIT}:converters/interaction.py"],
        check=True, capture_output=True, text=True,
    ).stdout  # fmt: skip
    path = Path(tempfile.mkdtemp()) / "old_interaction.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("old_interaction", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.read_lane_map


def median_ms(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def compare(osm: Path, repeat: int) -> None:
    lmap, errors = lanelet2.io.loadRobust(str(osm), UtmProjector(Origin(0, 0)))
    rules = lanelet2.traffic_rules.create(
        lanelet2.traffic_rules.Locations.Germany, lanelet2.traffic_rules.Participants.Vehicle
    )
    graph = lanelet2.routing.RoutingGraph(lmap, rules)
    truth = {ll.id: sorted(x.id for x in graph.following(ll, False)) for ll in lmap.laneletLayer}
    print(f"{osm.name}: {len(truth)} lanelets in Lanelet2 ({len(errors)} load messages)")
    load_ms = median_ms(
        lambda: lanelet2.io.loadRobust(str(osm), UtmProjector(Origin(0, 0))), repeat
    )
    print(f"  lanelet2.io.loadRobust alone: {load_ms:.1f} ms")
    for name, reader in (("lanelet2 reader (now)", interaction.read_lane_map),
                         ("hand-written parser (before)", old_parser())):  # fmt: skip
        lanes = {lane.id: lane for lane in reader(osm).lanes if lane.id > 0}
        differ = sum(sorted(s for s in lanes[i].successors if s > 0) != t for i, t in truth.items())
        centre = [
            np.abs(lanes[ll.id].centerline - _centre(ll)).max()
            for ll in lmap.laneletLayer
            if lanes[ll.id].centerline.shape == _centre(ll).shape
        ]
        ms = median_ms(lambda reader=reader: reader(osm), repeat)
        print(
            f"  {name:30s} {len(lanes)} lanelets, centre lines within {max(centre):.1e} m, "
            f"successor sets differing from the routing graph: {differ}, {ms:.1f} ms"
        )


def _centre(ll) -> np.ndarray:
    left = np.array([(p.x, p.y) for p in ll.leftBound])
    right = np.array([(p.x, p.y) for p in ll.rightBound])
    return interaction.lanelet_centerline(left, right)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("maps", nargs="*", type=Path)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    for osm in args.maps or [m for m in MAPS if m.is_file()]:
        compare(osm, args.repeat)


if __name__ == "__main__":
    main()
