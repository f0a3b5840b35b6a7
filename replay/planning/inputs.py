"""A planner's inputs from a frame: the ego's reference path, the usable lanes beside it,
and the other agents' forecasts (the toolkit's own constant-speed prediction).

- :func:`plan_request`: one :class:`~replay.planning.types.PlanRequest` for the frame's ego;
- :func:`forecasts_for`: predicted boxes of chosen agents (no Python loop over agents);
- :func:`reference_path`: the ego's first path candidate, extended straight;
- :func:`side_lanes`: how many map lanes run beside the reference, left and right.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from replay.planning.errors import NoReferencePath, PlanningError
from replay.planning.types import AgentForecasts, EgoState, PlanRequest, plan_times
from risk import geometry
from risk.frame import KIND_NAMES, Frame, Kind, LaneMap

#: Which egos the car planners plan for: ``vehicles`` (the default: a pedestrian or a
#: cyclist is not driven by a car planner) or ``all``.
EGO_KINDS: tuple[str, ...] = ("vehicles", "all")

#: Extra reference length beyond what the ego covers within the horizon (m): room for the
#: planners' look-ahead (fiss-planner samples end states up to the horizon and checks the
#: gap to a leader beyond the trajectory's end). The reference also covers the fastest
#: other agent's travel over the horizon beyond that (see :func:`plan_request`).
REFERENCE_MARGIN_M = 50.0

#: The reference starts this far behind the point where the ego's path meets its lane
#: centre (m), so that the ego and the agents just behind it project inside it.
REFERENCE_BEHIND_M = 10.0

#: A map path starts at the agent and joins its lane's centre line ``join_m`` (2 m) ahead
#: of its projection, at most 2 m to the side (converters.lanegraph.PathSettings): a first
#: segment at most this long (m) in a path of three or more points is that join, and the
#: reference drops it (the lane centre line, with the ego at its lateral offset, has no
#: kink; a 1 m offset over a 2 m join is a 0.46 rad turn that no smoothing removes).
JOIN_MAX_M = 3.0


#: The reference is resampled at this spacing (m) and smoothed by a moving average over
#: +-REFERENCE_SMOOTH_M: recorded paths join the lane graph with short kinked segments
#: (a Waymo path turned 0.24 rad within 4 m where the agent met its lane), which a
#: spline through the points turns into curvatures of 0.15 /m, and fiss-planner then
#: rejected every candidate for lateral acceleration at 12 m/s.
REFERENCE_SPACING_M = 1.0
REFERENCE_SMOOTH_M = 4.0

#: At speed the smoothing window grows to +-(this many seconds x the ego's speed): at
#: 40 m/s a lateral acceleration of 4 m/s^2 (fiss-planner's limit) is a curvature of
#: 0.0025 /m, which the joints of a lane's centre line pieces exceed over +-4 m. A
#: moving average over +-h moves a curve of radius R inwards by about h^2 / (6 R): 0.13 m
#: for +-20 m on a 500 m motorway curve.
REFERENCE_SMOOTH_S = 0.5

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


def ego_kind(frame: Frame) -> str:
    """The frame's ego kind by name (``risk.Kind``: vehicle, pedestrian, cyclist, other)."""
    return KIND_NAMES[int(frame.kinds[frame.ego])]


def plans_for(frame: Frame, ego_kinds: str) -> bool:
    """Whether a car planner plans for the frame's ego under ``ego_kinds`` (EGO_KINDS):
    with ``vehicles`` only a vehicle ego (pedestrians, cyclists and ``other`` are
    skipped)."""
    if ego_kinds not in EGO_KINDS:
        raise PlanningError(f"ego kinds: expected one of {', '.join(EGO_KINDS)}, got {ego_kinds!r}")
    return ego_kinds == "all" or int(frame.kinds[frame.ego]) == int(Kind.VEHICLE)


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
    others = np.flatnonzero(frame.others)
    # Long enough that every agent ahead within the margin stays on it over the horizon:
    # an agent whose forecast ran past the end was clamped to the end point, its speed
    # along the path fell to 0, and IDM braked for a phantom standing car there.
    fastest = float(frame.speed[others].max(initial=0.0))
    reference = reference_path(
        frame,
        min_length_m=reach_m + REFERENCE_MARGIN_M + fastest * horizon_s,
        smooth_m=max(REFERENCE_SMOOTH_M, REFERENCE_SMOOTH_S * reach_m / horizon_s),
    )
    left, right = side_lanes(
        reference, lane_map, lane_width_m=lane_width_m, stretch_m=max(reach_m, MIN_LANE_STRETCH_M)
    )
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


def reference_path(
    frame: Frame, *, min_length_m: float, smooth_m: float = REFERENCE_SMOOTH_M
) -> np.ndarray:
    """The ego's lane centre line: its first path candidate without the join from the
    ego to the centre line (see JOIN_MAX_M), extended REFERENCE_BEHIND_M backwards and
    straight forwards or cut to ``min_length_m`` beyond the ego, smoothed over
    ``+-smooth_m``, a point every REFERENCE_POINT_SPACING_M: ``(P, 2)`` in m. The ego
    sits at its lateral offset from it; the planners take that offset and the heading
    error into their initial state."""
    e = frame.ego
    row = int(np.searchsorted(frame.path_agent, e))
    n_points = int(frame.path_points[row])
    path = frame.paths[row, :n_points]
    length = float(geometry.cumulative_lengths(path[None])[0, -1])
    if length < MIN_PATH_M:
        raise NoReferencePath(
            f"ego {frame.ego_id} at t={frame.t:g} s has no path to plan along "
            f"(its path is {length:.2f} m long); choose a moving ego or a scene with paths"
        )
    pts = path[np.r_[True, np.any(np.diff(path, axis=0) != 0.0, axis=1)]]
    if len(pts) >= 3 and float(np.hypot(*(pts[1] - pts[0]))) <= JOIN_MAX_M:
        pts = pts[1:]  # the join: the rest is the lane's centre line
    # Backwards along the centre line's first metre (or first segment when shorter).
    cum0 = geometry.cumulative_lengths(pts[None])[0]
    ahead = geometry.interpolate(pts[None], cum0[None], np.array([[min(1.0, cum0[-1])]]))[0]
    direction = ahead[0, 0] - pts[0]
    direction /= max(float(np.hypot(*direction)), 1e-12)
    behind = REFERENCE_BEHIND_M + float(frame.length[e])
    pts = np.vstack([pts[0] - behind * direction, pts])
    # The ego's arc on it: the reference reaches min_length_m beyond that.
    cum1 = geometry.cumulative_lengths(pts[None])[0]
    ego_arc = float(geometry.project_points(frame.xy[e][None], pts, cum1)[1][0])
    want = ego_arc + float(min_length_m)
    ext, _ = geometry.extend_paths(
        pts[None], np.array([len(pts)]), frame.heading[e : e + 1], np.array([want])
    )
    # Cut to what the planners need: every agent at every time is projected onto it.
    cum = geometry.cumulative_lengths(ext)
    cut, n_cut = geometry.cut_paths(ext, cum, np.array([want]))
    pts = cut[0, : int(n_cut[0])]
    keep = np.r_[True, np.any(np.diff(pts, axis=0) != 0.0, axis=1)]
    smooth = smooth_polyline(pts[keep], spacing_m=REFERENCE_SPACING_M, half_window_m=smooth_m)
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
    candidate, extended straight along its last segment. Heading: the agent's recorded
    heading now (a standing agent keeps it: a parked car's box keeps its orientation
    whatever its path says); then the path's direction at the predicted point, except on
    a join (a first segment of at most JOIN_MAX_M in a path of three or more points: the
    blend from the agent to its lane centre, whose direction is not where the agent
    points; a truck recorded at 0.001 rad got 0.39 rad from it), along which the heading
    turns linearly from the recorded one to the direction of the lane beyond the join.
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
    first_len = np.hypot(*(paths[:, 1] - paths[:, 0]).T)  # (K,)
    join = (frame.path_points[rows] >= 3) & (first_len <= JOIN_MAX_M) & (first_len > 0)
    beyond = np.arctan2(uy[:, 1], ux[:, 1]) if ux.shape[1] > 1 else heading  # (K,)
    turn = np.angle(np.exp(1j * (beyond - heading)))  # wrapped to (-pi, pi]
    share = np.clip(arc / np.where(join, first_len, 1.0)[:, None], 0.0, 1.0)
    on_join = join[:, None] & (arc < first_len[:, None])
    heading_kt = np.where(arc > 0.0, path_heading, heading[:, None])
    heading_kt = np.where(
        on_join, np.angle(np.exp(1j * (heading[:, None] + share * turn[:, None]))), heading_kt
    )
    return AgentForecasts(
        ids=frame.ids[idx],
        kinds=frame.kinds[idx],
        length_m=frame.length[idx],
        width_m=frame.width[idx],
        times_s=times,
        xy=xy,
        heading_rad=heading_kt,
        speed_mps=speed,
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
    prepared = _padded_lanes(lane_map)
    if prepared is None:
        return 0, 0
    all_lanes, counts, box_lo, box_hi = prepared
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
    near = ((box_hi >= lo) & (box_lo <= hi)).all(axis=1)
    if not near.any():
        return 0, 0
    # Every segment of the nearby lanes whose own box comes near the samples, grouped by
    # lane: the samples' distances to them are one (S, M) matrix, and each lane's nearest
    # segment per sample comes from per-group reductions (no loop over lanes).
    padded = all_lanes[near, : int(counts[near].max())]  # (L, Q, 2)
    a_pts, b_pts = padded[:, :-1], padded[:, 1:]  # (L, Q-1, 2)
    seg_lo, seg_hi = np.minimum(a_pts, b_pts), np.maximum(a_pts, b_pts)
    real = (np.diff(padded, axis=1) ** 2).sum(axis=-1) > 0
    close = real & ((seg_hi >= lo) & (seg_lo <= hi)).all(axis=-1)  # (L, Q-1)
    lane_of, seg_of = np.nonzero(close)
    if lane_of.size == 0:
        return 0, 0
    a = a_pts[lane_of, seg_of]  # (M, 2), grouped by lane (nonzero is row-major)
    ab = b_pts[lane_of, seg_of] - a
    len2 = (ab**2).sum(axis=-1)
    starts = np.flatnonzero(np.r_[True, lane_of[1:] != lane_of[:-1]])
    rel = pts[:, None, :] - a[None]  # (S, M, 2)
    t = np.clip((rel * ab[None]).sum(axis=-1) / len2[None], 0.0, 1.0)
    foot = a[None] + t[..., None] * ab[None]  # (S, M, 2)
    dist2 = ((pts[:, None, :] - foot) ** 2).sum(axis=-1)  # (S, M)
    group_min = np.minimum.reduceat(dist2, starts, axis=1)  # (S, G)
    sizes = np.diff(np.r_[starts, lane_of.size])
    is_best = dist2 == np.repeat(group_min, sizes, axis=1)
    # The first best segment of each group: the running count of bests within it is 1.
    running = np.cumsum(is_best, axis=1)
    before = np.repeat(np.c_[np.zeros((len(pts), 1)), running[:, starts[1:] - 1]], sizes, axis=1)
    first = is_best & (running - before == 1)

    def at_best(values: np.ndarray) -> np.ndarray:  # (S, M) -> (S, G)
        return np.add.reduceat(np.where(first, values, 0.0), starts, axis=1)

    unit = ab / np.sqrt(len2)[:, None]  # (M, 2)
    off = foot - pts[:, None, :]
    lateral = at_best((off * normal[:, None, :]).sum(axis=-1))  # (S, G), + to the left
    along = at_best((off * tan[:, None, :]).sum(axis=-1))
    aligned = at_best((unit[None] * tan[:, None, :]).sum(axis=-1)) >= math.cos(LANE_ANGLE_RAD)
    k = np.rint(lateral / lane_width_m)
    beside = (
        aligned
        & (np.abs(lateral - k * lane_width_m) <= LANE_OFFSET_TOLERANCE * lane_width_m)
        & (np.abs(along) <= 0.5 * LANE_SAMPLE_M)  # the lane covers this sample
        & (k != 0)
        & (np.abs(k) <= max_lanes)
    )
    offsets = np.arange(-max_lanes, max_lanes + 1)
    present = (beside[..., None] & (k[..., None] == offsets)).any(axis=1)  # (S, 2*max+1)
    usable = present.mean(axis=0) >= LANE_COVERAGE
    left = _run(usable[max_lanes + 1 :])
    right = _run(usable[:max_lanes][::-1])
    return left, right


@functools.lru_cache(maxsize=8)
def _padded_lanes(
    lane_map: LaneMap,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The map's lane centre lines as one padded array ``(L, Q, 2)`` (each padded with its
    last point), their point counts ``(L,)`` and bounding boxes ``(L, 2)`` low and high;
    built once per map (a scene's frames share one map; maps are compared by identity)."""
    lanes = [lane.centerline for lane in lane_map.lanes if len(lane.centerline) >= 2]
    if not lanes:
        return None
    counts = np.array([len(c) for c in lanes], dtype=np.int64)
    padded = np.empty((len(lanes), int(counts.max()), 2))
    for i, c in enumerate(lanes):  # once per map, not per frame
        padded[i, : len(c)] = c
        padded[i, len(c) :] = c[-1]
    return padded, counts, padded.min(axis=1), padded.max(axis=1)


def _run(flags: np.ndarray) -> int:
    """Length of the leading run of True."""
    return int(np.argmin(flags)) if not flags.all() else int(flags.size)
