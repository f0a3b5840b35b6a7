"""Benchmark: writing the Rerun recording of a 100-agent, 100-frame replay.

Target (issue 4): the recording, with all nine risk timelines, in well under 1.25 s
(a quarter of the 5 s end-to-end budget of ``replay run``).

The replay itself runs once, outside the timing: a synthetic intersection scene
(``converters.synthetic``, 100 agents besides the ego, 10 s at 10 Hz) through the engine
with every model and the cascade; its per-frame results are kept in memory. Then the
recorder writes them ``--repeat`` times, each into a fresh file: ``begin`` + ``add`` per
frame (what the recorder does while the replay runs) and ``close`` (everything is
written here), timed separately. The machine is shared, so medians are reported.

Usage::

    .venv/bin/python benchmarks/bench_recording.py [--repeat 7] [--agents 100] [--seed 0]
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import tempfile
import time


class _Collect:
    """A sink that keeps every result in memory (to replay them into the recorder)."""

    def __init__(self) -> None:
        self.info = None
        self.results: list = []

    def begin(self, info) -> None:
        self.info = info

    def add(self, result) -> None:
        self.results.append(result)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


def replay_results(agents: int, seed: int) -> _Collect:
    """Run the engine once on a synthetic scene and keep its results."""
    from converters.synthetic import SyntheticSettings, generate_scene
    from replay.core.engine import run_scene
    from risk.cascade import DEFAULT_CASCADE_PATH, CascadeConfig, Stage, Tier

    scene = generate_scene(SyntheticSettings(n_agents=agents + 1, duration_s=10.0), seed=seed)
    if DEFAULT_CASCADE_PATH.is_file():
        cascade = CascadeConfig.default()
    else:  # before the calibrated default ships: the paper's three stages, loose thresholds
        cascade = CascadeConfig(
            stages=(
                Stage("path_distance", 0.1),
                Stage("trajectory_distance", 0.1),
                Stage("gaussian", 1e-12),
            ),
            tiers=(Tier("behavior", 1e-25), Tier("interactive", 1e-8), Tier("cooperative", 1e-3)),
        )
    sink = _Collect()
    run_scene(scene, sinks=[sink], cascade=cascade, progress=False)
    return sink


def record_once(data: _Collect, out: pathlib.Path, labels: str) -> tuple[float, float]:
    """Write one recording; returns (seconds in begin + add, seconds in close)."""
    from recordings import SceneRecorder

    rec = SceneRecorder(out, labels=labels)  # type: ignore[arg-type]
    start = time.perf_counter()
    rec.begin(data.info)
    for result in data.results:
        rec.add(result)
    mid = time.perf_counter()
    rec.close()
    return mid - start, time.perf_counter() - mid


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--agents", type=int, default=100, help="agents besides the ego")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--labels", default="kept", choices=("kept", "all", "none"))
    args = ap.parse_args()

    data = replay_results(args.agents, args.seed)
    n_frames = len(data.results)
    n_agents = max(r.frame.n_agents for r in data.results)
    print(f"scene: {n_frames} frames, up to {n_agents} agents (ego included), "
          f"{len(data.info.model_names)} models")  # fmt: skip
    adds, closes, totals = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeat):
            out = pathlib.Path(tmp) / f"bench{k}.rrd"
            add_s, close_s = record_once(data, out, args.labels)
            adds.append(add_s)
            closes.append(close_s)
            totals.append(add_s + close_s)
        size_mb = out.stat().st_size / 1e6
    med = statistics.median
    print(f"recording ({args.repeat} runs, median [min-max]):")
    print(f"  begin + add x{n_frames}: {med(adds):.3f} s [{min(adds):.3f}-{max(adds):.3f}]")
    print(f"  close (all writing):  {med(closes):.3f} s [{min(closes):.3f}-{max(closes):.3f}]")
    print(f"  total:                {med(totals):.3f} s [{min(totals):.3f}-{max(totals):.3f}]"
          f"   (target: well under 1.25 s)")  # fmt: skip
    print(f"  file size: {size_mb:.1f} MB")


if __name__ == "__main__":
    main()
