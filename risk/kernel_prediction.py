"""The kernel's prediction: constant speed along an extended path with the per-kind
covariances (as :mod:`risk.prediction`), and the ego's path candidates, extended, cut,
boxed and predicted once per call for every model."""

from __future__ import annotations

import numpy as np

from risk.kernel_jit import _inner, np_sum
from risk.kernel_paths import _boxes, _cut, _extend, _interp, _project, _segment_lengths, _segments


@_inner
def _predict(
    path_x,
    path_y,
    path_arc,
    path_ux,
    path_uy,
    v,
    steps,
    unc,
    kind,
    row,
    pred_x,
    pred_y,
    pred_dir_x,
    pred_dir_y,
    pred_sigma_lon,
    pred_cov_xx,
    pred_cov_xy,
    pred_cov_yy,
):
    """Constant-speed prediction along the extended path, and the covariances
    (risk.prediction.FrameContext._trajectory, uncertainty_sigmas, covariances), with
    the uncertainties ``unc[kind]``, into row ``row`` of the outputs (rows indexed in
    place: a row view costs an atomic reference count where it outlives a call)."""
    # the uncertainties in registers (the stores below might alias them otherwise)
    u0, u1, u2, u3 = unc[kind, 0], unc[kind, 1], unc[kind, 2], unc[kind, 3]
    u4, u5, u6, u7 = unc[kind, 4], unc[kind, 5], unc[kind, 6], unc[kind, 7]
    j = np.int64(0)
    for k in range(steps.shape[0]):
        t = steps[k]
        travelled = v * t
        x, y, seg, j = _interp(path_x, path_y, path_arc, travelled, j)
        pred_x[row, k], pred_y[row, k] = x, y
        c, s = path_ux[seg], path_uy[seg]
        pred_dir_x[row, k], pred_dir_y[row, k] = c, s
        lon = min(u0 + u2 * travelled + u6 * t, u4)
        lat = min(u1 + u3 * travelled + u7 * t, u5)
        pred_sigma_lon[row, k] = lon
        a = lon * lon
        b = lat * lat
        cc = c * c
        ss = s * s
        pred_cov_xx[row, k] = a * cc + b * ss
        pred_cov_xy[row, k] = (a - b) * c * s
        pred_cov_yy[row, k] = a * ss + b * cc


@_inner
def _others(valid, ego):
    """Every valid agent but the ego, in order (a loop: the list comprehension it replaces
    cost about a second of cold compile in each entry point, in numba's closure inlining)."""
    out = np.empty(valid.shape[0], np.int64)
    k = 0
    for i in range(valid.shape[0]):
        if valid[i] and i != ego:
            out[k] = i
            k += 1
    return out[:k]


@_inner
def _row_starts(path_agent, n):
    start = np.full(n + 1, -1, np.int64)
    m = path_agent.shape[0]
    for r in range(m - 1, -1, -1):
        start[path_agent[r]] = r
    start[n] = m
    for i in range(n - 1, -1, -1):
        if start[i] < 0:
            start[i] = start[i + 1]
    return start


@_inner
def _ego_candidates(
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
):
    """The ego's path candidates, shared by :func:`evaluate_agents` and
    :func:`cascade_agents`: each extended to ``v T``, cut at ``v T``, boxed by chunks and
    predicted with its covariances, with its segment data and the ego's arc position on
    it."""
    p = paths.shape[1]
    n_points = p + 1
    n_steps = steps.shape[0]
    horizon = steps[n_steps - 1]
    ego_x = np.empty((n_ego_paths, n_points))
    ego_y = np.empty((n_ego_paths, n_points))
    ego_arc = np.empty((n_ego_paths, n_points))
    ego_ux = np.empty((n_ego_paths, n_points))
    ego_uy = np.empty((n_ego_paths, n_points))
    ego_n = np.empty(n_ego_paths, np.int64)
    ego_boxes = np.empty((n_ego_paths, n_chunks, 4))
    ego_nboxes = np.empty(n_ego_paths, np.int64)
    ego_cut_x = np.empty((n_ego_paths, n_points))
    ego_cut_y = np.empty((n_ego_paths, n_points))
    ego_cut_n = np.empty(n_ego_paths, np.int64)
    ego_cut_boxes = np.empty((n_ego_paths, n_chunks, 4))
    ego_cut_nboxes = np.empty(n_ego_paths, np.int64)
    ego_px = np.empty((n_ego_paths, n_steps))
    ego_py = np.empty((n_ego_paths, n_steps))
    ego_dir_x = np.empty((n_ego_paths, n_steps))
    ego_dir_y = np.empty((n_ego_paths, n_steps))
    ego_sigma_lon = np.empty((n_ego_paths, n_steps))
    ego_cov_xx = np.empty((n_ego_paths, n_steps))
    ego_cov_xy = np.empty((n_ego_paths, n_steps))
    ego_cov_yy = np.empty((n_ego_paths, n_steps))
    ego_arc_pos = np.empty(n_ego_paths)
    ego_inv_len2 = np.empty((n_ego_paths, n_points))
    ego_seg_len = np.empty((n_ego_paths, n_points))
    ego_speed = speed[ego]
    for e in range(n_ego_paths):
        r = ego_row0 + e
        _segment_lengths(paths, r, seg)
        ego_n[e] = _extend(
            paths,
            r,
            path_points[r],
            heading[ego],
            ego_speed * horizon,
            seg,
            np_sum(seg, p - 1),
            ego_x,
            ego_y,
            ego_arc,
            ego_ux,
            ego_uy,
            e,
        )
        ego_nboxes[e] = _boxes(ego_x[e], ego_y[e], ego_n[e], ego_boxes[e])
        ego_cut_n[e] = _cut(
            ego_x[e], ego_y[e], ego_arc[e], ego_speed * horizon, ego_cut_x[e], ego_cut_y[e]
        )
        ego_cut_nboxes[e] = _boxes(ego_cut_x[e], ego_cut_y[e], ego_cut_n[e], ego_cut_boxes[e])
        _predict(
            ego_x[e],
            ego_y[e],
            ego_arc[e],
            ego_ux[e],
            ego_uy[e],
            ego_speed,
            steps,
            unc,
            kinds[ego],
            e,
            ego_px,
            ego_py,
            ego_dir_x,
            ego_dir_y,
            ego_sigma_lon,
            ego_cov_xx,
            ego_cov_xy,
            ego_cov_yy,
        )
        _segments(ego_x[e], ego_y[e], ego_n[e], ego_inv_len2[e], ego_seg_len[e])
        ego_arc_pos[e] = _project(
            xy[ego, 0],
            xy[ego, 1],
            ego_x,
            ego_y,
            ego_arc,
            ego_n[e],
            ego_inv_len2,
            ego_seg_len,
            ego_boxes,
            ego_nboxes[e],
            e,
        )[1]
    return (
        ego_x,
        ego_y,
        ego_arc,
        ego_ux,
        ego_uy,
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
        ego_dir_x,
        ego_dir_y,
        ego_sigma_lon,
        ego_cov_xx,
        ego_cov_xy,
        ego_cov_yy,
        ego_arc_pos,
        ego_inv_len2,
        ego_seg_len,
    )
