"""The risk kernel as the rest of :mod:`risk` calls it: the compiled production path of
:func:`risk.evaluate` and of the fused cascade, and its Python side (argument packing,
:func:`run`, :func:`warm_up`).

The code is :mod:`risk.kernel_numba`. It runs compiled in one of two forms, bit for bit
the same on one machine:

- **ahead of time** (:mod:`risk.kernel_aot`): an extension module built once into the
  cache folder by numba's ``pycc``. Loading it imports neither numba nor LLVM: about
  1 ms, against about 0.9 s for the just-in-time form in every new process;
- **just in time**: numba compiles the code on first use and caches it (``cache=True``)
  in the same folder; used until the ahead-of-time module exists for this exact source,
  numba, CPU and Python, and always with ``RISKREPLAY_KERNEL=jit``.

The replay's commands start the ahead-of-time build in the background the first time
they run on the just-in-time form (:func:`risk.kernel_aot.start_background_build`);
``python -m risk.kernel_aot_build`` builds it in the foreground.

:data:`IMPLEMENTATION` says which form this process runs. Every array argument of the
entry points must be read-only and C-contiguous with the dtype :func:`warm_up` uses (one
compiled signature; the ahead-of-time module does not check dtypes).
"""

from __future__ import annotations

import logging
import os
import pathlib
import subprocess
import sys
import time
import types
from collections.abc import Mapping
from typing import Any

import numpy as np

from risk import kernel_aot
from risk.errors import RiskError
from risk.frame import Frame
from risk.kernel_shared import (
    DT_TAU,
    FLOAT_AT,
    GAUSS,
    HAVE_CYCLE_COUNTER,
    INT_AT,
    N_CIRC,
    N_FLOAT,
    N_INT,
    N_MODELS,
    PATH,
    SLOTS,
    TRAJ,
    K,
    cache_dir,
)
from risk.registry import MODELS

__all__ = [
    "CACHE_DIR",
    "HAVE_CYCLE_COUNTER",
    "IMPLEMENTATION",
    "N_MODELS",
    "SLOTS",
    "cascade_agents",
    "corridor_keep",
    "evaluate_agents",
    "frame_arrays",
    "pack_params",
    "reachable",
    "run",
    "tiers",
    "warm_up",
]

log = logging.getLogger("risk")

#: The kernel cache folder (``NUMBA_CACHE_DIR``, else a per-user folder).
CACHE_DIR = cache_dir()
#: ``RISKREPLAY_KERNEL``: ``auto`` (the ahead-of-time module when built) or ``jit``.
KERNEL_ENV = "RISKREPLAY_KERNEL"
KERNEL_MODES = ("auto", "jit")


class KernelSettingError(RiskError):
    """``RISKREPLAY_KERNEL`` has a value the kernel does not know."""


def kernel_mode() -> str:
    mode = os.environ.get(KERNEL_ENV, "auto").strip().lower() or "auto"
    if mode not in KERNEL_MODES:
        raise KernelSettingError(
            f"{KERNEL_ENV}={mode!r} is not one of {', '.join(KERNEL_MODES)}; unset it or choose one"
        )
    return mode


def _load() -> tuple[str, types.ModuleType]:
    if kernel_mode() == "auto":
        module = kernel_aot.load(CACHE_DIR)
        if module is not None:
            return "aot", module
    from risk import kernel_numba

    return "jit", kernel_numba


#: ``"aot"`` (the ahead-of-time extension module) or ``"jit"`` (numba, just in time).
IMPLEMENTATION, _compiled = _load()
evaluate_agents = _compiled.evaluate_agents
reachable = _compiled.reachable
tiers = _compiled.tiers
corridor_keep = _compiled.corridor_keep
#: None where the CPU has no cycle counter (:data:`HAVE_CYCLE_COUNTER`) in the
#: ahead-of-time module.
cascade_agents = getattr(_compiled, "cascade_agents", None)


def _readonly(a: np.ndarray) -> np.ndarray:
    """``a`` as a read-only C-contiguous array (no copy when it already is one), so that
    every call has the same argument types and the kernel compiles once."""
    b = np.ascontiguousarray(a)
    if b.flags.writeable:
        b = b.view()
        b.flags.writeable = False
    return b


def frame_arrays(frame: Any) -> tuple[np.ndarray, ...]:
    """The frame's arrays in kernel order (xy .. path_agent), cached on the frame (frames
    are immutable)."""
    cached = frame.__dict__.get("_kernel_arrays")
    if cached is None:
        cached = tuple(
            _readonly(a)
            for a in (
                frame.xy,
                frame.heading,
                frame.speed,
                frame.length,
                frame.width,
                frame.kinds,
                frame.valid,
                frame.paths,
                frame.path_points,
                frame.path_agent,
            )
        )
        object.__setattr__(frame, "_kernel_arrays", cached)
    return cached


def pack_params(chosen: Mapping[str, Any], horizon_s: float, dt_s: float) -> tuple[np.ndarray, ...]:
    """The kernel's float and int parameter vectors from every model's parameter object:
    each model's numbers (:attr:`risk.registry.ModelSpec.kernel_args`) at the indices the
    layout gives them (:data:`risk.kernel_shared.FLOAT_AT`, ``INT_AT``)."""
    floats = np.zeros(N_FLOAT)
    ints = np.zeros(N_INT, np.int64)
    for name, spec in MODELS.items():
        args = spec.kernel_args
        values = args.values(chosen[name], horizon_s, dt_s)
        if len(values) != len(args.floats) + len(args.ints):
            raise RiskError(f"{name}: kernel_args gives {len(values)} numbers for "
                            f"{args.floats + args.ints}")  # fmt: skip
        for arg, value in zip(args.floats, values, strict=False):
            floats[FLOAT_AT[name, arg]] = value
        for arg, value in zip(args.ints, values[len(args.floats) :], strict=True):
            ints[INT_AT[name, arg]] = value
    floats.flags.writeable = False
    ints.flags.writeable = False
    return floats, ints


def _constant(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


#: ``stop2``, ``cut2`` for exact values; the empty agent list ("every valid agent").
NO_STOP = _constant(np.full(N_MODELS, -1.0))
NO_CUT = _constant(np.full(N_MODELS, np.inf))
ALL_AGENTS = _constant(np.zeros(0, np.int64))


def run(
    frame: Any,
    want: np.ndarray,
    fp: np.ndarray,
    ip: np.ndarray,
    steps: np.ndarray,
    unc: np.ndarray,
    agents: np.ndarray | None = None,
    stop2: np.ndarray | None = None,
    cut2: np.ndarray | None = None,
) -> np.ndarray:
    """Risks ``(9, N)`` of the models flagged in ``want`` for ``agents`` (default: every
    valid agent but the ego); NaN elsewhere. Every array argument must be read-only (one
    compiled signature)."""
    if agents is None:
        agents = ALL_AGENTS
    elif agents.size == 0:
        return np.full((N_MODELS, frame.n_agents), np.nan)
    if _first_evaluate:
        _before_first_evaluate()
    return evaluate_agents(
        *frame_arrays(frame),
        int(frame.ego),
        agents,
        steps,
        unc,
        want,
        fp,
        ip,
        NO_STOP if stop2 is None else stop2,
        NO_CUT if cut2 is None else cut2,
    )


def warm_up(compiled: types.ModuleType | None = None, *, build_ahead_of_time: bool = False) -> None:
    """Load every kernel entry point (or compile it: the just-in-time form on a cold
    cache), with the argument types that :func:`risk.evaluate` and the cascade use.

    Call it once in a parent process before starting workers (pytest-xdist, batch, Ray),
    so that they load the cached kernels instead of each compiling them. ``compiled``:
    the form to warm up (default: the one this process runs; :mod:`risk.kernel_aot_build`
    passes :mod:`risk.kernel_numba` to compile the signatures it builds).

    ``build_ahead_of_time``: when this process runs the just-in-time form (and
    ``RISKREPLAY_KERNEL`` is not ``jit``), start the ahead-of-time build in the background
    afterwards (:func:`risk.kernel_aot.start_background_build`), so that later processes
    start about 0.9 s faster. The replay's commands pass True."""
    c = _compiled if compiled is None else compiled
    _warm_up_calls(c)
    if (
        build_ahead_of_time
        and IMPLEMENTATION == "jit"
        and kernel_mode() == "auto"
        and getattr(_compiled, "CACHE_PROBLEM", None) is None  # (the notice said why)
    ):
        kernel_aot.start_background_build(CACHE_DIR)


def _warm_up_calls(c: types.ModuleType) -> None:
    beside = _compile_split(c, cascade=True)
    try:
        _warm_up_evaluate(c)
        _warm_up_sorting(c)  # (while the process beside compiles the cascade)
    except BaseException:  # (Ctrl-C too): end the helper rather than wait for it
        _stop(beside)
        raise
    if beside is not None:
        beside.wait()  # its kernels are in the cache now (or it failed: compiled below)
    _warm_up_cascade(c)


def _compile_split(c: types.ModuleType, *, cascade: bool) -> subprocess.Popen[bytes] | None:
    """On a cold just-in-time cache (and two or more cores), compile the inner functions
    in two processes: start the process beside (:func:`_start_beside`), compile
    ``HERE``'s (and ``CASCADE``'s when ``cascade``) here, and wait until ``BESIDE``'s are
    cached. Then returns the process beside, which goes on to compile the cascade when
    ``cascade`` (else it has ended). None when no process was started: the entry points
    then compile their inner functions here."""
    beside = _start_beside(c, cascade=cascade)
    if beside is None:
        return None
    try:
        _warm_up_inner(c, HERE)
        if cascade:
            _warm_up_inner(c, CASCADE)
            _wait_until_cached(c, BESIDE, beside)
        else:
            beside.wait()
    except BaseException:
        _stop(beside)
        raise
    return beside


def _stop(beside: subprocess.Popen[bytes] | None) -> None:
    if beside is not None:
        beside.kill()
        beside.wait()


#: Whether this process is yet to make its first ``evaluate_agents`` call on the
#: just-in-time form (see :func:`_before_first_evaluate`).
_first_evaluate = IMPLEMENTATION == "jit"


def _before_first_evaluate() -> None:
    """Before this process's first :func:`run`: on a cold just-in-time cache, compile the
    inner functions in two processes (:func:`_compile_split`), so that the call compiles
    only ``evaluate_agents`` itself. The cold first call of :func:`risk.evaluate` took
    20.5-22.7 s of wall time instead of 30.5-31.2 s in one process (README, "Compiling
    from cold"); the process beside has ended when this returns, so that no compile
    outlives a short script."""
    global _first_evaluate
    _first_evaluate = False
    _compile_split(_compiled, cascade=False)


#: The inner kernel functions compiled first on a cold cache, in this process (HERE, and
#: CASCADE before the whole warm-up) and in the one beside (BESIDE), so that the entry
#: points, compiled next, find them in the cache and each is compiled once (numba
#: compiles one function at a time per process; seconds each). Split for similar times,
#: measured with numba's compile events: ``_ego_candidates`` alone (with the path and
#: prediction functions it calls) takes as long as BESIDE.
HERE = "here"
BESIDE = "beside"
CASCADE = "cascade"  # (the cascade's own: evaluate_agents calls none of them)
_INNER = {
    HERE: ("_ego_candidates",),
    BESIDE: (
        "_polyline_distance", "_first_crossing", "_pair_q", "_escape_track", "_time_gap",
        "_overlap_risks", "_cut_boxes", "_row_starts", "_others",
    ),
    CASCADE: ("_gauss_reaches", "_reach_limits", "_reach_keep"),
}  # fmt: skip


def _warm_up_inner(c: types.ModuleType, part: str) -> None:
    """Compile the inner functions of ``_INNER[part]`` for the argument types the entry
    points pass them (contiguous float64 scratch arrays and their rows, int64 counts,
    float64 scalars, read-only frame arrays). A type that differed would compile a
    second, unused version; ``tests/test_kernel.py`` checks that none is."""
    fa, steps, unc, fp, _ = _warm_up_arguments()
    xy, heading, speed, _, _, kinds, valid, paths, path_points, path_agent = fa
    p1 = paths.shape[1] + 1
    ns = steps.shape[0]
    nch = (p1 - 1 + K - 1) // K + 1
    dt_tau = float(fp[DT_TAU])

    def line() -> np.ndarray:
        return np.zeros(p1)

    def track() -> np.ndarray:
        return np.zeros(ns)

    def boxes() -> np.ndarray:
        return np.zeros((nch, 4))

    def rows2() -> np.ndarray:  # (a path per row)
        return np.zeros((1, p1))

    def boxes3() -> np.ndarray:  # (chunk boxes per row)
        return np.zeros((1, nch, 4))

    compile_like = c.compile_like
    if part == HERE:
        compile_like(
            c._ego_candidates, xy, heading, speed, kinds, paths, path_points, 0, 0, 1, steps,
            unc, np.zeros(max(p1 - 2, 1)), nch,
        )  # fmt: skip
    elif part == CASCADE:
        compile_like(c._gauss_reaches, track(), track(), ns, 0.5, 0.0)
        compile_like(c._reach_limits, unc, kinds, 0, ns, 1e-25)
        limits = np.zeros(unc.shape[0])
        starts = np.zeros(xy.shape[0] + 1, np.int64)
        compile_like(c._reach_keep, paths, starts, 0, 0, speed, kinds, 1.0, _MAX_SPEEDS, limits)
    else:
        rows = [np.zeros((1, ns)) for _ in range(5)]  # (x, y, cov: an agent's, the ego's)
        pair = (*rows, 0, *rows, 0)
        compile_like(
            c._polyline_distance, rows2(), rows2(), 0, 2, boxes3(), 1, rows2(), rows2(), 0,
            2, boxes3(), 1, np.zeros(nch * nch), -1.0, np.inf, np.inf,
        )  # fmt: skip
        compile_like(
            c._first_crossing, line(), line(), line(), 2, boxes(), 1, line(), line(), line(),
            2, boxes(), 1,
        )  # fmt: skip
        compile_like(c._pair_q, *pair, ns, track(), track())
        compile_like(c._escape_track, ns, dt_tau, track(), track())
        compile_like(c._time_gap, 1.0, 0.0, 1.0)
        compile_like(
            c._overlap_risks, track(), track(), 1.0, ns, dt_tau, track(), track(), track(),
            track(), np.zeros(ns, np.int64), True, True,
        )  # fmt: skip
        compile_like(c._cut_boxes, line(), line(), 2, line(), 1.0, boxes(), 2, boxes())
        compile_like(c._row_starts, path_agent, xy.shape[0])
        compile_like(c._others, valid, 0)


def _wait_until_cached(
    c: types.ModuleType,
    part: str,
    other: subprocess.Popen[bytes] | None = None,
    timeout_s: float = 300.0,
) -> None:
    """Wait until the other process has cached the inner functions of ``part`` (or has
    ended, when it is ``other``, or ``timeout_s`` has passed: then whatever is missing
    compiles here)."""
    deadline = time.monotonic() + timeout_s
    names = list(_INNER[part])
    while names and time.monotonic() < deadline:
        names = [n for n in names if _cache_is_cold(getattr(c, n))]
        if names:
            if other is not None and other.poll() is not None:
                return
            time.sleep(0.1)


def _compile_beside(c: types.ModuleType, cascade: bool) -> None:
    """What the process beside compiles: its inner functions; when ``cascade``, then
    (once the other process has cached its own inner functions) the one-pass cascade,
    while the other compiles ``evaluate_agents``, the bound and the tier sort."""
    _warm_up_inner(c, BESIDE)
    if cascade:
        _wait_until_cached(c, HERE)
        _wait_until_cached(c, CASCADE)
        _warm_up_fused(c)


def _cache_is_cold(dispatcher: Any) -> bool:
    """Whether numba's cache holds no entry for this source of ``dispatcher`` (False
    when numba's layout differs: then nothing is compiled beside)."""
    try:
        return not dispatcher._cache._cache_file._load_index()
    except Exception:  # numba internals: any change means "don't know"
        return False


def _start_beside(c: types.ModuleType, *, cascade: bool) -> subprocess.Popen[bytes] | None:
    """On a cold just-in-time cache and two or more cores, start a process that compiles
    half of the inner functions and, when ``cascade``, the bound, the tier sort and then
    the cascade (:func:`_compile_beside`), while this one compiles the other half and
    then ``evaluate_agents``. numba compiles one function at a time per process, and each
    entry point would otherwise compile every inner function it calls itself (the two
    processes compiled most of them twice: 57-70 s of CPU in all, 47-53 s without,
    measured on a busy machine). None when not started (or nothing to compile: the
    entry point it leads to, ``cascade_agents`` or ``evaluate_agents``, is cached)."""
    if getattr(c, "__name__", "") != "risk.kernel_numba" or (os.cpu_count() or 1) < 2:
        return None
    if c.CACHE_PROBLEM is not None:
        return None  # nothing it compiles could be loaded from the cache
    if cascade and not HAVE_CYCLE_COUNTER:
        return None
    if not _cache_is_cold(c.cascade_agents if cascade else c.evaluate_agents):
        return None
    code = (
        "from risk import kernel, kernel_numba; "
        f"kernel._compile_beside(kernel_numba, cascade={cascade})"
    )
    try:
        return subprocess.Popen(
            [sys.executable, "-c", code],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "NUMBA_CACHE_DIR": str(CACHE_DIR), KERNEL_ENV: "jit"},
            cwd=pathlib.Path(__file__).resolve().parent.parent,
        )
    except OSError:
        return None  # this process compiles them with the entry points


def _warm_up_arguments() -> tuple[
    tuple[np.ndarray, ...], np.ndarray, np.ndarray, np.ndarray, np.ndarray
]:
    """A two-agent frame's arrays and parameters, of the types the replay passes."""
    frame = Frame.from_arrays(
        np.array([[0.0, 0.0], [8.0, 1.0]]),
        np.zeros(2),
        np.array([5.0, 3.0]),
        np.full(2, 4.5),
        np.full(2, 1.9),
        [np.array([[0.0, 0.0], [20.0, 0.0]]), np.array([[8.0, 1.0], [8.0, 20.0]])],
        ego=0,
    )
    steps = _constant(np.linspace(0.0, 1.0, 5))
    unc = _constant(np.tile([0.5, 0.3, 0.1, 0.1, 2.0, 1.0, 0.0, 0.0], (4, 1)))
    fp = np.ones(N_FLOAT)
    fp[DT_TAU] = 0.25
    ip = np.zeros(N_INT, np.int64)
    ip[N_CIRC] = 3
    ip = _constant(ip)
    return frame_arrays(frame), steps, unc, _constant(fp), ip


def _warm_up_evaluate(c: types.ModuleType) -> None:
    fa, steps, unc, fp, ip = _warm_up_arguments()
    c.evaluate_agents(  # (run)
        *fa, 0, ALL_AGENTS, steps, unc, _constant(np.ones(N_MODELS, dtype=np.bool_)), fp, ip,
        NO_STOP, NO_CUT,
    )  # fmt: skip


_MAX_SPEEDS = _constant(np.full(4, 10.0))
#: ``protected`` of :func:`cascade_agents` without a corridor stage.
NOT_PROTECTED = _NOT_PROTECTED = _constant(np.zeros(0, dtype=np.bool_))


def _warm_up_sorting(c: types.ModuleType) -> None:
    """The reachability bound and the tier sort."""
    fa, _, unc, _, _ = _warm_up_arguments()
    c.reachable(
        fa[7], fa[9], fa[2], fa[5], 0, _constant(np.array([1])), 1.0, 5, unc, _MAX_SPEEDS, 1e-25
    )
    c.tiers(  # (risk.cascade.assign_tiers; a writable copy of the risks)
        np.zeros(2), _constant(np.array([1e-25])),
        _constant(np.array([-1], dtype=np.int64)),
    )  # fmt: skip
    c.corridor_keep(*fa[:5], fa[6], fa[7], fa[8], fa[9], 0, _constant(np.ones(9)))


def _warm_up_cascade(c: types.ModuleType) -> None:
    """The reachability bound, the tier sort and the one-pass cascade."""
    _warm_up_sorting(c)
    _warm_up_fused(c)


def _warm_up_fused(c: types.ModuleType) -> None:
    """The one-pass cascade (none where the CPU has no cycle counter)."""
    if not HAVE_CYCLE_COUNTER:
        return
    fa, steps, unc, fp, ip = _warm_up_arguments()
    c.cascade_agents(
        *fa, 0, ALL_AGENTS, steps, unc, fp, ip,
        _constant(np.array([PATH, TRAJ, GAUSS], dtype=np.int64)),
        _constant(np.array([0.01, 0.01, 1e-30])), _constant(np.full(3, -1.0)),
        _constant(np.full(3, np.inf)), True, _MAX_SPEEDS, 1e-25,
        np.zeros(2),  # (writable: a row of evaluate_agents' result in the cascade)
        _constant(np.array([1e-25])), _constant(np.array([-1], dtype=np.int64)),
        _NOT_PROTECTED,
    )  # fmt: skip
