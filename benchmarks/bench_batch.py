"""Benchmark: ``replay batch`` throughput on 100 synthetic scenes, local (1 and 2 workers)
and Ray.

Target (issue 7): the local engine with 2 workers at least 1.7x faster than with 1
worker, on 100 synthetic scenes of 50 agents over 5 s at 10 Hz.

What is timed: :func:`replay.batch.run_batch` into a fresh output folder, split into the
engine's part (starting the workers, replaying every scene into its tables, writing the
markers: ``run_seconds``) and the whole call (plus planning and the dataset statistics).
Scenes per second are scenes / engine time. The local pool's start-up (spawned
processes importing numpy, polars, ...) is inside the engine time; the Ray instance is
started once beforehand (its start-up is reported apart) and its worker processes start
inside the timed part, like the local pool's. The configurations take turns in every
repeat, so a load change on the (shared) machine hits all of them; medians are reported.

Usage::

    .venv/bin/python benchmarks/bench_batch.py [--scenes 100] [--agents 50]
        [--duration-s 5] [--repeat 3] [--no-ray]
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib
import resource
import shutil
import statistics
import tempfile
import time


def make_scenes(folder: pathlib.Path, n: int, agents: int, duration_s: float) -> int:
    """Write ``n`` synthetic scenes; returns the total number of frames."""
    from converters.scene.writer import write_scene
    from converters.synthetic import SyntheticSettings, generate_scene

    settings = SyntheticSettings(n_agents=agents, duration_s=duration_s, frame_period_s=0.1)
    frames = 0
    for i in range(n):
        scene = generate_scene(settings, seed=i)
        frames += len(scene.frames)
        write_scene(folder / f"scene_{i:04d}.mcap", scene)
    return frames


def one_run(
    inputs: pathlib.Path, out: pathlib.Path, engine: str, workers: int
) -> tuple[float, float, float]:
    """(engine seconds, total seconds, CPU seconds of the local worker processes) of one
    batch run into a fresh ``out``. The worker CPU time comes from ``getrusage`` of the
    reaped child processes, so it is NaN for Ray (its workers are the raylet's children)."""
    from replay.batch import BatchSettings, run_batch
    from risk.cascade import CascadeConfig

    shutil.rmtree(out, ignore_errors=True)
    settings = BatchSettings(cascade=CascadeConfig.default())
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    report = run_batch([inputs], out, settings, engine=engine, workers=workers, progress=False)
    total = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if report.failures or report.replayed == 0:
        raise SystemExit(f"benchmark run failed: {report.failures[:3]}")
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    return report.run_seconds, total, cpu if engine == "local" else math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", type=int, default=100)
    parser.add_argument("--agents", type=int, default=50)
    parser.add_argument("--duration-s", type=float, default=5.0)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--no-ray", action="store_true", help="skip the Ray engine")
    args = parser.parse_args()

    configs: list[tuple[str, str, int]] = [("local, 1 worker", "local", 1),
                                           ("local, 2 workers", "local", 2)]  # fmt: skip
    ray_start_s = None
    if not args.no_ray:
        try:
            import ray
        except ImportError:
            print("ray is not installed: Ray engine skipped (pip install 'riskreplay[ray]')")
        else:
            start = time.perf_counter()
            ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
            ray_start_s = time.perf_counter() - start
            configs.append(("ray, 2 CPUs", "ray", 2))

    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        root = pathlib.Path(tmp)
        inputs = root / "scenes"
        inputs.mkdir()
        start = time.perf_counter()
        frames = make_scenes(inputs, args.scenes, args.agents, args.duration_s)
        print(
            f"{args.scenes} synthetic scenes, {args.agents} agents, {args.duration_s:g} s at "
            f"10 Hz ({frames} frames) written in {time.perf_counter() - start:.1f} s; "
            f"{os.cpu_count()} CPUs (shared with other work: medians of {args.repeat} runs)"
        )
        if ray_start_s is not None:
            print(f"Ray instance start-up (not in the times below): {ray_start_s:.1f} s")
        times: dict[str, list[tuple[float, float]]] = {c[0]: [] for c in configs}
        for r in range(args.repeat):
            for label, engine, workers in configs:
                load_before = os.getloadavg()[0]
                run_s, total_s, cpu_s = one_run(inputs, root / "out", engine, workers)
                times[label].append((run_s, total_s))
                # How busy the shared machine was: the 1-minute load average, and how many
                # CPUs the workers got on average while the engine ran.
                share = "" if math.isnan(cpu_s) else f"  workers got {cpu_s / run_s:.2f} CPUs"
                print(f"  run {r + 1} {label:<17} engine {run_s:6.2f} s  total {total_s:6.2f} s"
                      f"  load {load_before:.1f} -> {os.getloadavg()[0]:.1f}{share}",
                      flush=True)  # fmt: skip

    print(f"\n{'configuration':<18}{'engine s':>10}{'scenes/s':>10}{'total s':>10}   all engine s")
    medians = {}
    for label, runs in times.items():
        run_med = statistics.median(r for r, _ in runs)
        total_med = statistics.median(t for _, t in runs)
        medians[label] = run_med
        every = ", ".join(f"{r:.1f}" for r, _ in runs)
        print(f"{label:<18}{run_med:10.2f}{args.scenes / run_med:10.2f}{total_med:10.2f}   {every}")
    speedup = medians["local, 1 worker"] / medians["local, 2 workers"]
    verdict = "meets" if speedup >= 1.7 else "MISSES"
    print(f"\nlocal speed-up 2 vs 1 worker: {speedup:.2f}x ({verdict} the 1.7x target)")
    if "ray, 2 CPUs" in medians:
        print(
            f"ray (2 CPUs) vs local 2 workers: {medians['local, 2 workers'] / medians['ray, 2 CPUs']:.2f}x"
        )


if __name__ == "__main__":
    main()
