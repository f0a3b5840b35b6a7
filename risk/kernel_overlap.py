"""The kernel's stochastic models of one prediction pair: the Gaussian overlap's exponents
and determinants, the 2D Gaussian risk and survival analysis from them (as
:mod:`risk.stochastic`), with ``exp`` only at the steps that can change a result."""

from __future__ import annotations

import math

from risk.kernel_jit import _inner
from risk.kernel_shared import EXP_ZERO, INF


@_inner
def _escape_track(n_steps, dt_tau, escape_log_s, escape_s):
    """``escape_log_s[k]``: the survival loop's ``log_s`` before step ``k`` when every
    earlier ``P_o + dt/tau`` rounds to ``dt/tau`` (always so far from the ego);
    ``escape_s[k] = exp(-escape_log_s[k])``. The loop looks ``exp(-log_s)`` up here
    whenever ``log_s == escape_log_s[k]`` (the same argument, so the same value) instead
    of computing it."""
    log_s = 0.0
    for k in range(n_steps):
        escape_log_s[k] = log_s
        escape_s[k] = math.exp(-log_s)
        log_s += 0.0 + dt_tau


@_inner
def _pair_q(
    pred_x,
    pred_y,
    pred_cov_xx,
    pred_cov_xy,
    pred_cov_yy,
    m,
    ego_px,
    ego_py,
    ego_cov_xx,
    ego_cov_xy,
    ego_cov_yy,
    e,
    n_steps,
    qs,
    dets,
):
    """The exponent ``q_k = -1/2 dmu^T S^-1 dmu`` and ``det S`` of the Gaussian overlap
    at every step of one prediction pair (the agent's row ``m``, the ego's row ``e``;
    ``S`` the summed covariance), as
    risk.stochastic._overlap computes them; returns the least ``det`` (NaN ignored).
    The loop has no reduction, so it compiles to SIMD code."""
    for k in range(n_steps):
        rx = pred_x[m, k] - ego_px[e, k]
        ry = pred_y[m, k] - ego_py[e, k]
        sxx = pred_cov_xx[m, k] + ego_cov_xx[e, k]
        sxy = pred_cov_xy[m, k] + ego_cov_xy[e, k]
        syy = pred_cov_yy[m, k] + ego_cov_yy[e, k]
        det = sxx * syy - sxy * sxy
        q = syy * (rx * rx) - 2.0 * (sxy * (rx * ry))
        qs[k] = (q + sxx * (ry * ry)) / det * -0.5
        dets[k] = det
    m0, m1, m2, m3 = INF, INF, INF, INF  # four chains: the minimum is latency-bound
    k = 0
    while k + 4 <= n_steps:
        m0 = dets[k] if dets[k] < m0 else m0
        m1 = dets[k + 1] if dets[k + 1] < m1 else m1
        m2 = dets[k + 2] if dets[k + 2] < m2 else m2
        m3 = dets[k + 3] if dets[k + 3] < m3 else m3
        k += 4
    while k < n_steps:
        m0 = dets[k] if dets[k] < m0 else m0
        k += 1
    return min(min(m0, m1), min(m2, m3))


@_inner
def _overlap_risks(
    qs,
    dets,
    dmin,
    n_steps,
    dt_tau,
    terms,
    escape_log_s,
    escape_s,
    log_s_deferred,
    defer,
    want_g,
    want_s,
):
    """The Gaussian risk ``max_k P_o(k)`` and the survival risk ``sum_k P_o(k) S_k`` of one
    prediction pair from ``q_k``, ``det_k`` and their least ``det`` (:func:`_pair_q`),
    with ``exp`` only at the steps that can change them.

    With ``l = sqrt(min_k det_k)``, ``P_o(k) = exp(q_k) / (2 pi sqrt(det_k)) <= exp(q_k) /
    (2 pi l)`` at every step (the computed values; the rounding of ``P_o`` is covered by
    the margins below). Hence:

    1. In step order, ``log S`` is accumulated as ``log_s += P_o + dt/tau``. Where
       ``q_k < q_a = log(2^-55 dt/tau 2 pi l)``, ``P_o < 2^-55 dt/tau`` is below half an
       ulp of ``dt/tau``, so ``P_o + dt/tau == dt/tau`` in floating point: ``log S`` is
       carried on without ``P_o``, bit for bit, and the step is put aside. The other
       steps are computed as always.
    2. Of the steps put aside, the one with the largest ``q`` (for the Gaussian) and the
       one with the largest ``q - log S`` (for survival) are computed. With the steps of
       1 they give ``G``, a lower bound of the Gaussian risk, and ``T``, of the largest
       survival term.
    3. Another step put aside is computed only when ``exp(q) / (2 pi l) >= G`` (it could
       be the maximum; no other can, so the Gaussian risk stays exact) or when its
       survival term's bound ``exp(q - log S) / (2 pi l) >= T e^-46``. The terms left
       out count as 0; each is below ``1e-20`` of the sum, together below ``n_steps 1e-20``
       of it, under the sum's own rounding for any horizon below 10^4 steps.

    Without a positive finite ``min det`` every step is computed. Returns the Gaussian
    risk (meaningless when not requested) and leaves the survival terms in ``terms``:
    the survival risk is ``np_sum(terms, n_steps)``, summed by the caller (numba keeps an
    atomic reference-count increment and decrement per array argument around each call
    that LLVM does not inline)."""
    two_pi = 2.0 * math.pi
    usable = dmin > 0 and dmin < INF  # (False for NaN)
    log2pil = math.log(two_pi * math.sqrt(dmin)) if usable else 0.0
    qa = -INF  # q below it: P_o + dt/tau == dt/tau; -inf: compute every step in 1
    if usable:
        qa = math.log(dt_tau * 2.0**-55) + log2pil if want_s else INF
    gmax = -INF
    tmax = 0.0
    nd = 0
    kq, qbest = -1, -INF
    kz, zbest = -1, -INF
    log_s = 0.0
    for k in range(n_steps):
        q = qs[k]
        if q < qa:
            defer[nd] = k
            nd += 1
            log_s_deferred[k] = log_s
            terms[k] = 0.0
            if q > qbest:
                qbest, kq = q, k
            z = q - log_s
            if z > zbest:
                zbest, kz = z, k
            log_s += dt_tau  # (P_o + dt/tau == dt/tau)
            continue
        if q < EXP_ZERO:  # exp(q) is exactly 0: skip two exp and a root
            po = 0.0
            terms[k] = 0.0
        else:
            po = math.exp(q) / (math.sqrt(dets[k]) * two_pi)
            if want_s:
                t = po * (escape_s[k] if log_s == escape_log_s[k] else math.exp(-log_s))
                terms[k] = t
                tmax = max(tmax, t)
        gmax = max(gmax, po)
        log_s += po + dt_tau
    if nd == 0:
        return gmax
    gthr, sthr = INF, INF
    if want_g:
        po = 0.0
        if qbest >= EXP_ZERO:
            po = math.exp(qbest) / (math.sqrt(dets[kq]) * two_pi)
        gmax = max(gmax, po)
        # exp(q) / (2 pi l) < gmax <=> q < log(gmax) + log(2 pi l); a margin for rounding
        gthr = math.log(gmax) + log2pil - 1e-6 if gmax > 0 else EXP_ZERO
    if want_s:
        q = qs[kz]
        if q >= EXP_ZERO:
            ls = log_s_deferred[kz]
            t = math.exp(q) / (math.sqrt(dets[kz]) * two_pi)
            gmax = max(gmax, t)
            t *= escape_s[kz] if ls == escape_log_s[kz] else math.exp(-ls)
            terms[kz] = t
            tmax = max(tmax, t)
        sthr = math.log(tmax) + log2pil - 46.0 if tmax > 0 else -INF
    for d in range(nd):
        k = defer[d]
        q = qs[k]
        if q < EXP_ZERO or (want_s and k == kz):  # (kz: computed above)
            continue
        ls = log_s_deferred[k]
        need_s = want_s and q - ls >= sthr
        if not (need_s or q >= gthr):
            continue
        po = math.exp(q) / (math.sqrt(dets[k]) * two_pi)
        gmax = max(gmax, po)
        if need_s:
            terms[k] = po * (escape_s[k] if ls == escape_log_s[k] else math.exp(-ls))
    return gmax
