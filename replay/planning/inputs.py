"""A planner's inputs from a frame: the ego's reference path, the usable lanes beside it,
and the other agents' forecasts (the toolkit's own constant-speed prediction).

- :func:`plan_request`: one :class:`~replay.planning.types.PlanRequest` for the frame's ego;
- :func:`forecasts_for`: predicted boxes of chosen agents (no Python loop over agents);
- :func:`reference_path`: the ego's first path candidate, extended straight;
- :func:`side_lanes`: how many map lanes run beside the reference, left and right.
"""

from __future__ import annotations

import math

import numpy as np

from replay.planning.errors import NoReferencePath
from replay.planning.types import AgentForecasts, EgoState, PlanRequest, plan_times
from risk import geometry
from risk.frame import Frame, LaneMap

#: Extra reference length beyond what the ego covers within the horizon (m): room for the
#: planners' look-ahead (fiss-planner samples end states up to the horizon and checks the
#: gap to a leader beyond the trajectory's end).
REFERENCE_MARGIN_M = 50.0

#: The reference is resampled at this spacing (m) and smoothed by a moving average over
#: +-REFERENCE_SMOOTH_M: recorded paths join the lane graph with short kinked segments
#: (a Waymo path turned 0.24 rad within 4 m where the agent met its lane), which a
#: spline through the points turns into curvatures of 0.15 /m, and fiss-planner then
#: rejected every candidate for lateral acceleration at 12 m/s.
REFERENCE_SPACING_M = 1.0
REFERENCE_SMOOTH_M = 4.0

#: The smoothed reference keeps a point every this many metres (and its last point): the
#: planners' projections cost in proportion to its segments (every agent at every time is
#: projected onto it), and a 3 m chord of a 15 m radius curve is within 0.08 m of the arc.
REFERENCE_POINT_SPACING_M = 3.0

#: A path shorter than this (m) is no path: a standing agent's single point.
MIN_PATH_M = 0.5

#: Spacing (m) of the reference samples at which side lanes are looked for.
LANE_SAMPLE_M = 5.0

#: A map lane runs beside the reference at a sample when its nearest point lies within this
#: share of a lane width of a whole number of lane widths to the side, and its direction is
#: within LANE_ANGLE_RAD of the reference's (so oncoming lanes do not count).
LANE_OFFSET_TOLERANCE = 0.3
LANE_ANGLE_RAD = math.radians(30.0)

#: Share of the reference samples ahead (over the ego's reach within the horizon, at least
#: MIN_LANE_STRETCH_M) at which a side lane must be present to count as usable.
LANE_COVERAGE = 0.5
MIN_LANE_STRETCH_M = 30.0


def plan_request(
    frame: Frame,
    lane_map: LaneMap,
    *,
    target_speed_mps: float,
    horizon_s: float = 5.0,
    dt_s: float = 0.1,
    lane_width_m: float = 3.5,
) -> PlanRequest:
    """The planner's request for the frame's ego, with every valid non-ego agent.

    Raises :class:`NoReferencePath` when the ego's first path candidate is shorter than
    MIN_PATH_M (a standing ego with no path).
    """
    e = frame.ego
    ego_speed = float(frame.speed[e])
    reach_m = max(ego_speed, float(target_speed_mps)) * horizon_s
    reference = reference_path(frame, min_length_m=reach_m + REFERENCE_MARGIN_M)
    left, right = side_lanes(
        reference, lane_map, lane_width_m=lane_width_m, stretch_m=max(reach_m, MIN_LANE_STRETCH_M)
    )
    others = np.flatnonzero(frame.others)
    return PlanRequest(
        ego=EgoState(
            xy=frame.xy[e].copy(),
            heading_rad=float(frame.heading[e]),
            speed_mps=ego_speed,
            length_m=float(frame.length[e]),
            width_m=float(frame.width[e]),
        ),
        reference=reference,
        target_speed_mps=float(target_speed_mps),
        agents=forecasts_for(frame, others, plan_times(horizon_s, dt_s)),
        lane_width_m=lane_width_m,
        lanes_left=left,
        lanes_right=right,
        horizon_s=horizon_s,
        dt_s=dt_s,
    )


def reference_path(frame: Frame, *, min_length_m: float) -> np.ndarray:
    """The ego's first path candidate, extended straight or cut to ``min_length_m``,
    smoothed, a point every REFERENCE_POINT_SPACING_M: ``(P, 2)`` in m."""
    e = frame.ego
    row = int(np.searchsorted(frame.path_agent, e))
    paths = frame.paths[row : row + 1]
    points = frame.path_points[row : row + 1]
    length = float(geometry.cumulative_lengths(paths)[0, -1])
    if length < MIN_PATH_M:
        raise NoReferencePath(
            f"ego {frame.ego_id} at t={frame.t:g} s has no path to plan along "
            f"(its path is {length:.2f} m long); choose a moving ego or a scene with paths"
        )
    ext, _ = geometry.extend_paths(
        paths, points, frame.heading[e : e + 1], np.array([float(min_length_m)])
    )
    # Cut to what the planners need: every agent at every time is projected onto it.
    cum = geometry.cumulative_lengths(ext)
    cut, n_cut = geometry.cut_paths(ext, cum, np.array([float(min_length_m)]))
    pts = cut[0, : int(n_cut[0])]
    keep = np.r_[True, np.any(np.diff(pts, axis=0) != 0.0, axis=1)]
    smooth = smooth_polyline(
        pts[keep], spacing_m=REFERENCE_SPACING_M, half_window_m=REFERENCE_SMOOTH_M
    )
    step = max(round(REFERENCE_POINT_SPACING_M / REFERENCE_SPACING_M), 1)
    rows = np.r_[np.arange(0, smooth.shape[0] - 1, step), smooth.shape[0] - 1]
    return np.ascontiguousarray(smooth[rows])


def smooth_polyline(points: np.ndarray, *, spacing_m: float, half_window_m: float) -> np.ndarray:
    """``points`` (P, 2) resampled every ``spacing_m`` and smoothed by a moving average over
    ``+-half_window_m``. Both ends are padded by point reflection (``2 p0 - p_k``), so the
    first and last points stay where they are and straight stretches stay straight."""
    cum = geometry.cumulative_lengths(points[None])
    length = float(cum[0, -1])
    s = np.linspace(0.0, length, max(int(np.ceil(length / spacing_m)) + 1, 2))
    dense = geometry.interpolate(points[None], cum, s[None])[0][0]
    h = min(round(half_window_m / spacing_m), dense.shape[0] - 1)
    if h < 1:
        return dense
    head = 2.0 * dense[0] - dense[h:0:-1]
    tail = 2.0 * dense[-1] - dense[-2 : -h - 2 : -1]
    padded = np.concatenate([head, dense, tail])
    kernel = np.full(2 * h + 1, 1.0 / (2 * h + 1))
    out = np.stack([np.convolve(padded[:, c], kernel, mode="valid") for c in (0, 1)], axis=1)
    out[0], out[-1] = dense[0], dense[-1]  # exact, whatever the rounding
    return out


def forecasts_for(frame: Frame, indices: np.ndarray, times_s: np.ndarray) -> AgentForecasts:
    """Predicted boxes of the agents ``indices`` (K,) at ``times_s`` (T,).

    The toolkit's prediction (risk.prediction): constant speed along the agent's first path
    candidate, extended straight along its last segment. Heading: the path's direction at
    the predicted point for moving agents; the agent's own heading for standing ones (a
    parked car's box keeps its orientation whatever its path says).
    """
    idx = np.asarray(indices, dtype=np.int64)
    times = np.asarray(times_s, dtype=np.float64)
    if idx.size == 0:
        return AgentForecasts.empty(times)
    rows = np.searchsorted(frame.path_agent, idx)  # each agent's first candidate
    speed = frame.speed[idx]
    heading = frame.heading[idx]
    travel = speed * float(times[-1]) + 1.0
    paths, _ = geometry.extend_paths(frame.paths[rows], frame.path_points[rows], heading, travel)
    cum = geometry.cumulative_lengths(paths)
    arc = speed[:, None] * times[None, :]
    xy, seg = geometry.interpolate(paths, cum, arc)
    ux, uy = geometry.segment_unit_vectors(paths, heading)
    flat = seg + (np.arange(idx.size) * ux.shape[1])[:, None]
    path_heading = np.arctan2(np.take(uy.ravel(), flat), np.take(ux.ravel(), flat))
    moving = speed > 0.0
    heading_kt = np.where(moving[:, None], path_heading, heading[:, None])
    return AgentForecasts(
        ids=frame.ids[idx],
        kinds=frame.kinds[idx],
        length_m=frame.length[idx],
        width_m=frame.width[idx],
        times_s=times,
        xy=xy,
        heading_rad=heading_kt,
    )


def side_lanes(
    reference: np.ndarray,
    lane_map: LaneMap,
    *,
    lane_width_m: float,
    stretch_m: float,
    max_lanes: int = 4,
) -> tuple[int, int]:
    """Usable lanes ``(left, right)`` beside the reference over its first ``stretch_m``.

    A lane at offset ``k`` (k lane widths to the left, negative to the right) is usable
    when map lanes run there, in the reference's direction, at at least LANE_COVERAGE of
    the samples; the count on each side is the run of usable offsets from 1 outwards (a
    gap ends it). Vectorised over lanes and samples; (0, 0) when the map has no lanes.
    """
    lanes = [lane.centerline for lane in lane_map.lanes if len(lane.centerline) >= 2]
    if not lanes:
        return 0, 0
    ref_cum = geometry.cumulative_lengths(reference[None])[0]
    s = np.arange(0.0, min(stretch_m, float(ref_cum[-1])) + 1e-9, LANE_SAMPLE_M)
    pts, seg = geometry.interpolate(reference[None], ref_cum[None], s[None])
    pts, seg = pts[0], seg[0]  # (S, 2), (S,)
    d = np.diff(reference, axis=0)
    tangent = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    tan = tangent[np.minimum(seg, len(tangent) - 1)]  # (S, 2)
    normal = np.stack([-tan[:, 1], tan[:, 0]], axis=1)  # left of the direction

    # Lanes padded to one array; keep only those whose box comes near the samples.
    reach = (max_lanes + 1) * lane_width_m
    lo, hi = pts.min(axis=0) - reach, pts.max(axis=0) + reach
    q = max(len(c) for c in lanes)
    padded = np.stack([np.concatenate([c, np.repeat(c[-1:], q - len(c), axis=0)]) for c in lanes])
    near = ((padded.max(axis=1) >= lo) & (padded.min(axis=1) <= hi)).all(axis=1)
    if not near.any():
        return 0, 0
    padded = padded[near]  # (L, Q, 2)
    a = padded[:, None, :-1, :]  # (L, 1, Q-1, 2)
    ab = np.diff(padded, axis=1)[:, None]  # (L, 1, Q-1, 2)
    len2 = (ab**2).sum(axis=-1)
    rel = pts[None, :, None, :] - a  # (L, S, Q-1, 2)
    t = np.clip((rel * ab).sum(axis=-1) / np.where(len2 > 0, len2, 1.0), 0.0, 1.0)
    foot = a + t[..., None] * ab
    dist2 = ((pts[None, :, None, :] - foot) ** 2).sum(axis=-1)
    dist2 = np.where(len2 > 0, dist2, np.inf)  # padding segments
    best = np.argmin(dist2, axis=2)  # (L, S)
    take = best[..., None, None]
    foot_b = np.take_along_axis(foot, take, axis=2)[:, :, 0]  # (L, S, 2)
    dir_b = np.take_along_axis(np.broadcast_to(ab, foot.shape), take, axis=2)[:, :, 0]
    dir_b = dir_b / np.maximum(np.linalg.norm(dir_b, axis=-1, keepdims=True), 1e-12)
    off = foot_b - pts[None]
    lateral = (off * normal[None]).sum(axis=-1)  # (L, S), + to the left
    along = (off * tan[None]).sum(axis=-1)
    aligned = (dir_b * tan[None]).sum(axis=-1) >= math.cos(LANE_ANGLE_RAD)
    k = np.rint(lateral / lane_width_m)
    beside = (
        aligned
        & (np.abs(lateral - k * lane_width_m) <= LANE_OFFSET_TOLERANCE * lane_width_m)
        & (np.abs(along) <= 0.5 * LANE_SAMPLE_M)  # the lane covers this sample
        & (k != 0)
        & (np.abs(k) <= max_lanes)
    )
    offsets = np.arange(-max_lanes, max_lanes + 1)
    present = (beside[..., None] & (k[..., None] == offsets)).any(axis=0)  # (S, 2*max+1)
    usable = present.mean(axis=0) >= LANE_COVERAGE
    left = _run(usable[max_lanes + 1 :])
    right = _run(usable[:max_lanes][::-1])
    return left, right


def _run(flags: np.ndarray) -> int:
    """Length of the leading run of True."""
    return int(np.argmin(flags)) if not flags.all() else int(flags.size)
