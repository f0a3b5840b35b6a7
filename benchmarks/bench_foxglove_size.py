"""Measure: how much the optional foxglove.SceneUpdate channels grow a scene file.

Issue 15 asks for the channels behind an option when they grow a file by more than 30 %.
Each given scene is read and written twice, without and with the channels (same data,
same writer), and the sizes and write times are printed.

Usage::

    .venv/bin/python benchmarks/bench_foxglove_size.py SCENE.mcap [SCENE.mcap ...]
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

from converters.scene.reader import read_scene
from converters.scene.writer import write_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", nargs="+", type=pathlib.Path)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.scenes:
            scene = read_scene(path)
            sizes, times = [], []
            for foxglove in (False, True):
                out = pathlib.Path(tmp) / f"{foxglove}.mcap"
                start = time.perf_counter()
                write_scene(out, scene, foxglove=foxglove)
                times.append(time.perf_counter() - start)
                sizes.append(out.stat().st_size)
            growth = 100.0 * (sizes[1] - sizes[0]) / sizes[0]
            print(
                f"{path}: {sizes[0]} B ({times[0]:.2f} s) -> with Foxglove channels "
                f"{sizes[1]} B ({times[1]:.2f} s): +{growth:.0f} %"
            )


if __name__ == "__main__":
    main()
