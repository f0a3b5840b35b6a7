"""How far the compiled kernel lies from the numpy modules, in ulps, per model and for
the cascade, on this machine and under other numpy and numba code paths.

Usage::

    .venv/bin/python benchmarks/ulp_table.py            # every setting, one table
    .venv/bin/python benchmarks/ulp_table.py --here     # only this process's setting (JSON)

The settings (each in a new process):

- ``default``: numpy and the kernel as they are here (the ahead-of-time kernel when built);
- ``npy X86_V2``: ``NPY_ENABLE_CPU_FEATURES=X86_V2``, numpy's baseline code only (no
  AVX2, no AVX-512: numpy's ``exp``, ``log``, ``arctan2`` are the C library's);
- ``numba generic``: ``NUMBA_CPU_NAME=generic`` with a fresh ``NUMBA_CACHE_DIR`` and
  ``RISKREPLAY_KERNEL=jit`` (the kernel compiled for a generic x86-64, not loaded from
  the host's cache or its ahead-of-time module; a cold compile of about 25 s);
- ``exp moved 1 ulp``: ``RISKREPLAY_TEST_EXP_ULPS=1``, the numpy models' ``exp`` results
  moved by up to one float at random (another CPU's exp, simulated; tests/exactness.py).

Frames: the benchmark's intersection (N = 2, 40, 120 from seeds 5-7, and N = 120 from seeds
100-119; horizon 12 s, dt 0.1 s),
the conformance suite's crossing frame (8 s, 0.2 s), 200 mixed random frames of the oracle
tests (3 s, 0.25 s) and 20 scattered frames (defaults). The cascade (the default
configuration) runs fused on the kernel and staged on the numpy modules, on the
intersection and the scattered frames: survival ulps, and the decisions that differ,
with how many of those have a value within the tolerance of their threshold
(tests/exactness.py).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_models import random_frame as lane_frame  # noqa: E402
from exactness import kernel_ulps, near, numpy_exp_off_by, ulp_distance  # noqa: E402
from frames import mixed_frame, scattered_frame  # noqa: E402

from risk import MODELS, PredictionSettings, evaluate, kernel  # noqa: E402
from risk.cascade import CascadeConfig, run_cascade  # noqa: E402
from risk.registry import evaluate_numpy  # noqa: E402

EXP_ULPS_ENV = "RISKREPLAY_TEST_EXP_ULPS"  # as tests/conftest.py
SETTINGS = {
    "default": {},
    "npy X86_V2": {"NPY_ENABLE_CPU_FEATURES": "X86_V2"},
    "numba generic": {"NUMBA_CPU_NAME": "generic", "RISKREPLAY_KERNEL": "jit"},
    "exp moved 1 ulp": {EXP_ULPS_ENV: "1"},
}
CASCADE_OUTPUTS = ("cascade.survival_all", "cascade.survival")


def frames():
    """(label, frame, prediction) for every frame measured."""
    for seed in (5, 6, 7):
        rng = np.random.default_rng(seed)
        for n in (2, 40, 120):
            yield f"lane n={n} seed={seed}", lane_frame(n, rng), None
    for seed in range(100, 120):
        yield f"lane n=120 seed={seed}", lane_frame(120, np.random.default_rng(seed)), None
    from test_models_conformance import FRAME, PRED

    yield "conformance", FRAME, PRED
    short = PredictionSettings(horizon_s=3.0, dt_s=0.25)
    for seed in range(200):
        yield f"mixed seed={seed}", mixed_frame(np.random.default_rng(seed)), short
    for seed in range(20):
        yield f"scattered seed={seed}", scattered_frame(seed), None


def measure() -> dict:
    worst = {
        name: [0.0, "", 0, 0] for name in [*MODELS, *CASCADE_OUTPUTS]
    }  # ulps, where, differ, n

    def record(name: str, label: str, a: np.ndarray, b: np.ndarray) -> None:
        d = ulp_distance(a, b)
        w = worst[name]
        w[2] += int((d > 0).sum())
        w[3] += int((~np.isnan(a)).sum())
        if d.size and d.max() > w[0]:
            w[0], w[1] = float(d.max()), label

    decisions = {"compared": 0, "differ": 0, "differ_near_threshold": 0, "near_threshold": 0}
    config = CascadeConfig.default()
    for label, frame, pred in frames():
        fast = evaluate(frame, prediction=pred)
        slow = evaluate_numpy(frame, prediction=pred)
        for name in MODELS:
            record(name, label, fast[name], slow[name])
        if label.startswith(("lane", "scattered")):
            fused = run_cascade(frame, config, prediction=pred, reachability=False)
            staged = run_cascade(frame, config, prediction=pred, evaluate=evaluate_numpy)
            for name in CASCADE_OUTPUTS:
                field = name.split(".")[1]
                record(name, label, getattr(fused, field), getattr(staged, field))
            # An agent's decisions may differ only where one of its values lies within the
            # tolerance of a threshold it meets.
            amb = np.zeros(frame.n_agents, dtype=bool)
            for stage in config.stages:
                tol = kernel_ulps(stage.model)
                amb |= near(slow[stage.model], stage.threshold, tol)
            surv_tol = kernel_ulps("survival")
            for t in (config.baseline_threshold, *(t.min_survival_risk for t in config.tiers)):
                amb |= near(slow["survival"], t, surv_tol)
            differ = (
                (fused.kept != staged.kept).any(axis=0)
                | (fused.tier != staged.tier)
                | (fused.baseline != staged.baseline)
            )
            decisions["compared"] += int(frame.others.sum())
            decisions["differ"] += int(differ.sum())
            decisions["differ_near_threshold"] += int((differ & amb).sum())
            decisions["near_threshold"] += int(amb.sum())
    return {
        "implementation": kernel.IMPLEMENTATION,
        "numpy_simd": _simd(),
        "models": worst,
        "decisions": decisions,
    }


def _simd() -> list[str]:
    """numpy's baseline and the dispatch targets it enabled (as ``np.show_runtime``)."""
    from numpy._core._multiarray_umath import (
        __cpu_baseline__,
        __cpu_dispatch__,
        __cpu_features__,
    )

    return [*__cpu_baseline__, *(k for k in __cpu_dispatch__ if __cpu_features__.get(k))]


def run_all() -> None:
    results = {}
    with tempfile.TemporaryDirectory(prefix="ulp-table-") as cache:
        for name, env in SETTINGS.items():
            full = {**os.environ, **env}
            if "NUMBA_CPU_NAME" in env:
                full["NUMBA_CACHE_DIR"] = cache  # fresh: not the host CPU's compiled code
            out = subprocess.run(
                [sys.executable, __file__, "--here"], env=full, capture_output=True, text=True
            )
            if out.returncode != 0:
                sys.exit(f"{name}: {out.stderr}")
            results[name] = json.loads(out.stdout.splitlines()[-1])
    names = list(results)
    print("Largest difference, kernel against numpy, in ulps (values counted: not NaN)")
    print()
    print("| output | bound | " + " | ".join(names) + " |")
    print("|---|---:|" + "---:|" * len(names))
    first = results[names[0]]["models"]
    for out in first:
        bound = kernel_ulps(out if out in MODELS else "survival")
        cells = []
        for n in names:
            u, where, differ, count = results[n]["models"][out]
            cells.append(f"{u:g} ({differ} of {count} differ{'; ' + where if u else ''})")
        print(f"| {out} | {bound:g} | " + " | ".join(cells) + " |")
    print()
    for n in names:
        r = results[n]
        d = r["decisions"]
        print(
            f"{n}: kernel {r['implementation']}, numpy features {','.join(r['numpy_simd']) or '-'};"
            f" cascade decisions: {d['differ']} of {d['compared']} agents differ"
            f" ({d['differ_near_threshold']} of them near a threshold;"
            f" {d['near_threshold']} agents near a threshold in all)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--here", action="store_true", help="measure in this process (JSON)")
    args = parser.parse_args()
    if args.here:
        ulps = os.environ.get(EXP_ULPS_ENV, "").strip()
        if ulps:
            numpy_exp_off_by(int(ulps), np.random.default_rng(0)).start()
        print(json.dumps(measure()))
    else:
        run_all()


if __name__ == "__main__":
    main()
