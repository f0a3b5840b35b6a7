"""The planner in the loop: what the cascade saves a real planner, and how long the loops take.

Usage::

    .venv/bin/python benchmarks/bench_planner_loop.py                 # dense + closed loop
    .venv/bin/python benchmarks/bench_planner_loop.py --corpus DIR... # + the corpus open loop

Three goals of issue 32, each measured with the library calls ``replay plan`` makes:

1. **Dense scenes** (50 or more other agents): the cascade's own time plus the plan with
   its agents against the plan with all agents, for ``fop``. At every frame (one per
   0.5 s) the all-agents plan and the filtered plan run in turns, so the shared machine's
   slow spells fall on both alike; the ratio is of the medians over the dense frames.
   Scenes: a 257-agent synthetic intersection (``replay convert synthetic --agents 257
   --seed 7 --lanes 3 --arm-length 250``) and, when ../shared/data is there, the densest
   nuScenes scene (scene-0061 through ScenarioNet), each seen from its own ego.
2. **Closed loop** on a 20 s scene at 10 Hz (nuScenes scene-0061, the recorded ego): the
   wall time of one run with all agents, per planner (goal: 10 s).
3. **Open loop over a corpus** (``--corpus``): every moving agent as the ego at 1 Hz, two
   planners (idm, fiss_plus), the default filter (the cascade), two worker processes
   (goal: 15 minutes for the recorded corpus).

Results (medians, with the machine's load) go to ``benchmarks/results/planner_loop.md``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np
import polars as pl

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from replay.analysis.planner_eval.closed_loop import ClosedLoopSettings, run_ego
from replay.analysis.planner_eval.open_loop import PlanSettings
from replay.analysis.planner_eval.study import run_open_loop, scene_files
from replay.core.egos import load_scene
from replay.core.engine import Stride

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
NUSCENES = SHARED / "scenarionet" / "nuscenes_0" / "sd_nuscenes_v1.0-mini_scene-0061.pkl"
RESULTS = ROOT / "benchmarks" / "results" / "planner_loop.md"
DENSE = 50


def _load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def _replay(*words: str) -> None:
    subprocess.run([sys.executable, "-m", "replay", *words], check=True, capture_output=True)


def dense_scenes(folder: pathlib.Path) -> list[pathlib.Path]:
    """The two dense scenes, made with the commands of the module docstring."""
    synthetic = folder / "synthetic" / "dense-257.mcap"
    synthetic.parent.mkdir(parents=True)
    _replay("convert", "synthetic", "-o", str(synthetic), "--agents", "257", "--seed", "7",
            "--lanes", "3", "--arm-length", "250")  # fmt: skip
    scenes = [synthetic]
    if NUSCENES.is_file():
        nuscenes = folder / "nuscenes" / "scene-0061.mcap"
        nuscenes.parent.mkdir(parents=True)
        _replay("convert", "scenarionet", str(NUSCENES), "-o", str(nuscenes))
        scenes.append(nuscenes)
    return scenes


def dense_ratio(scenes: list[pathlib.Path], planner: str) -> dict[str, object]:
    settings = PlanSettings(planner=planner, filters=("cascade",))
    tables = run_open_loop(scenes, settings, every=Stride(seconds=0.5), workers=1, progress=False)
    rows = tables.plans.filter(pl.col("n_others") >= DENSE)
    key = ["scene", "ego_id", "frame"]
    everyone = rows.filter(pl.col("filter") == "none").select(
        [*key, pl.col("plan_ms").alias("all_ms"), pl.col("plan_ok").alias("all_ok")]
    )
    cascade = rows.filter(pl.col("filter") == "cascade").join(everyone, on=key)
    both = cascade.filter(pl.col("plan_ok") & pl.col("all_ok"))
    total = (both["filter_ms"] + both["plan_ms"]).to_numpy()
    all_ms = both["all_ms"].to_numpy()
    return {
        "planner": planner,
        "frames": cascade.height,
        "both_ok": both.height,
        "others": float(cascade["n_others"].mean() or 0),
        "kept": float(cascade["n_agents"].mean() or 0),
        "all_ms": float(np.median(all_ms)) if all_ms.size else float("nan"),
        "filter_plus_plan_ms": float(np.median(total)) if total.size else float("nan"),
        "ratio": float(np.median(total) / np.median(all_ms)) if all_ms.size else float("nan"),
        "changed": int(cascade["changed"].fill_null(False).sum()),
        "comparable": int(cascade["changed"].is_not_null().sum()),
    }


def closed_loop_time(scene: pathlib.Path, planner: str, repeats: int) -> dict[str, object]:
    ego = int(load_scene(scene).metadata["ego_id"])
    settings = ClosedLoopSettings(plan=PlanSettings(planner=planner, filters=()))
    times, row = [], {}
    for _ in range(repeats):
        start = time.perf_counter()
        (row,) = run_ego(scene, ego, settings)  # all agents only
        times.append(time.perf_counter() - start)
    return {
        "planner": planner,
        "steps": row["steps"],
        "duration_s": row["duration_s"],
        "wall_s": float(np.median(times)),
        "collisions": row["collisions"],
    }


def corpus_time(folders: list[str]) -> dict[str, object]:
    scenes = scene_files(folders)
    out = {"scenes": len(scenes)}
    start = time.perf_counter()
    frames = 0
    for planner in ("idm", "fiss_plus"):
        settings = PlanSettings(planner=planner, filters=("cascade",))
        tables = run_open_loop(
            scenes, settings, ego="all", every=Stride(seconds=1.0), workers=2, progress=True
        )
        frames = tables.ego_frames
    out["wall_s"] = time.perf_counter() - start
    out["ego_frames"] = frames
    return out


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--corpus", nargs="*", default=None, help="scene folders for the corpus open loop"
    )
    ap.add_argument("--repeats", type=int, default=3, help="closed-loop runs per planner")
    args = ap.parse_args()
    lines = [
        f"## {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC",
        "",
        f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}; "
        f"load average before: {_load()}. Command: `python benchmarks/bench_planner_loop.py"
        + (" --corpus ..." if args.corpus else "")
        + "`.",
        "",
    ]
    with tempfile.TemporaryDirectory() as tmp:
        scenes = dense_scenes(pathlib.Path(tmp))
        d = dense_ratio(scenes, "fop")
        lines += [
            f"**Dense frames (>= {DENSE} others), fop, cascade** (goal <= 0.5x): "
            f"{d['frames']} frames ({d['both_ok']} with both plans), {d['others']:.0f} others, "
            f"{d['kept']:.1f} kept; plan {d['all_ms']:.1f} ms with all agents, cascade + plan "
            f"{d['filter_plus_plan_ms']:.1f} ms: **{d['ratio']:.2f}x**; plan changed in "
            f"{d['changed']} of {d['comparable']} comparable frames.",
            "",
        ]
        if NUSCENES.is_file():
            for planner in ("idm", "fop"):
                c = closed_loop_time(scenes[-1], planner, args.repeats)
                lines.append(
                    f"**Closed loop, {planner}** (goal <= 10 s): nuScenes scene-0061, "
                    f"{c['duration_s']:.1f} s at 10 Hz ({c['steps']} steps), all agents: "
                    f"**{c['wall_s']:.1f} s** wall (median of {args.repeats}); "
                    f"{c['collisions']} collisions."
                )
            lines.append("")
    if args.corpus:
        c = corpus_time(args.corpus)
        lines += [
            f"**Open loop over the corpus** (goal <= 15 min): {c['scenes']} scenes, "
            f"{c['ego_frames']} ego-frames (every moving agent at 1 Hz), idm and fiss_plus, "
            f"the cascade, 2 workers: **{c['wall_s'] / 60:.1f} min** wall.",
            "",
        ]
    lines.append(f"Load average after: {_load()}.")
    text = "\n".join(lines) + "\n"
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    head = "# The planner in the loop: speed goals\n\nWritten by `benchmarks/bench_planner_loop.py`; newest first.\n\n"
    old = RESULTS.read_text().split("\n\n", 2)[2] if RESULTS.is_file() else ""
    RESULTS.write_text(head + text + ("\n" + old if old else ""))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
