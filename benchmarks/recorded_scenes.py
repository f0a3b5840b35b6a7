"""Recorded scenes for the benchmarks: CommonRoad files of ../shared/data/recorded
converted with the command line into a folder, loaded, and their moving vehicles."""

from __future__ import annotations

import pathlib
import subprocess
import sys
from collections.abc import Iterable, Iterator
from typing import Any

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from replay.core.egos import load_scene  # noqa: E402
from risk import Kind  # noqa: E402

RECORDED = ROOT.parent / "shared" / "data" / "recorded"


def converted(
    sources: Iterable[pathlib.Path], folder: pathlib.Path
) -> Iterator[tuple[pathlib.Path, Any]]:
    """Each source that exists and its scene, converted with ``python -m replay convert
    commonroad`` into ``folder`` and loaded (a missing one is named on stderr, skipped)."""
    for source in sources:
        if not source.is_file():
            print(f"skipped (not found): {source}", file=sys.stderr)
            continue
        target = folder / f"{source.stem}.mcap"
        subprocess.run(
            [sys.executable, "-m", "replay", "convert", "commonroad", str(source), "-o", str(target)],
            check=True, capture_output=True,
        )  # fmt: skip
        yield source, load_scene(target)


def moving_vehicles(scene: Any, min_speed_mps: float = 1.0) -> list[int]:
    """Ids of the vehicles moving faster than ``min_speed_mps`` in the scene's first frame."""
    first = scene.indexed[0][1]
    return [int(i) for i, k, v in zip(first.ids, first.kinds, first.speed, strict=True)
            if k == Kind.VEHICLE and v > min_speed_mps]  # fmt: skip
