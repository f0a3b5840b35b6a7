"""Benchmark: the driver's peak memory of a corpus command (``replay evaluate`` unless
``--command`` names another) on a corpus and on the same corpus replicated K times
(issue 38: at 4x, no more than 1.3x the peak of 1x).

The corpus is a folder of MCAP scenes. Replica ``K`` is a folder with K sub-folders
``r0 .. r{K-1}``, each holding a *copy* of every scene (copies, not links: the same file
given twice is one scene), so replica K has K times the scenes and rows. Each run is
``python -m replay evaluate REPLICA -o OUT`` in a fresh process; a sampler reads the
resident set size of the driver process (and, apart, of the driver with its worker
processes) every 20 ms. The scenes are replayed by ``--workers`` worker processes, so
the driver's figure is the evaluation's own memory: reading the parts back and
computing the summary.

``--streamed`` also measures, after each evaluation, a separate process that runs the
evaluation alone (:func:`replay.analysis.evaluation.streaming.evaluate_parts`, what
``replay evaluate`` runs since issue 38) over the same part files, and compares its AUCs
with the command's summary (the difference must lie within the stated bound).

Usage::

    python benchmarks/bench_memory.py --scenes DIR --work DIR [--factors 1,4]
        [--workers 2] [--bootstrap 200] [--repeat 1] [--keep-parts] [--streamed]
    python benchmarks/bench_memory.py --streamed-parts OUT --work DIR [--factors 1,4]
        [--bootstrap 1000] [--repeat 1]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import psutil

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from results_log import recorded


def replica(scenes: list[pathlib.Path], work: pathlib.Path, factor: int) -> pathlib.Path:
    folder = work / f"x{factor}"
    if folder.exists():
        return folder
    for k in range(factor):
        (folder / f"r{k}").mkdir(parents=True)
        for s in scenes:
            shutil.copyfile(s, folder / f"r{k}" / s.name)  # follows links: real copies
    return folder


def peak_rss(cmd: list[str], env: dict[str, str]) -> tuple[int, int, float, int]:
    """(driver peak bytes, driver + workers peak bytes, seconds, exit code)."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    driver = psutil.Process(proc.pid)
    peaks = [0, 0]
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            try:
                own = driver.memory_info().rss
                tree = own
                for child in driver.children(recursive=True):
                    with contextlib.suppress(psutil.Error):
                        tree += child.memory_info().rss
            except psutil.Error:
                break
            peaks[0] = max(peaks[0], own)
            peaks[1] = max(peaks[1], tree)
            time.sleep(0.02)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    _, err = proc.communicate()
    done.set()
    thread.join()
    if proc.returncode:
        sys.stderr.write(err.decode(errors="replace")[-2000:])
    return peaks[0], peaks[1], time.perf_counter() - start, proc.returncode


def streamed_pass(out: pathlib.Path, n_boot: int, result: pathlib.Path, factor: int = 1) -> None:
    """The child process of ``--streamed``: the streamed pass over ``out``'s parts (each
    part ``factor`` times, as that many scenes: a replica without copying the files)."""
    from replay.analysis.evaluation.streaming import (
        StreamSettings,
        evaluate_parts,
        max_difference,
        run_parts,
    )

    start = time.perf_counter()
    from replay.analysis.evaluation.corpus import EvaluationSettings

    settings = StreamSettings.of(EvaluationSettings(n_boot=n_boot))  # the command's defaults
    streamed = evaluate_parts(run_parts(out) * factor, settings)
    seconds = time.perf_counter() - start
    summary = json.loads((out / "summary.json").read_text())
    diff = max_difference(streamed.summary, summary) if factor == 1 else {}
    result.write_text(json.dumps({"seconds": seconds, "summary_bytes": streamed.held_bytes,
                                  "scenes": streamed.summary["scenes"], **diff}))  # fmt: skip


def streamed_only(args: argparse.Namespace) -> None:
    env = {**os.environ, "PYTHONPATH": str(pathlib.Path(__file__).resolve().parents[1])}
    args.work.mkdir(parents=True, exist_ok=True)
    factors = [int(f) for f in args.factors.split(",")]
    peaks: dict[int, list[int]] = {}
    for rep in range(args.repeat):
        for factor in factors:
            res = args.work / f"streamed-parts-x{factor}-{rep}.json"
            child = [sys.executable, __file__, "--stream-child", str(args.streamed_parts),
                     str(args.bootstrap), str(res), str(factor)]  # fmt: skip
            own, _, seconds, code = peak_rss(child, env)
            info = json.loads(res.read_text()) if code == 0 else {}
            peaks.setdefault(factor, []).append(own)
            print(
                f"x{factor} run {rep}: {info.get('scenes')} scenes, streamed pass peak "
                f"{own / 2**20:.0f} MiB, {seconds:.0f} s, summaries "
                f"{info.get('summary_bytes', 0) / 2**20:.1f} MiB"
                + (
                    f", max |AUC - evaluate's| {info['auc']:.2e} (max bound "
                    f"{info['auc_bound']:.2e}), max CI end difference {info['auc_ci']:.2e}, "
                    f"curves beyond their bound {info['beyond_bound']:.0f}"
                    if "auc" in info
                    else ""
                )
                + f", exit {code}",
                flush=True,
            )
    base = sorted(peaks[factors[0]])[len(peaks[factors[0]]) // 2]
    for factor in factors[1:]:
        p = sorted(peaks[factor])[len(peaks[factor]) // 2]
        print(f"x{factor} / x{factors[0]} streamed pass peak (medians): {p / base:.2f}")


def main() -> None:
    if len(sys.argv) in (5, 6) and sys.argv[1] == "--stream-child":
        out, n_boot, result, factor = [*sys.argv[2:], "1"][:4]
        streamed_pass(pathlib.Path(out), int(n_boot), pathlib.Path(result), int(factor))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=pathlib.Path, default=None)
    ap.add_argument("--work", type=pathlib.Path, required=True)
    ap.add_argument("--factors", default="1,4")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--bootstrap", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument(
        "--keep-parts", action="store_true",
        help="Evaluate into the folders of an earlier run: its scenes are complete, so only "
        "reading the parts back and the evaluation are measured.",
    )  # fmt: skip
    ap.add_argument(
        "--command",
        choices=sorted(COMMANDS),
        default="evaluate",
        help="The corpus command whose driver is measured.",
    )
    ap.add_argument(
        "--extra",
        nargs=argparse.REMAINDER,
        default=[],
        help="Further options of that command (last on the line).",
    )
    ap.add_argument("--streamed", action="store_true")
    ap.add_argument(
        "--streamed-parts", type=pathlib.Path, default=None,
        help="Only the streamed pass, over the parts of this evaluate output folder, each "
        "part given --factors times (as that many scenes); no scene is replayed.",
    )  # fmt: skip
    args = ap.parse_args()
    with recorded("memory", "Driver memory of the corpus commands (issue 38)"):
        if args.streamed_parts is not None:
            streamed_only(args)
        else:
            evaluate_runs(args)


def _evaluate_argv(folder: pathlib.Path, out: pathlib.Path, args: argparse.Namespace) -> list[str]:
    return [
        "evaluate", str(folder), "-o", str(out), "--bootstrap", str(args.bootstrap),
        "--no-plots", "--no-progress", "--workers", str(args.workers), *args.extra,
    ]  # fmt: skip


def _calibrate_argv(folder: pathlib.Path, out: pathlib.Path, args: argparse.Namespace) -> list[str]:
    """``replay calibrate`` on every scene of the replica: its parts (the per-scene jobs)
    in OUT (so that --keep-parts reuses them), the TOML beside it as OUT.toml. Without
    --extra: the survival reference."""
    return [
        "calibrate", *map(str, sorted(folder.rglob("*.mcap"))), "-o", f"{out}.toml",
        "--scores-cache", str(out), "--no-progress", "--workers", str(args.workers),
        *args.extra,
    ]  # fmt: skip


def _plan_argv(folder: pathlib.Path, out: pathlib.Path, args: argparse.Namespace) -> list[str]:
    """``replay plan``'s open loop (summary, merged plans.parquet and its plots), every
    moving agent as the ego once a second, IDM, the cascade against all agents."""
    return [
        "plan", str(folder), "-o", str(out), "--ego", "all", "--every", "1s",
        "--planner", "idm", "--filter", "cascade", "--no-progress",
        "--workers", str(args.workers), *args.extra,
    ]  # fmt: skip


def _stats_argv(folder: pathlib.Path, out: pathlib.Path, args: argparse.Namespace) -> list[str]:
    return [
        "stats", str(folder), "-o", str(out), "--no-plots", "--no-progress",
        "--workers", str(args.workers), *args.extra,
    ]  # fmt: skip


def _sensitivity_argv(
    folder: pathlib.Path, out: pathlib.Path, args: argparse.Namespace
) -> list[str]:
    return [
        "evaluate", str(folder), "-o", str(out), "--bootstrap", str(args.bootstrap),
        "--no-plots", "--no-progress", "--workers", str(args.workers), "--sensitivity",
        "--sensitivity-bootstrap", str(args.bootstrap), *args.extra,
    ]  # fmt: skip


# The corpus commands measured (issue 38): each maps (replica folder, output folder, the
# parsed options) to the arguments of ``python -m replay``. ``--extra`` appends options.
COMMANDS: dict[str, Callable[[pathlib.Path, pathlib.Path, argparse.Namespace], list[str]]] = {
    "evaluate": _evaluate_argv,
    "calibrate": _calibrate_argv,
    "plan": _plan_argv,
    "stats": _stats_argv,
    "sensitivity": _sensitivity_argv,
}


def evaluate_runs(args: argparse.Namespace) -> None:
    if args.scenes is None:
        raise SystemExit("--scenes DIR is needed (or --streamed-parts OUT)")
    scenes = sorted(args.scenes.glob("*.mcap"))
    factors = [int(f) for f in args.factors.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(pathlib.Path(__file__).resolve().parents[1])}
    rows = []
    streamed_rows: list[tuple[int, int]] = []
    for rep in range(args.repeat):
        for factor in factors:  # the factors take turns in every repeat
            folder = replica(scenes, args.work, factor)
            out = args.work / f"out-x{factor}-{0 if args.keep_parts else rep}"
            if not args.keep_parts:
                shutil.rmtree(out, ignore_errors=True)
            cmd = [sys.executable, "-m", "replay", *COMMANDS[args.command](folder, out, args)]
            own, tree, seconds, code = peak_rss(cmd, env)
            summary_file = out / "summary.json"
            summary = json.loads(summary_file.read_text()) if summary_file.is_file() else {}
            frames = summary.get("references", {}).get("hindsight", {}).get("agent_frames")
            rows.append((factor, rep, len(scenes) * factor, frames, own, tree, seconds, code))
            print(
                f"x{factor} run {rep}: {len(scenes) * factor} scenes, {frames} agent-frames, "
                f"driver peak {own / 2**20:.0f} MiB (with workers {tree / 2**20:.0f} MiB), "
                f"{seconds:.0f} s, exit {code}",
                flush=True,
            )
            if args.streamed and code == 0:
                res = args.work / f"streamed-x{factor}-{rep}.json"
                child = [sys.executable, __file__, "--stream-child", str(out),
                         str(args.bootstrap), str(res), "1"]  # fmt: skip
                s_own, _, s_sec, s_code = peak_rss(child, env)
                info = json.loads(res.read_text()) if s_code == 0 else {}
                streamed_rows.append((factor, s_own))
                print(
                    f"x{factor} run {rep} streamed ROC pass: peak {s_own / 2**20:.0f} MiB, "
                    f"{s_sec:.0f} s, summaries {info.get('summary_bytes', 0) / 2**20:.1f} MiB, "
                    f"max |AUC - evaluate's| {info.get('auc', float('nan')):.2e} "
                    f"(max bound {info.get('auc_bound', float('nan')):.2e}), max CI end "
                    f"difference {info.get('auc_ci', float('nan')):.2e}, curves beyond their bound "
                    f"{info.get('beyond_bound', float('nan')):.0f}, exit {s_code}",
                    flush=True,
                )
    for name, table in (("streamed ROC pass", streamed_rows),):
        ref_rows = sorted(r[1] for r in table if r[0] == factors[0])
        for factor in factors[1:]:
            peaks = sorted(r[1] for r in table if r[0] == factor)
            if ref_rows and peaks:
                ratio = peaks[len(peaks) // 2] / ref_rows[len(ref_rows) // 2]
                print(f"x{factor} / x{factors[0]} {name} peak (medians): {ratio:.2f}")
    base = [r[4] for r in rows if r[0] == factors[0]]
    if base:
        ref = sorted(base)[len(base) // 2]
        for factor in factors[1:]:
            peaks = sorted(r[4] for r in rows if r[0] == factor)
            print(
                f"x{factor} / x{factors[0]} driver peak (medians): {peaks[len(peaks) // 2] / ref:.2f}"
            )


if __name__ == "__main__":
    main()
