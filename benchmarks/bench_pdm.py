"""``pdm`` per call on real frames with about 30 other agents (issue 35's goal: 10 ms at the
median on this machine).

Usage::

    .venv/bin/python benchmarks/bench_pdm.py            # 2 scenes, 40 requests, 5 rounds
    .venv/bin/python benchmarks/bench_pdm.py --quick    # 12 requests, 2 rounds
    .venv/bin/python benchmarks/bench_pdm.py --tree main=/tmp/main --tree new=.  # trees in turns

The scenes: two MONA scenes of ../shared/data/recorded (36-43 valid agents a frame; the
exiD scenes there have 16 or fewer), converted with
``python -m replay convert commonroad FILE -o x.mcap`` into a temporary folder. The
requests: every moving vehicle as the ego, one frame per second, built as ``replay plan``
builds them (:func:`replay.planning.inputs.plan_request`, target speed from the recorded
future, 5 s at 0.1 s), kept where 25 to 40 other agents are valid; spread evenly over
what is found, up to ``--requests``.

Every request is planned by ``pdm`` and ``idm`` in turns, for several rounds, so that the
shared machine's slow spells fall on both alike; the table gives the medians and 95th
percentiles of the wall time (``time.perf_counter``) and of the process CPU time
(``time.process_time``, less disturbed by other processes on the 2 shared cores), the
ratio to ``idm`` on the same requests, and pdm's stages (CPU medians). Results are
appended, dated, to ``benchmarks/results/pdm.md``.

With ``--tree NAME=PATH`` (twice or more) the same requests (built once, by this tree)
are planned by each tree's own ``pdm`` instead, one process per tree and round, the trees
in turns round after round; the table gives each tree's medians and the ratios to the
first tree (of the medians, and the median of the per-request ratios).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import pickle
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from recorded_scenes import RECORDED, converted, moving_vehicles

from replay.analysis.planner_eval.open_loop import ego_frames
from replay.core.engine import Stride
from replay.planning import lqr
from replay.planning.errors import NoReferencePath
from replay.planning.idm import IdmPlanner
from replay.planning.inputs import plan_request
from replay.planning.pdm import PdmPlanner, _centres
from replay.planning.truth import target_speed
from replay.planning.types import PlanRequest

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = (
    RECORDED / "mona" / "C-DEU_MONAEast-2_1040_T-1119.xml",
    RECORDED / "mona" / "C-DEU_MONAEast-2_400_T-479.xml",
)
RESULTS = ROOT / "benchmarks" / "results" / "pdm.md"
AGENTS = (25, 40)


def requests(folder: pathlib.Path, limit: int) -> list[tuple[str, PlanRequest]]:
    found: list[tuple[str, PlanRequest]] = []
    for source, scene in converted(SCENES, folder):
        tracks = scene.tracks()
        column_of = {int(i): c for c, i in enumerate(tracks.ids)}
        egos = moving_vehicles(scene)
        for ego_id, _, frame in ego_frames(scene, egos, Stride(seconds=1.0)):
            n = int(frame.others.sum())
            if not AGENTS[0] <= n <= AGENTS[1]:
                continue
            row = round((frame.t - tracks.t0_s) / tracks.dt_s)
            speed = float(frame.speed[frame.ego])
            goal = target_speed(tracks, row, column_of[ego_id], 5.0, speed)
            try:
                found.append(
                    (source.parent.name, plan_request(frame, scene.map, target_speed_mps=goal))
                )
            except NoReferencePath:
                continue
    if len(found) > limit:
        pick = np.linspace(0, len(found) - 1, limit).round().astype(int)
        found = [found[i] for i in pick]
    return found


def timed(fn, *args) -> tuple[float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    fn(*args)
    return (time.perf_counter() - wall) * 1e3, (time.process_time() - cpu) * 1e3


def stages(pdm: PdmPlanner, request: PlanRequest) -> dict[str, float]:
    """CPU ms of pdm's stages on one request (one run each, after the timed rounds)."""
    out: dict[str, float] = {}
    t = time.process_time()
    line, scored, proposals, _, candidates = pdm._relevant(request)
    out["relevance + IDM + simulation"] = (time.process_time() - t) * 1e3
    t = time.process_time()
    pdm._simulate(request, proposals.states, request.dt_s)
    out["  of which the simulation (LQR + bicycle, 17 x 50 steps)"] = (
        time.process_time() - t
    ) * 1e3
    sim = proposals.simulated
    t = time.process_time()
    pdm._score(
        request,
        line,
        scored,
        sim,
        _centres(sim, proposals.wheelbase_m),
        candidates,
    )
    out["scoring"] = (time.process_time() - t) * 1e3
    return out


#: What one tree's process runs (cwd and PYTHONPATH the tree): its own ``pdm`` on the
#: pickled requests, 3 warm-up calls, then wall and CPU ms per request as JSON.
_TREE_WORKER = """
import json, pickle, sys, time
from replay.planning.pdm import PdmPlanner
reqs = pickle.load(open(sys.argv[1], "rb"))
pdm = PdmPlanner()
for r in reqs[:3]:
    pdm.plan(r)
out = []
for r in reqs:
    w, c = time.perf_counter(), time.process_time()
    pdm.plan(r)
    out.append(((time.perf_counter() - w) * 1e3, (time.process_time() - c) * 1e3))
print(json.dumps(out))
"""


def _commit(tree: pathlib.Path) -> str:
    """The tree's commit, or "not a git tree" (e.g. a ``git archive`` snapshot)."""
    done = subprocess.run(
        ["git", "-C", str(tree), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    dirty = subprocess.run(
        ["git", "-C", str(tree), "status", "--porcelain", "--untracked-files=no"],
        capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0 or not (tree / ".git").exists():
        return "not a git tree"
    return done.stdout.strip() + (" with changes" if dirty.stdout.strip() else "")


def compare_trees(
    trees: list[tuple[str, pathlib.Path]], reqs: list[PlanRequest], rounds: int
) -> list[str]:
    """Each tree's ``pdm`` on the same requests, one process per tree and round, in turns:
    the table's lines (medians, and ratios to the first tree)."""
    wall: dict[str, list[np.ndarray]] = {name: [] for name, _ in trees}
    cpu: dict[str, list[np.ndarray]] = {name: [] for name, _ in trees}
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as folder:
        path = pathlib.Path(folder) / "requests.pkl"
        path.write_bytes(pickle.dumps(reqs))
        for _ in range(rounds):
            for name, tree in trees:
                env = {**os.environ, "PYTHONPATH": str(tree)}
                done = subprocess.run(
                    [sys.executable, "-c", _TREE_WORKER, str(path)],
                    cwd=tree, env=env, check=True, capture_output=True, text=True,
                )  # fmt: skip
                times = np.array(json.loads(done.stdout.strip().splitlines()[-1]))
                wall[name].append(times[:, 0])
                cpu[name].append(times[:, 1])
    load_after = os.getloadavg()
    first = trees[0][0]
    lines = [
        f"- trees, in turns ({rounds} rounds, one process per tree and round): "
        + ", ".join(f"{n} = `{t}` ({_commit(t)})" for n, t in trees),
        f"- load average {load_before[0]:.1f} before, {load_after[0]:.1f} after",
        "",
        f"| tree | wall median ms | CPU median ms | CPU p95 ms | CPU median / {first} "
        f"| per-request CPU ratio to {first} (median) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    base_cpu = np.stack(cpu[first])
    for name, _ in trees:
        c, w = np.stack(cpu[name]), np.stack(wall[name])
        per_request = np.median(c, axis=0) / np.median(base_cpu, axis=0)
        lines.append(
            f"| {name} | {np.median(w):.2f} | {np.median(c):.2f} | {np.percentile(c, 95):.2f} "
            f"| {np.median(c) / np.median(base_cpu):.3f} | {np.median(per_request):.3f} |"
        )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--requests", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--tree", action="append", default=[], metavar="NAME=PATH",
        help="compare these trees' pdm in turns (twice or more)",
    )  # fmt: skip
    args = parser.parse_args()
    limit, rounds = (12, 2) if args.quick else (args.requests, args.rounds)
    with tempfile.TemporaryDirectory() as folder:
        reqs = requests(pathlib.Path(folder), limit)
    if not reqs:
        print("no scenes found under ../shared/data/recorded: nothing measured", file=sys.stderr)
        return 1
    if args.tree:
        trees = [
            (n, pathlib.Path(p).resolve()) for n, _, p in (t.partition("=") for t in args.tree)
        ]
        if len(trees) < 2 or any(not p.is_dir() for _, p in trees):
            print("Error: --tree NAME=PATH needs two or more existing folders", file=sys.stderr)
            return 2
        agents = np.array([r.agents.n for _, r in reqs])
        text = "\n".join(
            [
                f"\n## {datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}: "
                f"`python benchmarks/bench_pdm.py --tree ...`\n",
                f"- requests: {len(reqs)} frames, other agents {agents.min()}-{agents.max()} "
                f"(median {np.median(agents):.0f}); noisy shared machine: compare ratios",
                *compare_trees(trees, [r for _, r in reqs], rounds),
                "",
            ]
        )
        print(text)
        with RESULTS.open("a") as f:
            f.write(text)
        return 0
    pdm, idm = PdmPlanner(), IdmPlanner()
    for _, r in reqs[:3]:  # warm-up: imports, cached filter matrices
        pdm.plan(r)
        idm.plan(r)
    load_before = os.getloadavg()
    pdm_wall, pdm_cpu, idm_wall, idm_cpu = [], [], [], []
    relevant, brakes = [], 0
    for _ in range(rounds):
        for _, r in reqs:
            w, c = timed(pdm.plan, r)
            pdm_wall.append(w)
            pdm_cpu.append(c)
            w, c = timed(idm.plan, r)
            idm_wall.append(w)
            idm_cpu.append(c)
    for _, r in reqs:
        relevant.append(int(pdm.may_matter(r).sum()))
        brakes += int(pdm.plan(r).extras["emergency_brake"])
    load_after = os.getloadavg()
    split: dict[str, list[float]] = {}
    for _, r in reqs:
        for name, ms in stages(pdm, r).items():
            split.setdefault(name, []).append(ms)
    agents = np.array([r.agents.n for _, r in reqs])
    datasets = sorted({d for d, _ in reqs})

    def q(values: list[float], p: float) -> float:
        return float(np.percentile(values, p))

    lines = [
        f"\n## {datetime.datetime.now().astimezone():%Y-%m-%d %H:%M %Z}: `python benchmarks/bench_pdm.py"
        f"{' --quick' if args.quick else ''}`\n",
        f"- machine: {platform.machine()}, {os.cpu_count()} cores shared with other sessions; "
        f"load average {load_before[0]:.1f} before, {load_after[0]:.1f} after (noisy: compare "
        "CPU times and the ratio to idm, not single wall times)",
        f"- requests: {len(reqs)} frames from {', '.join(datasets)} (vehicle egos, 1 Hz), "
        f"other agents {agents.min()}-{agents.max()} (median {np.median(agents):.0f}); "
        f"agents pdm may read (`may_matter`): median {np.median(relevant):.0f}; "
        f"{rounds} rounds in turns with idm; emergency brakes: {brakes}",
        f"- pdm settings: {len(pdm.settings.target_fractions) * len(pdm.settings.lateral_offsets_m)} "
        f"IDM and {len(pdm.settings.brake_proposals_mps2)} braking proposals, horizon 5 s at 0.1 s, LQR look-ahead {lqr.TrackerSettings().horizon_steps} steps; "
        f"per-step loops {'compiled (numba)' if getattr(pdm, 'compiled', False) else 'numpy'}",
        "",
        "| | median ms | p95 ms |",
        "|---|---:|---:|",
        f"| pdm, wall | {np.median(pdm_wall):.1f} | {q(pdm_wall, 95):.1f} |",
        f"| pdm, CPU | {np.median(pdm_cpu):.1f} | {q(pdm_cpu, 95):.1f} |",
        f"| idm, wall | {np.median(idm_wall):.2f} | {q(idm_wall, 95):.2f} |",
        f"| idm, CPU | {np.median(idm_cpu):.2f} | {q(idm_cpu, 95):.2f} |",
        f"| pdm / idm (medians, CPU) | {np.median(pdm_cpu) / np.median(idm_cpu):.1f} | |",
        "",
        "pdm's stages (CPU ms, median over the requests, one run each):",
        "",
        *[f"- {name}: {np.median(ms):.1f}" for name, ms in split.items()],
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if not RESULTS.exists():
        RESULTS.write_text(
            "# pdm: time per call\n\nWritten by `benchmarks/bench_pdm.py` (newest last). Goal "
            "(issue 35): at most 10 ms per call at the median, at about 30 agents.\n"
        )
    with RESULTS.open("a") as f:
        f.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
