"""Benchmark: ``replay run`` end to end on a 100-agent, 10 s, 10 Hz synthetic scene.

Targets (issue 4): at most 5 s in total, of which the Rerun writing at most a quarter.

Two measurements, each repeated (the machine is shared, so medians are reported):

- **end to end**: the ``replay run SCENE --table T`` command as a user runs it, in a
  fresh process (interpreter start and imports included), wall-clock;
- **breakdown**: the same replay in-process via ``run_scene``, split into reading the
  MCAP, all nine models on all agents (timelines), the cascade (its stages, the survival
  sort and survival analysis on all agents), the Rerun recording and the table.

Usage::

    .venv/bin/python benchmarks/bench_replay.py [--repeat 5] [--agents 100] [--seed 7]
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import subprocess
import sys
import tempfile
import time

from replay.core.scene_run import DEMO_SEED


def make_scene(folder: pathlib.Path, agents: int, seed: int) -> pathlib.Path:
    from converters.scene.writer import write_scene
    from replay.core.scene_run import demo_scene

    return write_scene(folder / "bench.mcap", demo_scene(n_agents=agents, seed=seed))


def end_to_end(scene: pathlib.Path) -> float:
    replay = pathlib.Path(sys.executable).with_name("replay")
    cmd = [str(replay), "run", str(scene), "--table", str(scene.with_suffix(".parquet")),
           "--no-progress"]  # fmt: skip
    start = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - start


def breakdown(scene: pathlib.Path) -> dict[str, float]:
    from recordings import SceneRecorder
    from replay.core.engine import run_scene
    from replay.core.tables import TableSink

    sinks = [SceneRecorder(scene.with_suffix(".rrd")), TableSink(scene.with_suffix(".parquet"))]
    start = time.perf_counter()
    s = run_scene(scene, sinks=sinks, progress=False)
    total = time.perf_counter() - start
    return {
        "total (in-process)": total,
        "read": s.read_time_s,
        "models (8 on all agents; survival is in cascade)": s.models_time_s,
        "cascade (stages+sort+survival on all)": s.cascade_time_s,
        "  stages": sum(s.stage_time_s),
        "  sort (survival on survivors)": s.sort_time_s,
        "  survival on all agents": s.survival_all_time_s,
        "recording (SceneRecorder)": s.sink_time_s.get("SceneRecorder", 0.0),
        "table (TableSink)": s.sink_time_s.get("TableSink", 0.0),
        "frames": s.frames,
        "mean others": s.mean_others,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--seed", type=int, default=DEMO_SEED, help="default: the demo's")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scene = make_scene(pathlib.Path(tmp), args.agents, args.seed)
        e2e = [end_to_end(scene) for _ in range(args.repeat)]
        parts = [breakdown(scene) for _ in range(args.repeat)]
    print(f"scene: {args.agents} agents, 10 s at 10 Hz, seed {args.seed}; "
          f"{args.repeat} runs, medians (min-max)")  # fmt: skip
    print(f"  {'replay run, end to end (new process)':<50}{_stat(e2e)}")
    for key in parts[0]:
        values = [p[key] for p in parts]
        if key in ("frames", "mean others"):
            print(f"  {key:<50}{statistics.median(values):.1f}")
        else:
            print(f"  {key:<50}{_stat(values)}")
    rec = statistics.median(p["recording (SceneRecorder)"] for p in parts)
    total = statistics.median(e2e)
    print(f"recording share of end to end: {100 * rec / total:.1f} % (target <= 25 %); "
          f"end to end {total:.2f} s (target <= 5 s)")  # fmt: skip


def _stat(values: list[float]) -> str:
    return f"{statistics.median(values):7.3f} s  ({min(values):.3f}-{max(values):.3f})"


if __name__ == "__main__":
    main()
