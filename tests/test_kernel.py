"""The compiled kernel (risk.kernel, the production path of risk.evaluate) against its
oracles: the vectorised numpy modules (risk.registry.evaluate_numpy) and the plain-loop
reference (risk.reference).

Against numpy: within the ulps of the exactness contract (tests/exactness.py). The two
do the same operations in the same order, but numpy's ``exp`` is its own SIMD code on
CPUs with AVX-512 and the C library's elsewhere, so the last bits agree on one CPU and
not on another. Against the reference, which orders its operations differently: 1e-9
relative for the distance-like models, 1e-6 in log10 for the Gaussian and survival
models (values below 1e-300 are subnormal and compared absolutely); measured on 300
mixed frames: at most 24 ulps for the distance and time models, 10150 ulps (2.2e-12) for
the Gaussian, where ``exp`` multiplies the exponent's rounding by its size.

Bit for bit: a model asked alone or with the other (the same compiled code).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from exactness import assert_exact, assert_within_ulps, kernel_ulps
from frames import mixed_frame as random_frame
from hypothesis import example, given, settings
from hypothesis import strategies as st
from oracle_ties import settle_rounding_touches

from risk import (
    BASELINE_THRESHOLD,
    MODELS,
    Frame,
    KindUncertainty,
    PredictionSettings,
    UncertaintyTable,
    baseline_mask,
    evaluate,
    kernel,
)
from risk.reference import reference_evaluate
from risk.registry import evaluate_numpy
from risk.stochastic import CirclesParams, SurvivalParams
from risk.temporal import ClosestEncounterParams, Headway2DParams, HeadwayParams

STOCHASTIC = ("gaussian", "survival")
SHORT = PredictionSettings(horizon_s=3.0, dt_s=0.25)
DEFAULT = PredictionSettings()


def assert_numpy_contract(fast: dict, slow: dict, params=None, prediction=None) -> None:
    """The kernel's results ``fast`` within the contract's ulps of numpy's ``slow``."""
    horizon = (prediction or DEFAULT).horizon_s
    survival = (params or {}).get("survival", SurvivalParams())
    for name in fast:
        bound = kernel_ulps(name, horizon, survival.escape_time_s)
        assert_within_ulps(fast[name], slow[name], bound, f"kernel vs numpy: {name}")


def assert_close_to_reference(fast: dict, slow: dict, label: str = "") -> None:
    """The reference's tolerances (module doc): a different order of operations."""
    for name in fast:
        a, b = fast[name], slow[name]
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=f"{label}{name}")
        m = ~np.isnan(a)
        a, b = a[m], b[m]
        if name in STOCHASTIC:
            tiny = (a < 1e-300) | (b < 1e-300)
            np.testing.assert_allclose(a[tiny], b[tiny], rtol=0, atol=1e-300, err_msg=name)
            err = np.abs(np.log10(a[~tiny]) - np.log10(b[~tiny]))
            assert np.all(err <= 1e-6), f"{label}{name}: log10 error {err.max()}"
        else:
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=0, err_msg=f"{label}{name}")


def assert_oracles(frame: Frame, params=None, prediction=None, reference: bool = True) -> dict:
    fast = evaluate(frame, None, params, prediction=prediction)
    slow = evaluate_numpy(frame, None, params, prediction=prediction)
    assert_numpy_contract(fast, slow, params, prediction)
    if reference:
        slow = reference_evaluate(frame, None, params, prediction=prediction)
        slow = settle_rounding_touches(fast, slow, frame, params, prediction)
        assert_close_to_reference(fast, slow, "reference: ")
    return fast


# ---------------------------------------------------------------------- random frames
@pytest.mark.exactness
@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(235345)  # a touch within rounding: the kernel follows the distance (oracle_ties)
def test_hypothesis_frames_match_numpy_and_reference(seed):
    assert_oracles(random_frame(np.random.default_rng(seed)), prediction=SHORT)


OTHER = {
    "closest_encounter": ClosestEncounterParams(encounter_time_max_s=math.inf),  # keep d_E
    "headway": HeadwayParams(tau_s=2.5, on_path_tolerance_m=3.0, encounter_time_max_s=1.0),
    "headway_2d": Headway2DParams(tau_s=0.7, on_path_tolerance_m=0.5),
    "circles": CirclesParams(n_circles=4, sigma_scale=1.5, radius_rule="width"),
    "survival": SurvivalParams(escape_time_s=1.3),
}
GROWING = UncertaintyTable(
    vehicle=KindUncertainty(
        sigma0_lon_m=0.6, sigma0_lat_m=0.3, growth_lon=0.1, growth_lat=0.05,
        sigma_max_lon_m=4.0, sigma_max_lat_m=1.0, time_growth_lon_mps=0.3,
        time_growth_lat_mps=0.1,
    ),
    pedestrian=KindUncertainty(
        sigma0_lon_m=0.1, sigma0_lat_m=0.1, growth_lon=0.0, growth_lat=0.0,
        sigma_max_lon_m=2.0, sigma_max_lat_m=2.0, time_growth_lon_mps=0.5,
        time_growth_lat_mps=0.5,
    ),
)  # fmt: skip


@pytest.mark.exactness
@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
@example(41)  # a touch within rounding that the kernel and the reference both call a miss
def test_every_baseline_choice_is_honoured(seed):
    """Encounter rule, circle radii, escape time, horizon/step and a time-based growth of
    the uncertainty: the kernel follows both oracles on each."""
    pred = PredictionSettings(horizon_s=4.0, dt_s=0.5, uncertainty=GROWING)
    assert_oracles(random_frame(np.random.default_rng(seed)), OTHER, pred)


@pytest.mark.exactness
def test_time_growth_reaches_standing_agents():
    """g_t > 0 widens the Gaussian of an agent that stands now (k v s is 0 for it)."""
    f = Frame.from_arrays(
        np.array([[0.0, 0.0], [6.0, 3.0]]), np.zeros(2), np.zeros(2), np.full(2, 4.0),
        np.full(2, 2.0), [np.array([[0.0, 0.0]]), np.array([[6.0, 3.0]])], ego=0,
    )  # fmt: skip
    still = evaluate(f, ["gaussian"], prediction=SHORT)["gaussian"][1]
    grow = PredictionSettings(horizon_s=3.0, dt_s=0.25, uncertainty=GROWING)
    spread = assert_oracles(f, prediction=grow)["gaussian"][1]
    assert spread > 10 * still  # wider Gaussians overlap more at this distance


def test_encounter_rules():
    """Still closing at T: 0 under the paper's rule (s_max = T), eps / (eps + d_E) when
    d_E is kept (s_max = inf)."""
    f = Frame.from_arrays(
        np.array([[0.0, 0.0], [100.0, 0.0]]), np.array([0.0, math.pi]), np.array([1.0, 1.0]),
        np.zeros(2), np.zeros(2), [np.array([[0.0, 0.0], [1.0, 0.0]]),
        np.array([[100.0, 0.0], [99.0, 0.0]])], ego=0,
    )  # fmt: skip
    paper = evaluate(f, ["closest_encounter"], prediction=SHORT)["closest_encounter"][1]
    keep = ClosestEncounterParams(encounter_time_max_s=math.inf)
    kept = evaluate(f, ["closest_encounter"], {"closest_encounter": keep}, prediction=SHORT)
    assert paper == 0.0
    assert kept["closest_encounter"][1] == pytest.approx(1.0 / (1.0 + 94.0))  # 100 - 2 * 3


@pytest.mark.exactness
def test_lane_frames_match_numpy_within_the_contract():
    """The benchmark's intersection frames (T = 12 s, dt = 0.1 s): every model within the
    contract's ulps of the numpy code (up to 2 ulps apart on AVX-512, 0 here with numpy's
    baseline code: benchmarks/ulp_table.py)."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_models import random_frame as lane_frame

    rng = np.random.default_rng(5)
    for n in (2, 40, 120):
        f = lane_frame(n, rng)
        fast, slow = evaluate(f), evaluate_numpy(f)
        assert list(fast) == list(MODELS)
        assert_numpy_contract(fast, slow)


@pytest.mark.exactness
@pytest.mark.parametrize("gap_m", [10.0, 15.0, 20.0, 25.0])
def test_tiny_overlaps_stay_nonzero_and_follow_numpy(gap_m):
    """Far apart, every step's P_o is tiny (the kernel computes exp at few of them): the
    Gaussian risk is still the maximum (not 0) and survival the numpy value, within the
    contract's ulps (numpy's exp may differ from the C library's in the last bit)."""
    f = Frame.from_arrays(
        np.array([[0.0, 0.0], [0.0, gap_m]]), np.zeros(2), np.array([8.0, 8.0]),
        np.full(2, 4.5), np.full(2, 1.9),
        [np.array([[0.0, 0.0], [200.0, 0.0]]), np.array([[0.0, gap_m], [200.0, gap_m]])],
        ego=0,
    )  # fmt: skip
    fast = evaluate(f, STOCHASTIC)
    slow = evaluate_numpy(f, STOCHASTIC)
    for name in STOCHASTIC:
        assert 0.0 < slow[name][1] < 1e-20, name
        assert 0.0 < fast[name][1] < 1e-20, name
    assert_numpy_contract(fast, slow)


@pytest.mark.exactness
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_each_stochastic_model_alone_equals_it_with_the_other(seed):
    """Asked alone, the Gaussian (and survival) skip exp at other steps than asked
    together: the values stay the same, bit for bit (the same compiled code), and follow
    numpy within the contract."""
    f = random_frame(np.random.default_rng(seed))
    both = evaluate(f, STOCHASTIC)
    for name in STOCHASTIC:
        alone = evaluate(f, [name])[name]
        assert_exact(alone, both[name], name)
    assert_numpy_contract(both, evaluate_numpy(f, STOCHASTIC))


# ---------------------------------------------------------------------- degenerate frames
def test_ego_alone_and_all_invalid():
    alone = Frame.from_arrays(
        np.zeros((1, 2)), [0.0], [3.0], [4.0], [2.0], [np.array([[0.0, 0.0]])], ego=0
    )
    for name, r in evaluate(alone).items():
        assert r.shape == (1,) and np.isnan(r).all(), name
    f = random_frame(np.random.default_rng(3))
    invalid = Frame.from_padded(
        **{
            k: getattr(f, k)
            for k in ("ids", "kinds", "xy", "heading", "speed", "length", "width", "paths")
        },
        valid=np.arange(f.n_agents) == f.ego,
        path_points=f.path_points,
        path_agent=f.path_agent,
        ego=f.ego,
    )
    for name, r in evaluate(invalid).items():
        assert np.isnan(r).all(), name


@pytest.mark.exactness
def test_zero_length_paths_and_coincident_agents():
    """One-point paths, repeated points, standing and moving agents, and agents placed
    exactly on the ego (same point, same path)."""
    p = np.array([[5.0, 5.0]])
    rep = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    f = Frame.from_arrays(
        np.array([[0.0, 0.0], [5.0, 5.0], [0.0, 0.0], [0.0, 0.0], [5.0, 5.0]]),
        np.array([0.3, 1.0, 0.3, 2.0, -1.0]),
        np.array([4.0, 0.0, 4.0, 2.0, 3.0]),
        np.array([4.0, 0.5, 4.0, 0.0, 1.0]),
        np.array([2.0, 0.5, 2.0, 0.0, 1.0]),
        [rep, p, rep, np.array([[0.0, 0.0]]), [p, np.array([[5.0, 5.0], [5.0, 5.0]])]],
        ego=0,
        kinds=["vehicle", "pedestrian", "vehicle", "other", "cyclist"],
    )
    r = assert_oracles(f, prediction=SHORT)
    assert r["current_distance"][2] == 1.0 and r["path_distance"][2] == 1.0


@pytest.mark.exactness
def test_two_thousand_agents():
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
    from bench_models import random_frame as lane_frame

    f = lane_frame(2000, np.random.default_rng(9))
    fast = assert_oracles(f, prediction=SHORT, reference=False)
    assert all(np.isfinite(v[f.others]).all() for v in fast.values())


def test_baseline_threshold_is_a_parameter():
    r = np.array([np.nan, 1e-30, 1e-25, 1e-20])
    np.testing.assert_array_equal(baseline_mask(r), [False, False, True, True])
    np.testing.assert_array_equal(baseline_mask(r, threshold=1e-31), [False, True, True, True])
    assert BASELINE_THRESHOLD == 1e-25


# ---------------------------------------------------------------------- compile cost
#: Source that builds ``f``, a two-agent frame, for the tests that run a new process.
TWO_AGENTS = (
    "f = Frame.from_arrays(np.array([[0.0, 0.0], [5.0, 0.0]]), np.zeros(2), np.ones(2), "
    "np.ones(2), np.ones(2), [np.array([[0.0, 0.0], [1.0, 0.0]]), "
    "np.array([[5.0, 0.0], [6.0, 0.0]])], ego=0); "
)


#: Prints, as JSON, how many compiled versions the cache folder holds per kernel function
#: (0: none).
COUNT_COMPILED = (
    "import json, numba; from risk import kernel_numba as k; print(json.dumps({n: "
    "len(d._cache._cache_file._load_index()) for n, d in vars(k).items() "
    "if isinstance(d, numba.core.registry.CPUDispatcher)}))"
)
#: _pw_leaf and _interp are also called with a literal 0 (risk/kernel_numba.py says why).
TWO_VERSIONS = {"_pw_leaf", "_interp"}


def compiled_versions(env: dict[str, str]) -> dict[str, int]:
    counts = subprocess.run(
        [sys.executable, "-c", COUNT_COMPILED], env=env, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert counts.returncode == 0, counts.stderr
    return {name: n for name, n in json.loads(counts.stdout).items() if n}


@pytest.mark.slow
def test_cold_cache_compiles_once_then_loads(tmp_path):
    """A fresh NUMBA_CACHE_DIR: the first process says it compiles and fills the folder,
    half of the inner functions in a process beside it (on two or more cores), which has
    ended when evaluate returns; the second loads the kernels silently."""
    code = (
        "import numpy as np; from risk import Frame, evaluate, kernel; " + TWO_AGENTS + "\n"
        "started = []\n"
        "def spy(c, cascade):\n"
        "    started.append(kernel_start(c, cascade=cascade))\n"
        "    return started[-1]\n"
        "kernel_start, kernel._start_beside = kernel._start_beside, spy\n"
        "print(repr(evaluate(f)['survival'][1]))\n"
        "print([None if p is None else p.poll() for p in started])"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "RISKREPLAY_KERNEL": "jit"}
    runs = [
        subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600
        )
        for _ in range(2)
    ]
    for run in runs:
        assert run.returncode == 0, run.stderr
    assert "compiling the risk kernels" in runs[0].stderr
    assert "compiling" not in runs[1].stderr
    risks = [run.stdout.splitlines()[0] for run in runs]
    assert risks[0] == risks[1]
    beside = [run.stdout.splitlines()[1] for run in runs]
    assert beside == (["[0]", "[None]"] if (os.cpu_count() or 1) >= 2 else ["[None]"] * 2)
    assert any(tmp_path.rglob("*.nbi")) and any(tmp_path.rglob("*.nbc"))
    # Each function evaluate_agents calls was compiled once (in one of the two processes),
    # with the types it passes; the cascade's own were not compiled.
    compiled = compiled_versions(env)
    inner = set(kernel._INNER[kernel.HERE] + kernel._INNER[kernel.BESIDE])
    assert inner <= set(compiled)
    assert not set(kernel._INNER[kernel.CASCADE]) & set(compiled)
    assert {n: c for n, c in compiled.items() if c != (2 if n in TWO_VERSIONS else 1)} == {}


def test_warm_up_covers_the_cascade(tmp_path):
    """After warm_up in one process, a second process runs evaluate and the fused cascade
    without compiling (so workers started after warm_up load every kernel)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    first = subprocess.run(
        [sys.executable, "-c", "from risk import kernel; kernel.warm_up()"],
        env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert first.returncode == 0, first.stderr
    assert "compiling the risk kernels" in first.stderr
    code = (
        "import numpy as np; from risk import Frame, evaluate; "
        "from risk.cascade import CascadeConfig, run_cascade; "
        + TWO_AGENTS
        + "evaluate(f); print(run_cascade(f, CascadeConfig.default()).tier)"
    )
    second = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600
    )
    assert second.returncode == 0, second.stderr
    assert "compiling" not in second.stderr
    # Each kernel function was compiled once per signature its callers use: the inner
    # functions that warm_up compiles first (risk.kernel._INNER) had the callers' types.
    compiled = compiled_versions(env)
    assert {n for names in kernel._INNER.values() for n in names} <= set(compiled)
    assert {n: c for n, c in compiled.items() if c != (2 if n in TWO_VERSIONS else 1)} == {}


def test_first_call_skips_numbas_blas_probe_but_blas_still_compiles():
    """Loading the kernels does not import scipy.linalg (numba's BLAS probe, 0.3-0.6 s per
    process, is answered from the installed files), and code that does use BLAS still
    compiles and runs afterwards, importing scipy's BLAS then."""
    code = (
        "import sys, numpy as np, numba; from risk import Frame, evaluate; "
        + TWO_AGENTS
        + "evaluate(f); "
        "print('scipy.linalg' in sys.modules); "
        "dot = numba.njit(lambda a, b: np.dot(a, b)); "
        "print(dot(np.arange(3.0), np.ones(3)), 'scipy.linalg.cython_blas' in sys.modules)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "3.0", "True"]


def test_the_parameter_vectors_follow_the_registry_layout():
    """pack_params puts each model's numbers (ModelSpec.kernel_args) where the generated
    layout says, and only there."""
    from risk import kernel, kernel_shared, registry, stochastic, temporal

    chosen = registry.resolve_params(
        {
            "headway": temporal.HeadwayParams(tau_s=2.5, encounter_time_max_s=None),
            "headway_2d": temporal.Headway2DParams(encounter_time_max_s=3.0),
            "circles": stochastic.CirclesParams(n_circles=5, radius_rule="width"),
            "survival": stochastic.SurvivalParams(escape_time_s=4.0),
        }
    )
    floats, ints = kernel.pack_params(chosen, 12.0, 0.1)
    at, int_at = kernel_shared.FLOAT_AT, kernel_shared.INT_AT
    assert floats.shape == (len(at),) and ints.shape == (len(int_at),)
    assert floats[at["headway", "tau"]] == 2.5
    assert floats[at["headway", "encounter_limit"]] == 12.0  # None: the horizon
    assert floats[at["headway_2d", "encounter_limit"]] == 3.0
    assert floats[at["survival", "dt_over_escape_time"]] == 0.1 / 4.0
    assert ints[int_at["circles", "n_circles"]] == 5
    assert ints[int_at["circles", "radius_rule"]] == registry.RADIUS_RULES.index("width")
    for name in registry.MODELS:
        if "epsilon" in registry.MODELS[name].kernel_args.floats:
            assert floats[at[name, "epsilon"]] == chosen[name].epsilon_m
    # every index used once, models in registry order
    assert sorted(at.values()) == list(range(len(at)))
    assert [n for n, _ in at] == sorted((n for n, _ in at), key=list(registry.MODELS).index)
    assert tuple(registry.MODELS) == kernel.SLOTS


def test_the_compile_notice_names_whose_kernels_compile(caplog, monkeypatch):
    """One notice per family of kernels and process: the risk kernels, another module's
    compiled with the same decorator (pdm's), never numba's own helpers."""
    from types import SimpleNamespace

    from numba.core import event

    from risk import kernel_jit

    monkeypatch.setattr(kernel_jit._CompileNotice, "said", set())

    def compiled(module: str) -> event.Event:
        py_func = SimpleNamespace(__module__=module)
        return event.Event(
            "numba:compile",
            event.EventStatus.START,
            {"dispatcher": SimpleNamespace(py_func=py_func)},
        )

    notice = kernel_jit._CompileNotice()
    with caplog.at_level("WARNING", logger="risk"):
        for module in ("numba.np.arraymath", "replay.planning.pdm_kernel", "risk.kernel_numba"):
            notice.on_start(compiled(module))
            notice.on_start(compiled(module))  # the second of a family says nothing
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2, said
    assert "compiling the kernels of replay.planning.pdm_kernel once" in said[0]
    assert "compiling the risk kernels once" in said[1]
