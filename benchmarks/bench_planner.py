"""Plan time against the number of obstacles, for each planner of replay.planning.

Usage::

    .venv/bin/python benchmarks/bench_planner.py            # 0, 10, 50, 100 obstacles
    .venv/bin/python benchmarks/bench_planner.py --quick    # fewer frames and repeats

The scene: a straight road along +x with three lanes in the ego's direction (the ego in the
middle one at 10 m/s, target speed 12 m/s, so one usable lane on each side) and two
oncoming lanes. Obstacles are vehicles on random lanes between x = -100 and 400 m at 0-15
m/s (one in five standing; the ego's lane is kept clear for 30 m ahead so that a plan
exists), predicted with the toolkit's constant-speed prediction over 5 s at 0.1 s.

Every (frame, planner) is timed in turns (round robin over the planners, repeated), so
that the shared machine's slow spells fall on every planner alike; the table gives
medians of the wall time of ``planner.plan`` (for the Frenet planners also fiss-planner's
own ``stats.time_ms``) and of building the request (``plan_request``) and of
``may_matter``. The results go to ``benchmarks/results/planner.md``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from replay.planning import available_planners, make_planner, plan_request
from risk import Frame, Lane, LaneMap

LANE_WIDTH_M = 3.5
FORWARD_Y = (-LANE_WIDTH_M, 0.0, LANE_WIDTH_M)
ONCOMING_Y = (2 * LANE_WIDTH_M, 3 * LANE_WIDTH_M)
ROAD_X = (-200.0, 800.0)
RESULTS = Path(__file__).resolve().parent / "results" / "planner.md"


def road_map() -> LaneMap:
    x = np.linspace(*ROAD_X, 201)
    lanes = [Lane(i, np.stack([x, np.full_like(x, y)], 1)) for i, y in enumerate(FORWARD_Y)]
    lanes += [
        Lane(10 + i, np.stack([x[::-1], np.full_like(x, y)], 1)) for i, y in enumerate(ONCOMING_Y)
    ]
    return LaneMap(tuple(lanes))


def random_frame(n_obstacles: int, rng: np.random.Generator) -> Frame:
    ys = np.array(FORWARD_Y + ONCOMING_Y)
    lane = rng.integers(0, ys.size, n_obstacles)
    x = rng.uniform(-100.0, 400.0, n_obstacles)
    clear = (ys[lane] == 0.0) & (x > -8.0) & (x < 30.0)  # keep the ego's lane clear ahead
    x[clear] += 40.0
    forward = lane < len(FORWARD_Y)
    heading = np.where(forward, 0.0, np.pi)
    speed = rng.uniform(0.0, 15.0, n_obstacles)
    speed[rng.random(n_obstacles) < 0.2] = 0.0
    xy = np.vstack([[0.0, 0.0], np.stack([x, ys[lane]], 1)])
    end = np.where(forward, ROAD_X[1], ROAD_X[0])
    paths = [np.array([[0.0, 0.0], [ROAD_X[1], 0.0]])]
    paths += [np.array([[a, b], [e, b]]) for a, b, e in zip(x, ys[lane], end, strict=True)]
    return Frame.from_arrays(
        xy=xy,
        heading=np.r_[0.0, heading],
        speed=np.r_[10.0, speed],
        length=np.full(n_obstacles + 1, 4.5),
        width=np.full(n_obstacles + 1, 1.8),
        paths=paths,
        ego=0,
    )


def _ms(fn) -> float:
    start = time.perf_counter()
    fn()
    return (time.perf_counter() - start) * 1e3


def run(counts: list[int], frames: int, repeats: int, seed: int = 0) -> dict:
    names = list(available_planners())
    planners = {name: make_planner(name) for name in names}
    lane_map = road_map()
    rng = np.random.default_rng(seed)
    out: dict = {}
    for n in counts:
        wall: dict[str, list[float]] = {name: [] for name in names}
        cpu: dict[str, list[float]] = {name: [] for name in names}
        core: dict[str, list[float]] = {name: [] for name in names}
        may: dict[str, list[float]] = {name: [] for name in names}
        ok: dict[str, list[bool]] = {name: [] for name in names}
        build: list[float] = []
        for _ in range(frames):
            frame = random_frame(n, rng)
            request = plan_request(frame, lane_map, target_speed_mps=12.0)
            build.append(_ms(lambda f=frame: plan_request(f, lane_map, target_speed_mps=12.0)))
            for name in names:  # warm: the first call of a planner sets it up
                planners[name].plan(request)
            for _ in range(repeats):
                for name in names:  # in turns
                    planner = planners[name]
                    start, start_cpu = time.perf_counter(), time.process_time()
                    plan = planner.plan(request)
                    wall[name].append((time.perf_counter() - start) * 1e3)
                    cpu[name].append((time.process_time() - start_cpu) * 1e3)
                    core[name].append(plan.extras.get("core_ms", float("nan")))
                    ok[name].append(plan.ok)
                    may[name].append(_ms(lambda p=planner, r=request: p.may_matter(r)))
        out[n] = {
            "build_ms": statistics.median(build),
            **{
                name: {
                    "wall_ms": statistics.median(wall[name]),
                    "cpu_ms": statistics.median(cpu[name]),
                    "core_ms": statistics.median(core[name]),
                    "may_matter_ms": statistics.median(may[name]),
                    "ok_share": float(np.mean(ok[name])),
                }
                for name in names
            },
        }
        print(
            f"{n:4d} obstacles: "
            + ", ".join(f"{name} {out[n][name]['wall_ms']:.2f} ms" for name in names),
            flush=True,
        )
    return {"names": names, "rows": out}


def write(result: dict, *, counts: list[int], frames: int, repeats: int, command: str) -> None:
    names = result["names"]
    lines = [
        "# Plan time against the number of obstacles",
        "",
        f"Written by `benchmarks/bench_planner.py` on {datetime.date.today().isoformat()} "
        f"({platform.machine()}, {os.cpu_count()} CPUs shared with other work, Python "
        f"{platform.python_version()}). Command: `{command}`.",
        "",
        f"Straight road (three lanes in the ego's direction, two oncoming); {frames} random "
        f"frames per obstacle count, each planner timed {repeats} times per frame in turns. "
        "Medians of the wall time of `planner.plan(request)` in ms, and of its CPU time "
        "(`cpu`: the process's, which leaves out waiting for a shared core; for fiss-planner the "
        "adapter's obstacle conversion is included; `core` is fiss-planner's own "
        "`stats.time_ms`). `request` is building the request from the frame "
        "(`plan_request`: reference, side lanes, forecasts); `may_matter` the skip test of "
        "issue 28. `ok` the share of plans found.",
        "",
    ]
    head = (
        "| obstacles | request ms | "
        + " | ".join(
            f"{n} ms | {n} cpu ms"
            + (f" | {n} core ms" if n != "idm" else "")
            + f" | {n} may_matter ms | {n} ok"
            for n in names
        )
        + " |"
    )
    lines.append(head)
    lines.append("|" + "---:|" * (head.count("|") - 1))
    for n in counts:
        row = result["rows"][n]
        cells = [str(n), f"{row['build_ms']:.2f}"]
        for name in names:
            r = row[name]
            cells += [f"{r['wall_ms']:.2f}", f"{r['cpu_ms']:.2f}"]
            if name != "idm":
                cells.append(f"{r['core_ms']:.2f}")
            cells += [f"{r['may_matter_ms']:.2f}", f"{r['ok_share']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    tmp = RESULTS.with_suffix(".tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tmp.replace(RESULTS)
    print(f"wrote {RESULTS}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 frames x 3 repeats")
    parser.add_argument("--counts", default="0,10,50,100")
    args = parser.parse_args()
    counts = [int(c) for c in args.counts.split(",")]
    frames, repeats = (3, 3) if args.quick else (8, 7)
    command = "python " + " ".join([Path(sys.argv[0]).as_posix(), *sys.argv[1:]])
    result = run(counts, frames, repeats)
    write(result, counts=counts, frames=frames, repeats=repeats, command=command)


if __name__ == "__main__":
    main()
