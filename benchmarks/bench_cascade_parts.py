"""Where the one-pass cascade's time goes at N = 100, against survival on all agents.

Usage::

    .venv/bin/python benchmarks/bench_cascade_parts.py [--calls 500]

On the three N = 100 intersection frames of ``bench_kernel.py`` (same seed), calls the
cascade kernel (``risk.kernel.cascade_agents``) and the survival-only kernel
(``risk.kernel.run``) directly, in turns, and prints per frame: the agents kept after
each stage, the median CPU cycles the kernel counted in each of its parts (thousands:
set-up, reachability bound, each stage, survival of the survivors with the tiers), and
the median wall time of each call with their ratio. Then the Python around each:
``run_cascade`` minus both kernels (it computes survival on all agents for its report),
and ``evaluate(frame, ["survival"])`` minus the survival kernel (``bench_kernel.py``
times the cascade as ``run_cascade`` runs it).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_models import random_frame  # noqa: E402

from risk import cascade as cascade_module  # noqa: E402
from risk import evaluate, kernel  # noqa: E402
from risk.registry import kernel_inputs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=500, help="calls of each kernel per frame")
    args = ap.parse_args()

    rng = np.random.default_rng(7)  # (bench_kernel.py's N = 100 frames)
    frames = [random_frame(100, rng) for _ in range(3)]
    config = cascade_module.CascadeConfig.default()
    chosen, _, steps, unc, fp, ip = kernel_inputs(None, None)
    plan = cascade_module._plan(config, chosen)
    want_survival = cascade_module._WANT[(cascade_module._SURV_SLOT,)]
    names = ["set-up", "bound", *plan.stage_names, "survival + tiers"]
    print(f"kernel cycles (thousands) per part: {', '.join(names)}")
    no_tiers = np.zeros(0), np.zeros(0, np.int64)  # replay plan's filters: no tiers
    for f in frames:
        survival = kernel.run(f, want_survival, fp, ip, steps, unc)[cascade_module._SURV_SLOT]
        protected, _, _ = cascade_module.corridor_masks(f, config.corridor)
        shielded = kernel.NOT_PROTECTED if protected is None else protected
        call = (
            *kernel.frame_arrays(f), int(f.ego), kernel.ALL_AGENTS, steps, unc, fp, ip,
            plan.slots, plan.thr, plan.stop2, plan.cut2, True, cascade_module._MAX_SPEEDS,
            plan.baseline_threshold, survival, plan.tier_min, plan.tier_cap, shielded,
        )  # fmt: skip
        tierless = (*call[:-3], *no_tiers, shielded)
        kept = kernel.cascade_agents(*call)[0]
        cycles, t_cascade, t_survival, t_run, t_evaluate, t_tierless = [], [], [], [], [], []
        for _ in range(args.calls):
            t0 = time.perf_counter()
            out = kernel.cascade_agents(*call)
            t1 = time.perf_counter()
            kernel.cascade_agents(*tierless)
            t_tierless.append(time.perf_counter() - t1)
            t1 = time.perf_counter()
            kernel.run(f, want_survival, fp, ip, steps, unc)
            t2 = time.perf_counter()
            cascade_module.run_cascade(f, config)
            t3 = time.perf_counter()
            evaluate(f, ["survival"])
            t4 = time.perf_counter()
            cycles.append(out[5])
            t_cascade.append(t1 - t0)
            t_survival.append(t2 - t1)
            t_run.append(t3 - t2)
            t_evaluate.append(t4 - t3)
        parts = np.median(np.array(cycles), axis=0) / 1e3
        c, s = statistics.median(t_cascade), statistics.median(t_survival)
        glue_cascade = statistics.median(t_run) - c - s
        glue_evaluate = statistics.median(t_evaluate) - s
        print(
            f"kept {int(f.others.sum())} -> {' -> '.join(str(int(k.sum())) for k in kept)}; "
            f"cycles {np.round(parts).astype(int).tolist()}; cascade kernel {1e6 * c:.0f} µs, "
            f"survival kernel {1e6 * s:.0f} µs, ratio {c / s:.3f}; without tiers "
            f"{1e6 * statistics.median(t_tierless):.0f} µs; Python around "
            f"run_cascade {1e6 * glue_cascade:.0f} µs, around evaluate {1e6 * glue_evaluate:.0f} µs"
        )


if __name__ == "__main__":
    main()
