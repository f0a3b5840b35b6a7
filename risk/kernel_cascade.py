"""The kernel's entry points for the filter cascade (:mod:`risk.cascade`): the
reachability bound, the tier sort and the fused one-pass cascade."""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from risk.kernel_jit import _inner, _jit, np_sum
from risk.kernel_overlap import _escape_track, _overlap_risks, _pair_q
from risk.kernel_paths import (
    _boxes,
    _cut,
    _cut_boxes,
    _extend,
    _polyline_distance,
    _segment_lengths,
)
from risk.kernel_prediction import _ego_candidates, _others, _predict, _row_starts
from risk.kernel_shared import DT_TAU, EPS_PATH, EPS_TRAJ, EXP_ZERO, INF, PATH, TRAJ, K


@_inner
def _reach_limits(unc, kinds, ego, n_steps, threshold):
    """Per agent kind, the squared distance ``d^2`` up to which the reachability bound
    (see :func:`reachable`) keeps an agent of that kind: ``2 L (log(n / (2 pi l)) -
    log(threshold / 1000))``, from ``log bound >= log(threshold / 1000)`` (-1: none;
    ``inf`` when ``threshold`` is not positive)."""
    n_kinds = unc.shape[0]
    lim = np.empty(n_kinds)
    if not threshold > 0:
        lim[:] = INF
        return lim
    log_thr = math.log(threshold / 1000.0)
    k_e = kinds[ego]
    sm_e = max(unc[k_e, 4], unc[k_e, 5])
    s0_e = min(min(unc[k_e, 0], unc[k_e, 4]), min(unc[k_e, 1], unc[k_e, 5]))
    for k in range(n_kinds):
        big = max(unc[k, 4], unc[k, 5]) ** 2 + sm_e**2
        small = min(min(unc[k, 0], unc[k, 4]), min(unc[k, 1], unc[k, 5])) ** 2 + s0_e**2
        room = math.log(n_steps / (2.0 * math.pi * small)) - log_thr
        lim[k] = 2.0 * big * room if room >= 0 else -1.0
    return lim


@_inner
def _reach_keep(paths, starts, i, ego, speed, kinds, horizon, max_speed_by_kind, limits):
    """The reachability bound for agent ``i`` (see :func:`reachable`), with the limits of
    :func:`_reach_limits`: O(1) per pair of path rows."""
    d2 = INF
    for r in range(starts[i], starts[i + 1]):
        for re in range(starts[ego], starts[ego + 1]):
            dx = paths[r, 0, 0] - paths[re, 0, 0]
            dy = paths[r, 0, 1] - paths[re, 0, 1]
            d2 = min(d2, dx * dx + dy * dy)
    w = max(speed[i], max_speed_by_kind[kinds[i]]) + speed[ego]
    d = max(math.sqrt(d2) - w * horizon, 0.0)
    return d * d <= limits[kinds[i]]


@_jit
def reachable(
    paths,
    path_agent,
    speed,
    kinds,
    ego,
    agents,
    horizon,
    n_steps,
    unc,
    max_speed_by_kind,
    threshold,
):
    """The reachability bound of the cascade: False for agents of ``agents`` whose survival
    risk is certainly below ``threshold``; O(1) per path row.

    Positions along a path lie within ``v s`` of its first point, so the centre distance at
    any step is at least ``d = max(D0 - (w_i + v_ego) T, 0)``, ``D0`` the least distance of
    the candidates' first points and ``w_i = max(v_i, max_speed_by_kind[kind])``. With ``S`` the
    summed covariance, ``lambda_max(S) <= L = sm_i^2 + sm_e^2`` (``sm`` the largest
    ``sigma_max`` of the kind) and ``det(S) >= l^2``, ``l = s0_i^2 + s0_e^2`` (``s0`` the
    least of ``min(sigma0, sigma_max)``), so ``P_o <= exp(-d^2 / (2 L)) / (2 pi l)`` and
    ``R_S <= sum_k P_o(s_k) <= n exp(-d^2 / (2 L)) / (2 pi l)``. The agent is dropped when
    that bound is below ``threshold / 1000`` (the margin covers rounding), i.e. when
    ``d^2`` exceeds its kind's limit (:func:`_reach_limits`)."""
    n = speed.shape[0]
    starts = _row_starts(path_agent, n)
    keep = np.ones(agents.shape[0], np.bool_)
    if not threshold > 0:
        return keep
    limits = _reach_limits(unc, kinds, ego, n_steps, threshold)
    for a_idx in range(agents.shape[0]):
        keep[a_idx] = _reach_keep(
            paths, starts, agents[a_idx], ego, speed, kinds, horizon, max_speed_by_kind, limits
        )
    return keep


@intrinsic
def _cycles(typingctx):
    """The CPU's cycle counter (``llvm.readcyclecounter``: the TSC on x86; 0 where the
    target has none). Cacheable, unlike a call into C through ctypes."""

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.IntType(64), [])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.readcyclecounter")
        return builder.call(fn, [])

    return types.int64(), codegen


@_inner
def _gauss_reaches(qs, dets, n_steps, thr, qcut):
    """Whether the Gaussian overlap of one prediction pair reaches ``thr`` at some step,
    from its ``q_k`` and ``det_k`` (:func:`_pair_q`; ``P_o`` as :func:`_overlap_risks`
    computes it). Steps with ``q < qcut`` are skipped without ``exp``: there
    ``P_o < thr`` certainly (see :func:`cascade_agents`)."""
    for k in range(n_steps):
        q = qs[k]
        if q < qcut:
            continue
        po = 0.0 if q < EXP_ZERO else math.exp(q) / (math.sqrt(dets[k]) * (2.0 * math.pi))
        if po >= thr:
            return True
    return False


@_jit
def tiers(risk, tier_min, tier_cap):
    """Deepest tier of each agent, ``(K,)`` int8 from survival risks ``(K,)``; -1: none.

    Tier ``k`` holds the agents of tier ``k - 1`` whose risk is ``>= tier_min[k]``,
    capped to the ``tier_cap[k]`` riskiest (``-1``: no cap; ties: the lower index first,
    by a stable sort; NaN ranks last and reaches no tier)."""
    m = risk.shape[0]
    neg = np.empty(m)
    for j in range(m):
        neg[j] = INF if math.isnan(risk[j]) else -risk[j]
    order = np.argsort(neg, kind="mergesort")  # riskiest first; stable
    out = np.full(m, -1, np.int8)
    count = m
    for k in range(tier_min.shape[0]):
        # the members stay a prefix of the order: those with risk >= the minimum
        c = 0
        lim = -tier_min[k]
        while c < count and neg[order[c]] <= lim:
            c += 1
        count = c
        if tier_cap[k] >= 0:
            count = min(count, tier_cap[k])
        for j in range(count):
            out[order[j]] = k
    return out


@_jit
def cascade_agents(
    xy,
    heading,
    speed,
    length,
    width,
    kinds,
    valid,
    paths,
    path_points,
    path_agent,
    ego,
    agents,
    steps,
    unc,
    float_params,
    int_params,
    stage_models,
    stage_thresholds,
    stage_keep_d2,
    stage_drop_d2,
    use_bound,
    max_speed_by_kind,
    baseline_threshold,
    survival_all,
    tier_min,
    tier_cap,
    protected,
):
    """The fused cascade: one pass per agent of ``agents`` through the reachability bound
    (when ``use_bound``) and the stages (model slot ``stage_models[s]``, one of PATH, TRAJ,
    GAUSS; kept when its risk reaches ``stage_thresholds[s]``), then survival analysis for the
    survivors and their tiers (:func:`tiers`, with ``tier_min``, ``tier_cap``). Each
    agent's path is extended once and predicted once, whatever the stages.

    Distance stages are keep/drop tests (``stage_keep_d2``, ``stage_drop_d2``: see
    ``risk.cascade.keep_bounds``), the Gaussian stage stops at the first step that
    reaches the threshold and skips ``exp`` where ``q < log(2 pi l thr) - 1``: with
    ``l = s0_i^2 + s0_e^2`` (see :func:`reachable`) ``sqrt(det S) >= l`` (Minkowski's
    determinant inequality), so ``P_o <= exp(q) / (2 pi l) < thr`` there.

    ``agents``: an empty array for every valid agent but the ego. Returns ``kept``
    (S, N) bool (kept after stage ``s``), ``dropped_at`` (N,) int8 (the stage that dropped
    the agent, 0 for the bound, -1 survived or not judged), ``unreachable`` (N,) bool
    (dropped by the bound), the survivors' indices, the survival risk of the survivors
    (N,) (NaN elsewhere), the cycle counts (S + 3,) of the set-up (the ego's
    candidates), the bound, each stage and the survival analysis with the tiers (for the
    caller to share out the call's measured time), the tiers (N,) int8 (-1: none), the
    baseline (N,) bool (``survival_all >= baseline_threshold``, ``survival_all`` the
    survival risk of every agent; for agents of ``agents`` only) and the false negatives
    (S,) int64 (baseline agents not kept after stage ``s``).

    Why 26 plain arguments: numba's compiled entry points (and the ahead-of-time module
    built from them) take arrays and scalars, not Python objects, so the groups are kept
    on the Python side: the frame's arrays (:func:`risk.kernel.frame_arrays`), the
    prediction and model parameters (:func:`risk.registry.kernel_inputs`), the stages
    (``risk.cascade._Plan``: ``stage_models`` .. ``stage_drop_d2``, the tiers), and the
    baseline.

    ``protected`` (N,) bool, or empty for none: agents the corridor stage kept
    (:func:`risk.kernel_corridor.corridor_keep`); they skip the bound and the stages, are
    kept after every stage and get their survival risk and tier as survivors.

    With no tiers (``tier_min`` empty) survival analysis of the survivors is skipped:
    their survival risk stays NaN."""
    n = xy.shape[0]
    has_protected = protected.shape[0] == n
    n_st = stage_models.shape[0]
    if agents.shape[0] == 0:
        agents = _others(valid, ego)
    code = np.full(n, -2, np.int64)
    surv_out = np.full(n, np.nan)
    cycle_counts = np.zeros(n_st + 3, np.int64)
    t_prev = _cycles()
    p = paths.shape[1]
    n_points = p + 1
    n_steps = steps.shape[0]
    horizon = steps[n_steps - 1]
    n_chunks = (n_points - 1 + K - 1) // K + 1
    starts = _row_starts(path_agent, n)
    rmax = 1
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        rmax = max(rmax, starts[i + 1] - starts[i])
    # ------------------------------------------------ ego candidates
    ego_row0, e1 = starts[ego], starts[ego + 1]
    n_ego_paths = e1 - ego_row0
    seg = np.empty(max(p - 1, 1))
    u_e = unc[kinds[ego]]
    (
        ego_x,
        ego_y,
        _,
        _,
        _,
        ego_n,
        ego_boxes,
        ego_nboxes,
        ego_cut_x,
        ego_cut_y,
        ego_cut_n,
        ego_cut_boxes,
        ego_cut_nboxes,
        ego_px,
        ego_py,
        _,
        _,
        _,
        ego_cov_xx,
        ego_cov_xy,
        ego_cov_yy,
        _,
        _,
        _,
    ) = _ego_candidates(
        xy,
        heading,
        speed,
        kinds,
        paths,
        path_points,
        ego,
        ego_row0,
        n_ego_paths,
        steps,
        unc,
        seg,
        n_chunks,
    )
    s0_e = min(min(u_e[0], u_e[4]), min(u_e[1], u_e[5]))
    # ------------------------------------------------ per-agent scratch (rmax rows)
    path_x = np.empty((rmax, n_points))
    path_y = np.empty((rmax, n_points))
    path_arc = np.empty((rmax, n_points))
    path_ux = np.empty((rmax, n_points))
    path_uy = np.empty((rmax, n_points))
    path_n = np.empty(rmax, np.int64)
    path_boxes = np.empty((rmax, n_chunks, 4))
    path_nboxes = np.empty(rmax, np.int64)
    cut_x_row, cut_y_row, cut_boxes_row = (
        np.empty((1, n_points)),
        np.empty((1, n_points)),
        np.empty((1, n_chunks, 4)),
    )
    cut_x, cut_y, cut_boxes = (
        cut_x_row[0],
        cut_y_row[0],
        cut_boxes_row[0],
    )  # (row 0, also viewed once)
    row = np.int64(0)  # (their row)
    gaps = np.empty(n_chunks * n_chunks)
    pred_x = np.empty((rmax, n_steps))
    pred_y = np.empty((rmax, n_steps))
    pred_dir_x = np.empty((rmax, n_steps))
    pred_dir_y = np.empty((rmax, n_steps))
    pred_sigma_lon = np.empty((rmax, n_steps))
    pred_cov_xx = np.empty((rmax, n_steps))
    pred_cov_xy = np.empty((rmax, n_steps))
    pred_cov_yy = np.empty((rmax, n_steps))
    terms = np.empty(n_steps)
    qs = np.empty(n_steps)
    dets = np.empty(n_steps)
    log_s_deferred = np.empty(n_steps)
    defer = np.empty(n_steps, np.int64)
    extended = np.zeros(rmax, np.bool_)
    predicted = np.zeros(rmax, np.bool_)
    escape_log_s = np.empty(n_steps)
    escape_s = np.empty(n_steps)
    _escape_track(n_steps, float_params[DT_TAU], escape_log_s, escape_s)
    limits = _reach_limits(unc, kinds, ego, n_steps, baseline_threshold)
    t = _cycles()
    cycle_counts[0] += t - t_prev
    t_prev = t
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        shielded = has_protected and protected[i]
        if use_bound and baseline_threshold > 0 and not shielded:
            ok = _reach_keep(
                paths, starts, i, ego, speed, kinds, horizon, max_speed_by_kind, limits
            )
            t = _cycles()
            cycle_counts[1] += t - t_prev
            t_prev = t
            if not ok:
                code[i] = -1
                continue
        r0, r1 = starts[i], starts[i + 1]
        v = speed[i]
        ki = kinds[i]
        for m in range(r1 - r0):  # (no row or slice views: each costs reference counts)
            extended[m] = False
            predicted[m] = False
        q_pair = -1  # the pair (m n_ego_paths + e) whose q and det qs, dets hold; -1: none
        q_dmin = INF
        code[i] = n_st
        for s in range(0 if shielded else n_st):
            slot = stage_models[s]
            thr = stage_thresholds[s]
            keep = False
            if slot in (PATH, TRAJ):
                keep_d2 = stage_keep_d2[s]
                drop_d2 = stage_drop_d2[s]
                eps = float_params[EPS_PATH] if slot == PATH else float_params[EPS_TRAJ]
                if keep_d2 >= 0:  # O(1): the paths' first points bound the distance
                    d0 = INF
                    for r in range(r0, r1):
                        for e in range(n_ego_paths):
                            ddx = paths[r, 0, 0] - paths[ego_row0 + e, 0, 0]
                            ddy = paths[r, 0, 1] - paths[ego_row0 + e, 0, 1]
                            d0 = min(d0, ddx * ddx + ddy * ddy)
                    keep = d0 <= keep_d2 and eps / (eps + math.sqrt(d0)) >= thr
                for r in range(r0, r1):
                    if keep:
                        break
                    m = r - r0
                    if not extended[m]:
                        _segment_lengths(paths, r, seg)
                        path_n[m] = _extend(
                            paths,
                            r,
                            path_points[r],
                            heading[i],
                            v * horizon,
                            seg,
                            np_sum(seg, p - 1),
                            path_x,
                            path_y,
                            path_arc,
                            path_ux,
                            path_uy,
                            m,
                        )
                        path_nboxes[m] = _boxes(path_x[m], path_y[m], path_n[m], path_boxes[m])
                        extended[m] = True
                    if slot == TRAJ:
                        cut_n = _cut(path_x[m], path_y[m], path_arc[m], v * horizon, cut_x, cut_y)
                        cut_nboxes = _cut_boxes(
                            cut_x,
                            cut_y,
                            cut_n,
                            path_arc[m],
                            v * horizon,
                            path_boxes[m],
                            path_n[m],
                            cut_boxes,
                        )
                    for e in range(n_ego_paths):
                        if slot == PATH:
                            d = _polyline_distance(
                                ego_x,
                                ego_y,
                                e,
                                ego_n[e],
                                ego_boxes,
                                ego_nboxes[e],
                                path_x,
                                path_y,
                                m,
                                path_n[m],
                                path_boxes,
                                path_nboxes[m],
                                gaps,
                                keep_d2,
                                drop_d2,
                                INF,
                            )
                        else:
                            d = _polyline_distance(
                                ego_cut_x,
                                ego_cut_y,
                                e,
                                ego_cut_n[e],
                                ego_cut_boxes,
                                ego_cut_nboxes[e],
                                cut_x_row,
                                cut_y_row,
                                row,
                                cut_n,
                                cut_boxes_row,
                                cut_nboxes,
                                gaps,
                                keep_d2,
                                drop_d2,
                                INF,
                            )
                        if eps / (eps + d) >= thr:
                            keep = True
                            break
            else:  # GAUSS
                small = min(min(unc[ki, 0], unc[ki, 4]), min(unc[ki, 1], unc[ki, 5])) ** 2
                small += s0_e**2
                qcut = math.log(thr * (2.0 * math.pi) * small) - 1.0 if thr > 0 else -INF
                for r in range(r0, r1):
                    if keep:
                        break
                    m = r - r0
                    if not extended[m]:
                        _segment_lengths(paths, r, seg)
                        path_n[m] = _extend(
                            paths,
                            r,
                            path_points[r],
                            heading[i],
                            v * horizon,
                            seg,
                            np_sum(seg, p - 1),
                            path_x,
                            path_y,
                            path_arc,
                            path_ux,
                            path_uy,
                            m,
                        )
                        path_nboxes[m] = _boxes(path_x[m], path_y[m], path_n[m], path_boxes[m])
                        extended[m] = True
                    if not predicted[m]:
                        _predict(
                            path_x[m],
                            path_y[m],
                            path_arc[m],
                            path_ux[m],
                            path_uy[m],
                            v,
                            steps,
                            unc,
                            kinds[i],
                            m,
                            pred_x,
                            pred_y,
                            pred_dir_x,
                            pred_dir_y,
                            pred_sigma_lon,
                            pred_cov_xx,
                            pred_cov_xy,
                            pred_cov_yy,
                        )
                        predicted[m] = True
                    for e in range(n_ego_paths):
                        # q and det at every step, kept for survival when this pair is
                        # the first it computes (then the two models share this loop)
                        q_dmin = _pair_q(
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
                        )
                        q_pair = m * n_ego_paths + e
                        if _gauss_reaches(qs, dets, n_steps, thr, qcut):
                            keep = True
                            break
            t = _cycles()
            cycle_counts[2 + s] += t - t_prev
            t_prev = t
            if not keep:
                code[i] = s
                break
        if code[i] != n_st:
            continue
        if tier_min.shape[0] == 0:
            continue  # no tiers to sort: the survivors' survival risk is not needed
        best = -INF
        for r in range(r0, r1):
            m = r - r0
            if not extended[m]:
                _segment_lengths(paths, r, seg)
                path_n[m] = _extend(
                    paths,
                    r,
                    path_points[r],
                    heading[i],
                    v * horizon,
                    seg,
                    np_sum(seg, p - 1),
                    path_x,
                    path_y,
                    path_arc,
                    path_ux,
                    path_uy,
                    m,
                )
                extended[m] = True
            if not predicted[m]:
                _predict(
                    path_x[m],
                    path_y[m],
                    path_arc[m],
                    path_ux[m],
                    path_uy[m],
                    v,
                    steps,
                    unc,
                    kinds[i],
                    m,
                    pred_x,
                    pred_y,
                    pred_dir_x,
                    pred_dir_y,
                    pred_sigma_lon,
                    pred_cov_xx,
                    pred_cov_xy,
                    pred_cov_yy,
                )
                predicted[m] = True
            for e in range(n_ego_paths):
                if m * n_ego_paths + e == q_pair:  # q and det of this pair are still in qs, dets
                    dmin = q_dmin
                else:
                    dmin = _pair_q(
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
                    )
                    q_pair = m * n_ego_paths + e
                _overlap_risks(
                    qs,
                    dets,
                    dmin,
                    n_steps,
                    float_params[DT_TAU],
                    terms,
                    escape_log_s,
                    escape_s,
                    log_s_deferred,
                    defer,
                    np.bool_(False),
                    np.bool_(True),
                )
                rsurv = np_sum(terms, n_steps)
                best = max(best, rsurv)
        surv_out[i] = best
        t = _cycles()
        cycle_counts[n_st + 2] += t - t_prev
        t_prev = t
    # the result in the cascade's form
    kept = np.zeros((n_st, n), np.bool_)
    dropped_at = np.full(n, -1, np.int8)
    unreachable = np.zeros(n, np.bool_)
    n_surv = 0
    for i in range(n):
        c = code[i]
        for s in range(min(max(c, 0), n_st)):
            kept[s, i] = True
        if c == -1:
            unreachable[i] = True
            dropped_at[i] = 0
        elif 0 <= c < n_st:
            dropped_at[i] = c
        elif c == n_st:
            n_surv += 1
    survivors = np.empty(n_surv, np.int64)
    n_surv = 0
    for i in range(n):
        if code[i] == n_st:
            survivors[n_surv] = i
            n_surv += 1
    t_prev = _cycles()
    tier = np.full(n, -1, np.int8)
    if n_surv > 0:
        risk = np.empty(n_surv)
        for j in range(n_surv):
            risk[j] = surv_out[survivors[j]]
        levels = tiers(risk, tier_min, tier_cap)
        for j in range(n_surv):
            tier[survivors[j]] = levels[j]
    cycle_counts[n_st + 2] += _cycles() - t_prev
    baseline = np.zeros(n, np.bool_)
    false_neg = np.zeros(n_st, np.int64)
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        if survival_all[i] >= baseline_threshold:  # (False for NaN)
            baseline[i] = True
            for s in range(n_st):
                if not kept[s, i]:
                    false_neg[s] += 1
    return (
        kept,
        dropped_at,
        unreachable,
        survivors,
        surv_out,
        cycle_counts,
        tier,
        baseline,
        false_neg,
    )
