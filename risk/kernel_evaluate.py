"""The kernel's entry point for :func:`risk.evaluate`: every requested model for every
requested agent, one pass per agent row over its path candidates (the paths, prediction
and overlap functions of the other kernel modules, reused by every model)."""

from __future__ import annotations

import math

import numpy as np

from risk.kernel_jit import _inner, _jit, np_sum
from risk.kernel_overlap import _escape_track, _overlap_risks, _pair_q
from risk.kernel_paths import (
    _boxes,
    _cut,
    _cut_boxes,
    _extend,
    _first_crossing,
    _polyline_distance,
    _project,
    _segment_lengths,
)
from risk.kernel_prediction import _ego_candidates, _others, _predict, _row_starts
from risk.kernel_shared import (
    CIRC,
    CUR,
    DT_TAU,
    ENC,
    EPS_CIRC,
    EPS_CUR,
    EPS_ENC,
    EPS_H2D,
    EPS_HW,
    EPS_PATH,
    EPS_TRAJ,
    GAUSS,
    H2D,
    HW,
    INF,
    LIM_ENC,
    LIM_H2D,
    LIM_HW,
    N_CIRC,
    N_MODELS,
    PATH,
    RADIUS_RULE,
    SCALE_CIRC,
    SURV,
    TAU_H2D,
    TAU_HW,
    TIE,
    TOL_H2D,
    TOL_HW,
    TRAJ,
    K,
)


@_inner
def _time_gap(arc, l1, v1):
    """(l2 - l1) / v1 ahead of the ego, inf behind it, for NaN or a standing ego."""
    if v1 <= 0:
        return INF
    gap = arc - l1
    if gap >= 0:
        return gap / v1
    return INF


@_jit
def evaluate_agents(
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
    want,
    float_params,
    int_params,
    keep_d2,
    drop_d2,
):
    """Risks ``(9, N)`` of the requested models (``want``) for ``agents`` (an empty array:
    every valid agent but the ego); NaN elsewhere.

    ``keep_d2`` / ``drop_d2`` (9,): squared distances for the keep/drop mode of the distance
    models (the cascade): stop at ``keep_d2``, prune beyond ``drop_d2``; ``-1`` / ``inf`` for
    exact values."""
    n = xy.shape[0]
    if agents.shape[0] == 0:
        agents = _others(valid, ego)
    p = paths.shape[1]
    n_points = p + 1
    n_steps = steps.shape[0]
    horizon = steps[n_steps - 1]
    n_chunks = (n_points - 1 + K - 1) // K + 1
    out = np.full((N_MODELS, n), np.nan)
    starts = _row_starts(path_agent, n)
    want_path = want[PATH] or want[H2D]
    want_pred = want[ENC] or want[HW] or want[H2D] or want[CIRC] or want[GAUSS] or want[SURV]
    exact_path = want[H2D] or keep_d2[PATH] < 0
    traj_exact = keep_d2[TRAJ] < 0 and drop_d2[TRAJ] == INF
    # ------------------------------------------------ ego candidates
    ego_row0, e1 = starts[ego], starts[ego + 1]
    n_ego_paths = e1 - ego_row0
    seg = np.empty(max(p - 1, 1))
    ego_speed = speed[ego]
    (
        ego_x,
        ego_y,
        ego_arc,
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
        ego_sigma_lon,
        ego_cov_xx,
        ego_cov_xy,
        ego_cov_yy,
        ego_arc_pos,
        ego_inv_len2,
        ego_seg_len,
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
    # ------------------------------------------------ per-row scratch
    # one row each, for the functions that take rows (path_x_row ... with row 0), and that row's
    # views for the others (made once per call: each view costs an atomic reference count)
    path_x_row, path_y_row, path_arc_row = (
        np.empty((1, n_points)),
        np.empty((1, n_points)),
        np.empty((1, n_points)),
    )
    path_ux_row, path_uy_row = np.empty((1, n_points)), np.empty((1, n_points))
    cut_x_row, cut_y_row = np.empty((1, n_points)), np.empty((1, n_points))
    path_boxes_row, cut_boxes_row = np.empty((1, n_chunks, 4)), np.empty((1, n_chunks, 4))
    path_x, path_y, path_arc, path_ux, path_uy = (
        path_x_row[0],
        path_y_row[0],
        path_arc_row[0],
        path_ux_row[0],
        path_uy_row[0],
    )
    cut_x, cut_y, path_boxes, cut_boxes = (
        cut_x_row[0],
        cut_y_row[0],
        path_boxes_row[0],
        cut_boxes_row[0],
    )
    gaps = np.empty(n_chunks * n_chunks)
    pred_x = np.empty(
        (1, n_steps)
    )  # (one row: the functions shared with cascade_agents index rows)
    row = np.int64(0)  # (that row; not a literal 0: see _jit)
    pred_y = np.empty((1, n_steps))
    pred_dir_x = np.empty((1, n_steps))
    pred_dir_y = np.empty((1, n_steps))
    pred_sigma_lon = np.empty((1, n_steps))
    pred_cov_xx = np.empty((1, n_steps))
    pred_cov_xy = np.empty((1, n_steps))
    pred_cov_yy = np.empty((1, n_steps))
    terms = np.empty(n_steps)
    qs = np.empty(n_steps)
    dets = np.empty(n_steps)
    log_s_deferred = np.empty(n_steps)
    defer = np.empty(n_steps, np.int64)
    n_circles = int_params[N_CIRC]
    scale = float_params[SCALE_CIRC]
    dt_tau = float_params[DT_TAU]
    escape_log_s = np.empty(n_steps)
    escape_s = np.empty(n_steps)
    if want[SURV]:
        _escape_track(n_steps, dt_tau, escape_log_s, escape_s)
    lateral = np.empty(n_ego_paths)
    arc_on = np.empty(n_ego_paths)
    o2 = np.empty(max(n_circles, 1))
    oo = np.empty(max(n_circles, 1))
    best = np.empty(N_MODELS)
    cut_n, cut_nboxes = 0, 0
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        best[:] = -INF
        if want[CUR]:
            d = math.hypot(xy[i, 0] - xy[ego, 0], xy[i, 1] - xy[ego, 1])
            best[CUR] = float_params[EPS_CUR] / (float_params[EPS_CUR] + d)
        if want[HW] or want[H2D]:
            for e in range(n_ego_paths):
                lateral[e], arc_on[e] = _project(
                    xy[i, 0],
                    xy[i, 1],
                    ego_x,
                    ego_y,
                    ego_arc,
                    ego_n[e],
                    ego_inv_len2,
                    ego_seg_len,
                    ego_boxes,
                    ego_nboxes[e],
                    e,
                )
        v = speed[i]
        path_done = False
        traj_done = False
        if (want[PATH] and not exact_path) or (want[TRAJ] and keep_d2[TRAJ] >= 0):
            # Keep/drop mode: the paths' first points bound both distances from above, so
            # an agent whose path starts near an ego path start is kept in O(1).
            d0 = INF
            for r in range(starts[i], starts[i + 1]):
                for e in range(n_ego_paths):
                    ddx = paths[r, 0, 0] - paths[ego_row0 + e, 0, 0]
                    ddy = paths[r, 0, 1] - paths[ego_row0 + e, 0, 1]
                    d0 = min(d0, ddx * ddx + ddy * ddy)
            for slot, eps_at in ((PATH, EPS_PATH), (TRAJ, EPS_TRAJ)):
                if want[slot] and d0 <= keep_d2[slot]:
                    eps = float_params[eps_at]
                    best[slot] = eps / (eps + math.sqrt(d0))
                    if slot == PATH:
                        path_done = True
                    else:
                        traj_done = True
        for r in range(starts[i], starts[i + 1]):
            if not ((want_path and not path_done) or (want[TRAJ] and not traj_done) or want_pred):
                break
            _segment_lengths(paths, r, seg)
            path_n = _extend(
                paths,
                r,
                path_points[r],
                heading[i],
                v * horizon,
                seg,
                np_sum(seg, p - 1),
                path_x_row,
                path_y_row,
                path_arc_row,
                path_ux_row,
                path_uy_row,
                row,
            )
            path_nboxes = _boxes(path_x, path_y, path_n, path_boxes) if want_path else 0
            if want[TRAJ] and not traj_done:
                cut_n = _cut(path_x, path_y, path_arc, v * horizon, cut_x, cut_y)
                if want_path:
                    cut_nboxes = _cut_boxes(
                        cut_x, cut_y, cut_n, path_arc, v * horizon, path_boxes, path_n, cut_boxes
                    )
                else:
                    cut_nboxes = _boxes(cut_x, cut_y, cut_n, cut_boxes)
            if want_pred:
                _predict(
                    path_x,
                    path_y,
                    path_arc,
                    path_ux,
                    path_uy,
                    v,
                    steps,
                    unc,
                    kinds[i],
                    row,
                    pred_x,
                    pred_y,
                    pred_dir_x,
                    pred_dir_y,
                    pred_sigma_lon,
                    pred_cov_xx,
                    pred_cov_xy,
                    pred_cov_yy,
                )
            for e in range(n_ego_paths):
                d_path = INF
                d_traj = INF
                if want[TRAJ] and not traj_done:
                    d_traj = _polyline_distance(
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
                        keep_d2[TRAJ],
                        drop_d2[TRAJ],
                        INF,
                    )
                    eps = float_params[EPS_TRAJ]
                    best[TRAJ] = max(best[TRAJ], eps / (eps + d_traj))
                    if keep_d2[TRAJ] >= 0 and d_traj * d_traj <= keep_d2[TRAJ]:
                        traj_done = True
                if want_path and not path_done:
                    # The cut paths lie on the extended ones (the cut's end point to
                    # rounding), so an exact trajectory distance bounds the path distance
                    # from above: a margin of 1 um keeps the bound above the true minimum,
                    # which is then found exactly as without it.
                    bound = INF
                    if traj_exact and d_traj < INF:
                        bound = (d_traj + 1e-6) ** 2
                    d_path = _polyline_distance(
                        ego_x,
                        ego_y,
                        e,
                        ego_n[e],
                        ego_boxes,
                        ego_nboxes[e],
                        path_x_row,
                        path_y_row,
                        row,
                        path_n,
                        path_boxes_row,
                        path_nboxes,
                        gaps,
                        -1.0 if exact_path else keep_d2[PATH],
                        INF if exact_path else drop_d2[PATH],
                        bound,
                    )
                    if want[PATH]:
                        eps = float_params[EPS_PATH]
                        best[PATH] = max(best[PATH], eps / (eps + d_path))
                        if not exact_path and d_path * d_path <= keep_d2[PATH]:
                            path_done = True
                if not want_pred:
                    continue
                # closest encounter and circles in one loop; the Gaussian overlap and
                # survival from the exponents of a second one (exp where it matters)
                r_ego = 0.5 * (length[ego] if int_params[RADIUS_RULE] == 0 else width[ego])
                d2min = INF
                circ = INF
                gmax, rsurv = -INF, 0.0
                # loop invariants in registers, the circles' offsets once per agent; the
                # ego's rows indexed in place (a row view costs an atomic reference count)
                w_circ, w_stoch, w_surv = want[CIRC], want[GAUSS] or want[SURV], want[SURV]
                half_w = 0.5 * width[i]
                if w_circ:
                    for c in range(n_circles):
                        o = length[i] * ((c + 0.5) / n_circles - 0.5)
                        o2[c] = 2.0 * o
                        oo[c] = o * o
                for k in range(n_steps):
                    rx = pred_x[0, k] - ego_px[e, k]
                    ry = pred_y[0, k] - ego_py[e, k]
                    d2 = rx * rx + ry * ry
                    d2min = min(d2min, d2)
                    if w_circ and circ > 0.0:  # (once <= 0, the risk is 1)
                        reach = (r_ego + scale * ego_sigma_lon[e, k]) + (
                            half_w + scale * pred_sigma_lon[0, k]
                        )
                        along = rx * pred_dir_x[0, k] + ry * pred_dir_y[0, k]
                        c2min = INF
                        for c in range(n_circles):
                            c2min = min(c2min, d2 + o2[c] * along + oo[c])
                        # sqrt is monotone: one root per step gives the same minimum; a
                        # step certainly no nearer than the best (a margin for rounding)
                        # skips it
                        lim = circ + reach
                        if lim > 0.0 and c2min <= lim * lim * (1.0 + 1e-9):
                            circ = min(circ, math.sqrt(max(c2min, 0.0)) - reach)
                if w_stoch:
                    dmin = _pair_q(
                        pred_x,
                        pred_y,
                        pred_cov_xx,
                        pred_cov_xy,
                        pred_cov_yy,
                        row,
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
                    gmax = _overlap_risks(
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
                        want[GAUSS],
                        w_surv,
                    )
                    if w_surv:
                        rsurv = np_sum(terms, n_steps)
                if want[ENC] or want[HW] or want[H2D]:
                    d_e = math.sqrt(d2min)
                    tie = (d_e + TIE) ** 2
                    k_e = 0
                    for k in range(n_steps):
                        rx = pred_x[0, k] - ego_px[e, k]
                        ry = pred_y[0, k] - ego_py[e, k]
                        if rx * rx + ry * ry <= tie:
                            k_e = k
                            break
                    for slot, eps_at, lim in (
                        (ENC, EPS_ENC, LIM_ENC),
                        (HW, EPS_HW, LIM_HW),
                        (H2D, EPS_H2D, LIM_H2D),
                    ):
                        if want[slot]:
                            eps = float_params[eps_at]
                            r_enc = eps / (eps + d_e) if steps[k_e] < float_params[lim] else 0.0
                            best[slot] = max(best[slot], r_enc)
                if want[HW]:
                    th = INF
                    if lateral[e] <= float_params[TOL_HW]:
                        th = _time_gap(arc_on[e], ego_arc_pos[e], ego_speed)
                    tau = float_params[TAU_HW]
                    best[HW] = max(best[HW], tau / (tau + th))
                if want[H2D]:
                    th = INF
                    if lateral[e] <= float_params[TOL_H2D]:
                        th = _time_gap(arc_on[e], ego_arc_pos[e], ego_speed)
                    elif d_path == 0.0:
                        s_b, s_a = _first_crossing(
                            path_x,
                            path_y,
                            path_arc,
                            path_n,
                            path_boxes,
                            path_nboxes,
                            ego_x[e],
                            ego_y[e],
                            ego_arc[e],
                            ego_n[e],
                            ego_boxes[e],
                            ego_nboxes[e],
                        )
                        th = _time_gap(s_a - s_b, ego_arc_pos[e], ego_speed)
                    tau = float_params[TAU_H2D]
                    best[H2D] = max(best[H2D], tau / (tau + th))
                if want[CIRC]:
                    eps = float_params[EPS_CIRC]
                    best[CIRC] = max(best[CIRC], eps / (eps + max(circ, 0.0)))
                if want[GAUSS]:
                    best[GAUSS] = max(best[GAUSS], gmax)
                if want[SURV]:
                    best[SURV] = max(best[SURV], rsurv)
        for slot in range(N_MODELS):
            if want[slot]:
                out[slot, i] = best[slot]
    return out
