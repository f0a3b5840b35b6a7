"""The exactness contract: which results agree bit for bit, and which within how many ulps.

**Exact** (``==``, NaN where NaN): both sides run the same compiled code on one machine.
A model asked alone or with the others, the same call twice, the ahead-of-time kernel
against the just-in-time one built here, the fused cascade against the staged cascade
on the kernel, a cached result against a fresh one. Nothing may differ there; a 1-ulp
difference is a bug (a skipped ``exp`` that mattered, a changed operation order).

**Within ulps** (:data:`KERNEL_VS_NUMPY_ULPS`): the compiled kernel against the vectorised
numpy modules (``risk.registry.evaluate_numpy``). Both do the same IEEE operations in the
same order (no FMA contraction: numba compiles without fastmath), but the library
functions come from different code. The kernel calls the C library's ``exp``, ``sin``,
``cos`` and ``hypot`` (numba's ``math``). numpy picks its own SIMD versions at run time by
what the CPU offers. With AVX-512 (numpy's ``X86_V4``/``AVX512_ICL``), numpy's float64 ``exp``, ``log``
and ``arctan2`` differ from glibc's in the last bit on some inputs (``exp``: 4.6 % of
200,000 inputs in [-700, 5], numpy 2.4 on an AMD EPYC). With AVX2 or less, numpy falls
back to the C library and the two agree bit for bit. So agreement in the last bit is a
property of one CPU, not of the code.

How a last-bit difference of ``exp`` grows, model by model:

- ``gaussian``: ``P_o = exp(-q/2) / (2 pi sqrt(det))`` with ``q`` and ``det`` computed
  alike on both sides: one ``exp`` (each side within 1 ulp of the true value: glibc's
  within 0.52, numpy's AVX-512 one within 0.77 by its construction; so at most 2 ulps,
  a relative 2^-51, apart) and one division (a relative 2^-53 each side): a relative
  difference of up to 3 * 2^-52, which is up to 6 ulps of the result (an ulp is between
  2^-53 and 2^-52 of a value, by where it lies in its binade). The maximum over steps
  keeps the error of the element it picks: 6 ulps.
- ``survival``: ``R_S = sum_k P_k S_k`` with ``S_k = exp(-L_k)``, ``L_k`` the running sum
  of ``P_j + dt/tau`` over up to 120 steps (default horizon 12 s, dt 0.1 s). A
  difference of ``P_j`` in its last bit can round ``L_k`` to the neighbouring float, one
  ulp of ``L_k``: an absolute change of up to ``L_k * 2^-52``, which ``exp`` turns into a
  relative change of the same size in ``S_k``, that is ``L_k`` ulps. ``L_k`` grows to
  ``n dt / tau`` (30 with the defaults) plus the summed overlaps, and several steps may
  round differently: the bound is :func:`survival_ulps`, ``8 + 2 * L_max``: the
  Gaussian's 6 ulps for ``P_k``, 2 for the products and the sum, and one step of the
  running sum rounded the other way at its largest, where ``L_max`` is the largest
  hazard sum (``horizon / tau_esc``, plus 1 for the overlaps). The terms of the sum are
  all positive, so their relative errors do not grow when they are added.
- the seven distance and time models call no ``exp``, and numpy's ``sqrt``, ``hypot``,
  ``sin`` and ``cos`` are the C library's on x86 (or exact, ``sqrt``). But the kernel's
  pruned search for the least path distance may reach it through another of two
  candidate distances that are equal in exact arithmetic and rounded each its own way:
  2 ulps on one agent of 4130 (path and trajectory distance, lane frame N = 120, seed
  102), on every CPU setting alike. 4 ulps: two such roundings.

Measured (``benchmarks/ulp_table.py``, 250 frames, 4130 agents): at most 2 ulps with
numpy's AVX-512 ``exp`` (the Gaussian and survival analysis), 0 with its baseline code,
the same with the kernel compiled for a generic CPU; with an ``exp`` moved by up to one
more float at random (:func:`numpy_exp_off_by`: 2 floats from the C library's), 4 for
the Gaussian and 20 for survival analysis (the rounding of ``log S`` at work).

Values below :data:`FLOOR` (1e-300) are measured in ulps of :data:`FLOOR`, not of
themselves: there ``exp``'s result is subnormal (fewer than 53 significant bits), and a
last-bit change of a subnormal divided by ``2 pi sqrt(det) < 1`` is many ulps of a normal
result. Above it, ulps are relative: a survival risk of 1e-15 has ulps of 1e-31 and is
compared as strictly as a risk of 0.5.

**Decisions** (kept or dropped by a stage, the tiers, the baseline, ROC points) on two
results that agree within ulps agree exactly, except where a value lies within that
tolerance of the threshold it is compared with. :func:`near` finds those agents, so a
test can leave them out by name and count them, instead of assuming the tie never
happens.
"""

from __future__ import annotations

import math

import numpy as np

#: Below this magnitude, differences are counted in ulps of FLOOR (see the module doc).
FLOOR = 1e-300
_INT64_MIN = np.int64(-(2**63))

#: The compiled kernel against the numpy modules, per model (see the module doc).
KERNEL_VS_NUMPY_ULPS: dict[str, float] = {
    "current_distance": 4,
    "path_distance": 4,
    "trajectory_distance": 4,
    "closest_encounter": 4,
    "headway": 4,
    "headway_2d": 4,
    "circles": 4,
    "gaussian": 6,
}


def survival_ulps(horizon_s: float, escape_time_s: float) -> float:
    """The kernel-against-numpy bound of survival analysis, in ulps: ``8 + 2 * L_max``
    with ``L_max = horizon / tau_esc + 1`` the largest log-survival sum (module doc)."""
    return 8.0 + 2.0 * (horizon_s / escape_time_s + 1.0)


def kernel_ulps(name: str, horizon_s: float = 12.0, escape_time_s: float = 0.4) -> float:
    """The bound of model ``name`` (the survival bound needs the horizon and tau_esc)."""
    if name == "survival":
        return survival_ulps(horizon_s, escape_time_s)
    return KERNEL_VS_NUMPY_ULPS[name]


def _ordered(x: np.ndarray) -> np.ndarray:
    """float64 -> int64 in the order of the floats: consecutive floats differ by 1, and
    +0.0 and -0.0 both map to 0."""
    i = np.ascontiguousarray(x, dtype=np.float64).view(np.int64)
    return np.where(i < 0, _INT64_MIN - i, i)


def ulp_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """How many float64 steps apart ``a`` and ``b`` are, element by element (float64).

    0 where both are NaN or equal (also an infinity against the same infinity); ``inf``
    where only one is NaN, where only one is infinite, or where they are infinities of
    opposite sign. Magnitudes below :data:`FLOOR` are counted in steps of the float
    spacing at FLOOR."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a, b = np.broadcast_arrays(a, b)
    with np.errstate(invalid="ignore", over="ignore"):
        oa, ob = _ordered(a), _ordered(b)
        same_sign = (oa >= 0) == (ob >= 0)
        # Same sign: the int64 difference cannot overflow. Opposite signs: it may, but
        # then it is the sum of two magnitudes, exact as a float while below 2^53.
        steps = np.where(
            same_sign,
            np.abs(np.where(same_sign, oa - ob, 0)).astype(np.float64),
            np.abs(oa).astype(np.float64) + np.abs(ob).astype(np.float64),
        )
        tiny = (np.abs(a) < FLOOR) | (np.abs(b) < FLOOR)
        steps = np.where(tiny, np.abs(a - b) / np.spacing(FLOOR), steps)
        nan_a, nan_b = np.isnan(a), np.isnan(b)
        inf_a, inf_b = np.isinf(a), np.isinf(b)
        mismatch = (nan_a != nan_b) | ((inf_a | inf_b) & (a != b) & ~(nan_a | nan_b))
        steps = np.where(nan_a & nan_b, 0.0, steps)
        return np.where(mismatch, np.inf, steps)


def max_ulps(a: np.ndarray, b: np.ndarray) -> float:
    """The largest :func:`ulp_distance` (0 for empty arrays)."""
    d = ulp_distance(a, b)
    return float(d.max()) if d.size else 0.0


def assert_within_ulps(
    actual: np.ndarray, desired: np.ndarray, ulps: float, label: str = ""
) -> None:
    """``actual`` and ``desired`` have NaN at the same places, the same infinities, and
    every other pair within ``ulps`` (see :func:`ulp_distance`)."""
    actual = np.asarray(actual, dtype=np.float64)
    desired = np.asarray(desired, dtype=np.float64)
    assert actual.shape == desired.shape, f"{label}: shapes {actual.shape} != {desired.shape}"
    d = ulp_distance(actual, desired)
    bad = d > ulps
    if bad.any():
        idx = np.flatnonzero(bad.ravel())
        shown = ", ".join(
            f"[{i}] {float(actual.flat[i])!r} vs {float(desired.flat[i])!r} ({d.flat[i]:g} ulps)"
            for i in idx[:5]
        )
        more = f" and {idx.size - 5} more" if idx.size > 5 else ""
        raise AssertionError(
            f"{label}: {idx.size} values more than {ulps:g} ulps apart: {shown}{more}"
        )


def assert_exact(actual: np.ndarray, desired: np.ndarray, label: str = "") -> None:
    """Bit for bit (NaN where NaN): for results of the same compiled code."""
    np.testing.assert_array_equal(actual, desired, err_msg=label, strict=True)


def near(values: np.ndarray, threshold: float, ulps: float) -> np.ndarray:
    """Where a value lies within ``ulps`` of ``threshold`` (so that another computation
    within ``ulps`` of it may fall on the other side); False for NaN."""
    v = np.asarray(values, dtype=np.float64)
    if not math.isfinite(threshold):
        return np.zeros(v.shape, dtype=bool)
    return ulp_distance(v, np.full(v.shape, threshold)) <= ulps


class _NumpyWithExp:
    """numpy, except ``exp``: stands in for the ``np`` of a module under test."""

    def __init__(self, exp):
        self.exp = exp

    def __getattr__(self, name: str):
        return getattr(np, name)


def exp_off_by(ulps: int, rng: np.random.Generator):
    """An ``np.exp`` whose results move by up to ``ulps`` floats either way, at random:
    the ``exp`` of another CPU's numpy. Exact results (0, 1, inf) stay as they are, as
    they do in every ``exp``."""

    def exp(x, out=None):
        r = np.exp(x, out=out)
        flat = r.reshape(-1)
        steps = rng.integers(-ulps, ulps + 1, flat.size)
        moved = np.isfinite(flat) & (flat != 0.0) & (flat != 1.0)
        for k in range(1, ulps + 1):
            up = moved & (steps >= k)
            down = moved & (steps <= -k)
            flat[up] = np.nextafter(flat[up], np.inf)
            flat[down] = np.nextafter(flat[down], 0.0)
        return r

    return exp


def numpy_exp_off_by(ulps: int, rng: np.random.Generator):
    """A context in which the numpy models (``risk.stochastic``) use :func:`exp_off_by`."""
    from unittest.mock import patch

    import risk.stochastic

    return patch.object(risk.stochastic, "np", _NumpyWithExp(exp_off_by(ulps, rng)))


def rank_ties(values: np.ndarray, ulps: float) -> np.ndarray:
    """Where a value lies within ``ulps`` of another one (so that two computations, each
    within ``ulps / 2`` of the other's, may rank the two either way); False for NaN."""
    v = np.asarray(values, dtype=np.float64)
    out = np.zeros(v.shape, dtype=bool)
    idx = np.flatnonzero(~np.isnan(v))
    if idx.size < 2:
        return out
    order = idx[np.argsort(v[idx], kind="stable")]
    close = ulp_distance(v[order[1:]], v[order[:-1]]) <= ulps
    out[order[1:][close]] = True
    out[order[:-1][close]] = True
    return out


def cascade_ties(risks: dict[str, np.ndarray], config, ulps_of) -> np.ndarray:
    """Agents whose cascade decisions another computation within the contract may take the
    other way: a stage model's risk within ``ulps_of(model)`` of the stage threshold, the
    survival risk within ``ulps_of("survival")`` of the baseline or a tier threshold, or,
    where a tier has a cap and the risk reaches a capped tier's threshold, within twice
    that of another such agent's (the ranking).

    ``risks``: model name -> ``(N,)`` risks of one side; ``config``: a
    ``risk.cascade.CascadeConfig``."""
    survival = risks["survival"]
    ties = np.zeros(survival.shape, dtype=bool)
    for stage in config.stages:
        ties |= near(risks[stage.model], stage.threshold, ulps_of(stage.model))
    tol = ulps_of("survival")
    for threshold in (config.baseline_threshold, *(t.min_survival_risk for t in config.tiers)):
        ties |= near(survival, threshold, tol)
    capped = [t.min_survival_risk for t in config.tiers if t.max_agents is not None]
    if capped:  # (below every capped tier's threshold the ranking decides nothing)
        contend = np.nan_to_num(survival, nan=-1.0) >= min(capped)
        ties |= contend & rank_ties(np.where(contend, survival, np.nan), 2 * tol)
    return ties


def score_ties(scores: np.ndarray, other: np.ndarray, ulps: float) -> np.ndarray:
    """Agents whose place in a ROC sweep may differ between two computations of the same
    scores: a distinct value of ``scores`` within ``2 * ulps`` of the next one (the order
    may flip), or a group of equal ``scores`` whose ``other`` values are not all equal (one
    ROC point on one side, several on the other). False for NaN."""
    s = np.asarray(scores, dtype=np.float64)
    o = np.asarray(other, dtype=np.float64)
    out = np.zeros(s.shape, dtype=bool)
    valid = ~np.isnan(s)
    if not valid.any():
        return out
    values, group = np.unique(s[valid], return_inverse=True)
    lo = np.full(values.size, np.inf)
    hi = np.full(values.size, -np.inf)
    np.minimum.at(lo, group, o[valid])
    np.maximum.at(hi, group, o[valid])
    out[valid] = (rank_ties(values, 2 * ulps) | (lo != hi))[group]
    return out
