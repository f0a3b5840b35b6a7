"""Speed of the nine risk models per frame, and the speed-up over the slow reference.

Usage::

    .venv/bin/python benchmarks/bench_models.py            # full table (about 2-3 min)
    .venv/bin/python benchmarks/bench_models.py --quick    # fewer repeats, N up to 300

Frames are random but realistic: a two-road intersection with lanes in both directions
and turning lanes (centre lines with a point every 1.5 m), agents placed on lanes with
150 m forward paths, speeds 0-25 m/s (one in ten standing), a few pedestrians on
crosswalks. Prediction T = 12 s, dt = 0.1 s (121 steps).

Each model is timed alone through ``evaluate(frame, [name])`` (so it pays for the shared
work it needs), and all nine together through ``evaluate(frame)`` (shared work once).
Times are medians over repeats and over several frames, as wall time and as CPU time
(the machine is shared; CPU time leaves out waiting for a core). The reference
(risk/reference.py) is timed at small N on the same frames (it grows like N, with a
150 x 150 segment loop per agent, so N = 10 and 30 take seconds); the speed-up is the
ratio of the reference's wall time to ``evaluate``'s on the same frame.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from risk import MODELS, Frame, PredictionSettings, evaluate
from risk.reference import reference_evaluate

SPACING_M = 1.5
PATH_LENGTH_M = 150.0


def _resample(poly: np.ndarray, spacing: float) -> np.ndarray:
    seg = np.hypot(*np.diff(poly, axis=0).T)
    cum = np.r_[0.0, np.cumsum(seg)]
    s = np.arange(0.0, cum[-1], spacing)
    return np.column_stack([np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])])


def intersection_lanes() -> list[np.ndarray]:
    """Lane centre lines of a four-way intersection, each about 400 m long."""
    half = 1.75
    lanes = []
    far = 200.0
    # Straight lanes in both directions on two crossing roads, two lanes per direction.
    for off in (half, 3 * half):
        lanes.append(np.array([[-far, -off], [far, -off]]))  # eastbound
        lanes.append(np.array([[far, off], [-far, off]]))  # westbound
        lanes.append(np.array([[off, -far], [off, far]]))  # northbound
        lanes.append(np.array([[-off, far], [-off, -far]]))  # southbound
    # Right and left turns: straight approach, quarter circle, straight exit.
    theta = np.linspace(0, np.pi / 2, 20)
    for r, sign in ((8.0, 1), (12.0, -1)):
        arc = np.column_stack([r * np.sin(theta), sign * r * (1 - np.cos(theta))])
        for rot in range(4):
            c, s = np.cos(rot * np.pi / 2), np.sin(rot * np.pi / 2)
            rmat = np.array([[c, -s], [s, c]])
            start = np.array([-r - 5.0, -half * sign])
            exit_dir = np.array([0.0, sign])
            pts = np.vstack(
                [
                    start + np.array([-far, 0.0]),
                    start + arc,
                    start + arc[-1] + exit_dir * far,
                ]
            )
            lanes.append(pts @ rmat.T)
    return [_resample(lane, SPACING_M) for lane in lanes]


def random_frame(n_agents: int, rng: np.random.Generator) -> Frame:
    """``n_agents`` agents (the first is the ego) on the intersection's lanes."""
    lanes = intersection_lanes()
    xy, heading, paths, kinds = [], [], [], []
    for _ in range(n_agents):
        pedestrian = rng.random() < 0.05
        if pedestrian:
            # A crosswalk: 14 m across one road, walked in either direction.
            x0 = rng.choice([-15.0, 15.0])
            a, b = np.array([x0, -7.0]), np.array([x0, 7.0])
            if rng.random() < 0.5:
                a, b = b, a
            path = _resample(np.vstack([a, b]), SPACING_M)
            start = rng.integers(0, len(path) - 1)
            path = path[start:]
            kinds.append("pedestrian")
        else:
            lane = lanes[rng.integers(len(lanes))]
            n_pts = int(PATH_LENGTH_M / SPACING_M) + 1
            start = rng.integers(0, len(lane) - n_pts)
            path = lane[start : start + n_pts]
            kinds.append("vehicle" if rng.random() < 0.9 else "cyclist")
        d = path[1] - path[0] if len(path) > 1 else np.array([1.0, 0.0])
        xy.append(path[0])
        heading.append(np.arctan2(d[1], d[0]))
        paths.append(path)
    kinds_a = np.array(kinds)
    speed = np.where(
        kinds_a == "pedestrian", rng.uniform(0.5, 2.0, n_agents), rng.uniform(0, 25, n_agents)
    )
    speed[rng.random(n_agents) < 0.1] = 0.0
    length = np.where(kinds_a == "vehicle", 4.5, np.where(kinds_a == "cyclist", 1.8, 0.5))
    width = np.where(kinds_a == "vehicle", 1.9, np.where(kinds_a == "cyclist", 0.6, 0.5))
    return Frame.from_arrays(
        np.array(xy), np.array(heading), speed, length, width, paths, ego=0, kinds=kinds
    )


def _time(fn, repeats: int) -> tuple[float, float]:
    """Median wall time and median CPU time of ``fn()``, in seconds.

    CPU time (``time.process_time``) leaves out the time the process waits for a core,
    so it stays meaningful when other work shares the machine; wall time is what a user
    waits. The report gives both.
    """
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return statistics.median(wall), statistics.median(cpu)


def _table(title: str, sizes: list[int], names: list[str], table: dict, which: int) -> None:
    print(title)
    print()
    print("| model | " + " | ".join(f"N={n}" for n in sizes) + " |")
    print("|---|" + "---:|" * len(sizes))
    for name in names:
        cells = " | ".join(f"{1e3 * table[n][name][which]:.2f}" for n in sizes)
        label = f"**{name}**" if name == "all nine" else name
        print(f"| {label} | {cells} |")
    print()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats, N up to 300")
    ap.add_argument("--frames", type=int, default=3, help="random frames per N (default 3)")
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)

    sizes = [10, 30, 100, 300] if args.quick else [10, 30, 100, 300, 1000]
    repeats = 3 if args.quick else 7
    settings = PredictionSettings(horizon_s=12.0, dt_s=0.1)
    rng = np.random.default_rng(args.seed)
    frames = {n: [random_frame(n, rng) for _ in range(args.frames)] for n in sizes}
    for fr in frames.values():  # warm-up (imports, first allocations)
        evaluate(fr[0], prediction=settings)

    names = [*MODELS, "all nine"]
    load_before = os.getloadavg()[0]
    table: dict[int, dict[str, tuple[float, float]]] = {}
    for n in sizes:
        row = {}
        for name in names:
            models = None if name == "all nine" else [name]
            per_frame = [
                _time(lambda f=f, m=models: evaluate(f, m, prediction=settings), repeats)
                for f in frames[n]
            ]
            row[name] = (
                statistics.median(w for w, _ in per_frame),
                statistics.median(c for _, c in per_frame),
            )
        table[n] = row
        print(f"  measured N={n}", file=sys.stderr)
    load_after = os.getloadavg()[0]

    setup = (
        f"median of {repeats} runs x {args.frames} frames; T = 12 s, dt = 0.1 s, 150 m paths, "
        f"{SPACING_M} m point spacing"
    )
    print(
        f"Load average (1 min) on this {os.cpu_count()}-core machine: {load_before:.1f} before, "
        f"{load_after:.1f} after."
    )
    print()
    _table(f"Wall time per frame in ms ({setup})", sizes, names, table, 0)
    _table(f"CPU time per frame in ms ({setup})", sizes, names, table, 1)
    small, big = sizes[2], sizes[-1]
    for label, which in (("wall", 0), ("CPU", 1)):
        growth = table[big]["all nine"][which] / table[small]["all nine"][which]
        print(
            f"All nine, {label} time, N={small} -> N={big} ({big // small}x agents): {growth:.1f}x"
        )

    ref_sizes = [10] if args.quick else [10, 30]
    print()
    print("Speed-up over risk/reference.py (the same frame, all nine models; reference run once):")
    print()
    print("| N | reference (s) | evaluate (ms) | speed-up |")
    print("|---:|---:|---:|---:|")
    for n in ref_sizes:
        f = frames[n][0]
        t_ref = _time(lambda f=f: reference_evaluate(f, prediction=settings), 1)[0]
        t_vec = _time(lambda f=f: evaluate(f, prediction=settings), repeats)[0]
        print(f"| {n} | {t_ref:.2f} | {1e3 * t_vec:.2f} | {t_ref / t_vec:.0f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
