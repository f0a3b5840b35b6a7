"""Polyline geometry, vectorised over many paths at once.

Paths are stored padded: ``(M, P, 2)`` float64 in metres, each row padded by repeating its
last point. Padding adds only zero-length segments, and every function here treats a
zero-length segment as a point, so padding never changes a distance, a length or a
position.

Functions:

- arc-length parametrisation (:func:`cumulative_lengths`), segment directions with
  degenerate segments filled (:func:`segment_directions`);
- straight extension of short paths (:func:`extend_paths`), cutting at an arc length
  (:func:`cut_paths`), points at arc lengths (:func:`interpolate`);
- projection of points onto a path (:func:`project_points`);
- exact minimum distance between one polyline and many (:func:`polyline_distances`,
  segment to segment with an intersection test, so crossing paths give exactly 0) and the
  first intersection along each of many polylines (:func:`first_intersections`).

The minimum distance prunes with chunk bounding boxes before the exact segment test; the
pruning is exact (a chunk pair is skipped only when its box distance exceeds a distance
already achieved by two real vertices).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Segments per chunk for the bounding-box prefilter. 8 was fastest on 150 m lane paths
#: with 1-2 m point spacing (measured with benchmarks/bench_models.py).
CHUNK_SEGMENTS = 8


# ---------------------------------------------------------------------- parametrisation
def segment_lengths(paths: np.ndarray) -> np.ndarray:
    """Lengths ``(M, P-1)`` in m of the segments of ``paths`` ``(M, P, 2)``."""
    d = np.diff(paths, axis=1)
    return np.hypot(d[..., 0], d[..., 1])


def cumulative_lengths(paths: np.ndarray) -> np.ndarray:
    """Arc length ``(M, P)`` in m at every point of ``paths`` ``(M, P, 2)``; column 0 is 0.

    Padding points repeat the last arc length, so ``cum[:, -1]`` is each path's length.
    """
    cum = np.zeros(paths.shape[:2])
    np.cumsum(segment_lengths(paths), axis=1, out=cum[:, 1:])
    return cum


def segment_directions(paths: np.ndarray, fallback_heading: np.ndarray) -> np.ndarray:
    """Unit direction ``(M, P-1, 2)`` of every segment, degenerate segments filled.

    A zero-length segment (a repeated point or padding) takes the direction of the last
    non-degenerate segment before it; when there is none, the row's ``fallback_heading``
    ``(M,)`` in rad (the agent's heading). This is the path heading that prediction and the
    uncertainty model use, and the direction in which a short path is extended.
    """
    m, p = paths.shape[:2]
    fallback = np.stack([np.cos(fallback_heading), np.sin(fallback_heading)], axis=-1)
    if p < 2:
        return np.empty((m, 0, 2))
    d = np.diff(paths, axis=1)
    length = np.hypot(d[..., 0], d[..., 1])
    good = length > 0
    unit = np.where(good[..., None], d / np.where(good, length, 1.0)[..., None], 0.0)
    # Index of the last good segment at or before each segment (-1: none yet).
    last_good = np.where(good, np.arange(p - 1)[None, :], -1)
    np.maximum.accumulate(last_good, axis=1, out=last_good)
    rows = np.arange(m)[:, None]
    filled = unit[rows, np.maximum(last_good, 0)]
    return np.where((last_good >= 0)[..., None], filled, fallback[:, None, :])


def extend_paths(
    paths: np.ndarray,
    path_points: np.ndarray,
    fallback_heading: np.ndarray,
    min_length_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Extend every path straight to at least ``min_length_m`` ``(M,)``.

    A path shorter than its minimum length gets one more point along its last
    non-degenerate segment (a path of one point, or of repeated points, runs along
    ``fallback_heading`` ``(M,)``, the agent's heading). Paths that are long enough get a
    zero-length extension, so every row gains exactly one point.

    Returns the extended paths ``(M, P+1, 2)`` (padded with the new end point) and their
    point counts ``(M,)`` (``path_points + 1``).
    """
    m, p = paths.shape[:2]
    rows = np.arange(m)
    total = cumulative_lengths(paths)[:, -1]
    dirs = segment_directions(paths, fallback_heading)
    if p >= 2:
        last_dir = dirs[rows, np.maximum(path_points - 2, 0)]
        single = path_points < 2
        last_dir[single] = np.stack(
            [np.cos(fallback_heading[single]), np.sin(fallback_heading[single])], axis=-1
        )
    else:
        last_dir = np.stack([np.cos(fallback_heading), np.sin(fallback_heading)], axis=-1)
    extra = np.maximum(np.asarray(min_length_m, dtype=np.float64) - total, 0.0)
    end = paths[rows, path_points - 1] + last_dir * extra[:, None]
    ext = np.concatenate([paths, paths[:, -1:]], axis=1)
    tail = np.arange(p + 1)[None, :] >= path_points[:, None]
    ext = np.where(tail[..., None], end[:, None, :], ext)
    return ext, path_points + 1


# ---------------------------------------------------------------------- lookup along paths
def _tie_runs(cum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last column of each run of equal arc lengths, both ``(M, P)``."""
    m, p = cum.shape
    cols = np.broadcast_to(np.arange(p), (m, p))
    new_run = np.ones((m, p), dtype=bool)
    new_run[:, 1:] = cum[:, 1:] != cum[:, :-1]
    start = np.maximum.accumulate(np.where(new_run, cols, 0), axis=1)
    ends_run = np.ones((m, p), dtype=bool)
    ends_run[:, :-1] = new_run[:, 1:]
    end = np.minimum.accumulate(np.where(ends_run, cols, p - 1)[:, ::-1], axis=1)[:, ::-1]
    return start, end


def locate(cum: np.ndarray, s: np.ndarray) -> np.ndarray:
    """For arc lengths ``s`` ``(M, K)`` (within ``[0, cum[:, -1]]``), the last point index
    ``j`` with ``cum[m, j] <= s[m, k]``, shape ``(M, K)``, exact.

    One ``searchsorted`` over all rows at once: each row's keys are shifted by a row offset
    so the flattened keys are sorted. The shift can round a query that lies within about
    1e-10 m of a breakpoint onto the wrong side; a short exact fix-up moves those indices
    by whole runs of equal arc lengths, so the result is what a per-row search would give.
    """
    m, p = cum.shape
    rows = np.arange(m)[:, None]
    span = 2.0 * float(max(cum.max(initial=0.0), s.max(initial=0.0))) + 1.0
    offset = np.arange(m, dtype=np.float64)[:, None] * span
    keys = (cum + offset).ravel()
    found = np.searchsorted(keys, (s + offset).ravel(), side="right").reshape(s.shape)
    idx = np.clip(found - 1 - rows * p, 0, p - 1)
    runs = None
    for _ in range(p + 1):
        nxt = np.minimum(idx + 1, p - 1)
        too_high = (idx > 0) & (cum[rows, idx] > s)
        too_low = (idx < p - 1) & (cum[rows, nxt] <= s)
        if not (too_high.any() or too_low.any()):
            break
        if runs is None:
            runs = _tie_runs(cum)
        start, end = runs
        idx = np.where(too_high, np.maximum(start[rows, idx] - 1, 0), idx)
        idx = np.where(too_low, end[rows, nxt], idx)
    return idx


def interpolate(paths: np.ndarray, cum: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points at arc lengths ``s`` ``(M, K)`` along ``paths`` ``(M, P, 2)`` with ``P >= 2``.

    ``s`` is clipped to ``[0, length]`` (callers extend paths first). Returns the points
    ``(M, K, 2)`` in m and the index ``(M, K)`` of the segment each lies on (the segment
    starting at the last point at or before ``s``; at the very end, the last segment).
    """
    m, p = cum.shape
    rows = np.arange(m)[:, None]
    s = np.clip(s, 0.0, cum[:, -1:])
    seg = np.minimum(locate(cum, s), p - 2)
    c0 = cum[rows, seg]
    seg_len = cum[rows, seg + 1] - c0
    ok = seg_len > 0
    frac = np.where(ok, (s - c0) / np.where(ok, seg_len, 1.0), 0.0)
    np.clip(frac, 0.0, 1.0, out=frac)
    a = paths[rows, seg]
    b = paths[rows, seg + 1]
    return a + frac[..., None] * (b - a), seg


def cut_paths(paths: np.ndarray, cum: np.ndarray, length_m: np.ndarray) -> np.ndarray:
    """Cut every path at arc length ``length_m`` ``(M,)``; returns ``(M, P, 2)``.

    Points beyond the cut are replaced by the cut point, so the result is the original
    path up to ``length_m`` followed by zero-length padding. A length of 0 leaves a single
    point (a standing agent's trajectory). Lengths beyond a path's end keep it whole.
    """
    length = np.minimum(np.asarray(length_m, dtype=np.float64), cum[:, -1])
    end, _ = interpolate(paths, cum, length[:, None])
    keep = cum <= length[:, None]
    return np.where(keep[..., None], paths, end)


def project_points(
    points: np.ndarray, path: np.ndarray, cum: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project ``points`` ``(K, 2)`` onto one polyline ``path`` ``(P, 2)`` (``cum`` ``(P,)``).

    Returns the distance ``(K,)`` in m to the nearest point of the polyline and that
    point's arc length ``(K,)`` in m. When several segments are equally near, the first
    along the path wins (smallest arc length).
    """
    if path.shape[0] < 2:
        d = np.hypot(points[:, 0] - path[0, 0], points[:, 1] - path[0, 1])
        return d, np.zeros(points.shape[0])
    a = path[:-1]
    ab = path[1:] - a  # (S, 2)
    len2 = ab[:, 0] ** 2 + ab[:, 1] ** 2
    rx = points[:, 0:1] - a[None, :, 0]  # (K, S)
    ry = points[:, 1:2] - a[None, :, 1]
    ok = len2 > 0
    t = np.where(ok, (rx * ab[:, 0] + ry * ab[:, 1]) / np.where(ok, len2, 1.0), 0.0)
    np.clip(t, 0.0, 1.0, out=t)
    dist = np.hypot(rx - t * ab[:, 0], ry - t * ab[:, 1])
    best = np.argmin(dist, axis=1)
    k = np.arange(points.shape[0])
    seg_len = np.sqrt(len2)
    return dist[k, best], cum[best] + t[k, best] * seg_len[best]


# ---------------------------------------------------------------------- segment maths
def _orient(ax, ay, bx, by, cx, cy):
    """Sign of the turn a -> b -> c: the cross product (b - a) x (c - a)."""
    return np.sign((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))


def _point_segment_distance(px, py, ax, ay, bx, by):
    """Distance from points to segments (all broadcastable); zero-length segments are points."""
    abx = bx - ax
    aby = by - ay
    len2 = abx * abx + aby * aby
    rx = px - ax
    ry = py - ay
    ok = len2 > 0
    t = np.where(ok, (rx * abx + ry * aby) / np.where(ok, len2, 1.0), 0.0)
    np.clip(t, 0.0, 1.0, out=t)
    return np.hypot(rx - t * abx, ry - t * aby)


def segments_intersect(p1, q1, p2, q2) -> np.ndarray:
    """Whether segments ``p1-q1`` and ``p2-q2`` (arrays ``(..., 2)``) share a point.

    Proper crossings and touching (an endpoint on the other segment, shared endpoints) are
    detected from orientation signs; the fully collinear case is left to the distance
    test, where an overlap shows up as an endpoint at distance zero.
    """
    p1x, p1y, q1x, q1y = p1[..., 0], p1[..., 1], q1[..., 0], q1[..., 1]
    p2x, p2y, q2x, q2y = p2[..., 0], p2[..., 1], q2[..., 0], q2[..., 1]
    o1 = _orient(p1x, p1y, q1x, q1y, p2x, p2y)
    o2 = _orient(p1x, p1y, q1x, q1y, q2x, q2y)
    o3 = _orient(p2x, p2y, q2x, q2y, p1x, p1y)
    o4 = _orient(p2x, p2y, q2x, q2y, q1x, q1y)
    collinear = (o1 == 0) & (o2 == 0) & (o3 == 0) & (o4 == 0)
    return (o1 * o2 <= 0) & (o3 * o4 <= 0) & ~collinear


def segment_distances(p1, q1, p2, q2) -> np.ndarray:
    """Exact minimum distance between segments ``p1-q1`` and ``p2-q2`` (arrays ``(..., 2)``).

    0 when they intersect, else the least of the four endpoint-to-segment distances.
    """
    d = np.minimum(
        np.minimum(
            _point_segment_distance(
                p1[..., 0], p1[..., 1], p2[..., 0], p2[..., 1], q2[..., 0], q2[..., 1]
            ),
            _point_segment_distance(
                q1[..., 0], q1[..., 1], p2[..., 0], p2[..., 1], q2[..., 0], q2[..., 1]
            ),
        ),
        np.minimum(
            _point_segment_distance(
                p2[..., 0], p2[..., 1], p1[..., 0], p1[..., 1], q1[..., 0], q1[..., 1]
            ),
            _point_segment_distance(
                q2[..., 0], q2[..., 1], p1[..., 0], p1[..., 1], q1[..., 0], q1[..., 1]
            ),
        ),
    )
    return np.where(segments_intersect(p1, q1, p2, q2), 0.0, d)


# ---------------------------------------------------------------------- chunked polylines
@dataclass(frozen=True, eq=False)
class ChunkedPolylines:
    """Polylines cut into chunks of ``K`` segments with bounding boxes (the prefilter).

    ``vertices`` ``(M, C, K+1, 2)``: chunk ``c`` holds vertices ``c*K .. c*K+K`` (chunks
    share their boundary vertex; rows are padded with their last point). ``lo``/``hi``
    ``(M, C, 2)``: the chunk's bounding box. ``cum`` ``(M, C, K+1)``: arc length of each
    vertex.
    """

    vertices: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    cum: np.ndarray

    @property
    def n_rows(self) -> int:
        return int(self.vertices.shape[0])

    def row(self, m: int) -> ChunkedPolylines:
        """The chunks of row ``m`` alone (shape ``(1, C, ...)``)."""
        sl = slice(m, m + 1)
        return ChunkedPolylines(self.vertices[sl], self.lo[sl], self.hi[sl], self.cum[sl])


def chunk_polylines(
    paths: np.ndarray, cum: np.ndarray | None = None, k: int = CHUNK_SEGMENTS
) -> ChunkedPolylines:
    """Chunk padded ``paths`` ``(M, P, 2)`` (any ``P >= 1``) for :func:`polyline_distances`."""
    p = paths.shape[1]
    if cum is None:
        cum = cumulative_lengths(paths)
    n_seg = max(p - 1, 1)
    c = -(-n_seg // k)
    # Pad to C*K + 1 points with the last point (zero-length segments).
    n_pts = c * k + 1
    pad = n_pts - p
    pts = np.concatenate([paths, np.repeat(paths[:, -1:], pad, axis=1)], axis=1)
    arc = np.concatenate([cum, np.repeat(cum[:, -1:], pad, axis=1)], axis=1)
    idx = np.arange(c)[:, None] * k + np.arange(k + 1)[None, :]  # (C, K+1)
    vertices = pts[:, idx]  # (M, C, K+1, 2)
    return ChunkedPolylines(
        vertices=vertices,
        lo=vertices.min(axis=2),
        hi=vertices.max(axis=2),
        cum=arc[:, idx],
    )


def _candidate_chunk_pairs(
    a: ChunkedPolylines, b: ChunkedPolylines, zero_only: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chunk pairs (row of ``b``, chunk of ``b``, chunk of ``a``) that may hold the minimum.

    Lower bound: the distance between the chunks' boxes. Upper bound per row: the least
    distance between the chunks' first vertices (real points of both polylines). A pair
    whose lower bound exceeds its row's upper bound cannot hold the minimum. With
    ``zero_only``, only pairs whose boxes touch (candidates for an intersection).
    """
    a_lo, a_hi = a.lo[0][None, None], a.hi[0][None, None]  # (1, 1, Ca, 2)
    b_lo, b_hi = b.lo[:, :, None], b.hi[:, :, None]  # (M, Cb, 1, 2)
    gap = np.maximum(np.maximum(b_lo - a_hi, a_lo - b_hi), 0.0)
    lower = np.hypot(gap[..., 0], gap[..., 1])  # (M, Cb, Ca)
    if zero_only:
        keep = lower == 0.0
    else:
        fa = a.vertices[0, :, 0][None, None]  # (1, 1, Ca, 2)
        fb = b.vertices[:, :, 0][:, :, None]  # (M, Cb, 1, 2)
        upper = np.hypot(fb[..., 0] - fa[..., 0], fb[..., 1] - fa[..., 1]).min(axis=(1, 2))
        keep = lower <= upper[:, None, None]
    return np.nonzero(keep)


def _chunk_pair_distances(av: np.ndarray, bv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact minimum distance ``(n,)`` between chunk polylines ``av``/``bv`` ``(n, K+1, 2)``.

    Uses that the minimum over all segment pairs is 0 when any pair intersects and else the
    least vertex-to-segment distance in either direction, so each vertex-segment distance
    and orientation is computed once. Also returns the intersection mask ``(n, K, K)``
    (a's segment, b's segment).
    """
    ax, ay = av[..., 0], av[..., 1]
    bx, by = bv[..., 0], bv[..., 1]
    # a's segments (axis 1) against b's vertices (axis 2), and the converse.
    a0x, a0y, a1x, a1y = ax[:, :-1, None], ay[:, :-1, None], ax[:, 1:, None], ay[:, 1:, None]
    b0x, b0y, b1x, b1y = bx[:, :-1, None], by[:, :-1, None], bx[:, 1:, None], by[:, 1:, None]
    pbx, pby = bx[:, None, :], by[:, None, :]
    pax, pay = ax[:, None, :], ay[:, None, :]
    d_ab = _point_segment_distance(pbx, pby, a0x, a0y, a1x, a1y)  # (n, K, K+1)
    d_ba = _point_segment_distance(pax, pay, b0x, b0y, b1x, b1y)  # (n, K, K+1)
    o_ab = _orient(a0x, a0y, a1x, a1y, pbx, pby)  # (n, Ka, Kb+1)
    o_ba = _orient(b0x, b0y, b1x, b1y, pax, pay)  # (n, Kb, Ka+1)
    o1, o2 = o_ab[:, :, :-1], o_ab[:, :, 1:]  # (n, Ka, Kb)
    o3 = np.swapaxes(o_ba[:, :, :-1], 1, 2)
    o4 = np.swapaxes(o_ba[:, :, 1:], 1, 2)
    collinear = (o1 == 0) & (o2 == 0) & (o3 == 0) & (o4 == 0)
    hit = (o1 * o2 <= 0) & (o3 * o4 <= 0) & ~collinear
    dist = np.minimum(d_ab.min(axis=(1, 2)), d_ba.min(axis=(1, 2)))
    return np.where(hit.any(axis=(1, 2)), 0.0, dist), hit


def polyline_distances(a: ChunkedPolylines, b: ChunkedPolylines) -> np.ndarray:
    """Exact minimum distance ``(M,)`` in m between polyline ``a`` (one row) and each row of ``b``.

    Segment to segment (not point sampling): 0 wherever the polylines cross or touch.
    """
    mb, cb, ca = _candidate_chunk_pairs(a, b)
    d, _ = _chunk_pair_distances(a.vertices[0, ca], b.vertices[mb, cb])
    out = np.full(b.n_rows, np.inf)
    # np.nonzero yields rows in ascending order, so each row's candidates are contiguous.
    starts = np.flatnonzero(np.r_[True, mb[1:] != mb[:-1]]) if mb.size else np.empty(0, int)
    if starts.size:
        out[mb[starts]] = np.minimum.reduceat(d, starts)
    return out


def first_intersections(
    a: ChunkedPolylines, b: ChunkedPolylines, rows: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Where each row of ``b`` first meets polyline ``a`` (one row), walking along ``b``.

    Returns the arc length along ``b`` ``(M,)`` and along ``a`` ``(M,)`` of that point, in
    m, NaN for rows that never meet ``a`` (and for rows outside the boolean mask ``rows``
    ``(M,)``, when given: callers pass the rows at distance 0). Where ``b`` runs along
    ``a`` (collinear overlap) the first shared point counts.
    """
    m = b.n_rows
    arc_b = np.full(m, np.nan)
    arc_a = np.full(m, np.nan)
    mb, cb, ca = _candidate_chunk_pairs(a, b, zero_only=True)
    if rows is not None:
        keep = rows[mb]
        mb, cb, ca = mb[keep], cb[keep], ca[keep]
    if mb.size == 0:
        return arc_b, arc_a
    av, bv = a.vertices[0, ca], b.vertices[mb, cb]
    _, hit = _chunk_pair_distances(av, bv)
    # Collinear overlaps are not flagged by the orientation test: among parallel segment
    # pairs, add those at distance 0.
    da = np.diff(av, axis=1)[:, :, None]  # (n, Ka, 1, 2)
    db = np.diff(bv, axis=1)[:, None, :]  # (n, 1, Kb, 2)
    parallel = (da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]) == 0
    pi, pa, pb = np.nonzero(parallel & ~hit)
    touch = segment_distances(av[pi, pa], av[pi, pa + 1], bv[pi, pb], bv[pi, pb + 1]) == 0.0
    hit[pi[touch], pa[touch], pb[touch]] = True
    pair, ia, ib = np.nonzero(hit)
    if pair.size == 0:
        return arc_b, arc_a
    p, q = bv[pair, ib], bv[pair, ib + 1]  # b's segment (walking direction)
    e0, e1 = av[pair, ia], av[pair, ia + 1]  # a's segment
    d = q - p
    e = e1 - e0
    w = e0 - p
    denom = d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0]
    crossing = denom != 0
    t_cross = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / np.where(crossing, denom, 1.0)
    # Parallel (or degenerate) segments that touch: the first point of their overlap,
    # i.e. the smaller projection of a's endpoints onto b's segment.
    len2 = d[:, 0] ** 2 + d[:, 1] ** 2
    safe = np.where(len2 > 0, len2, 1.0)
    w1 = e1 - p
    t_e0 = (w[:, 0] * d[:, 0] + w[:, 1] * d[:, 1]) / safe
    t_e1 = (w1[:, 0] * d[:, 0] + w1[:, 1] * d[:, 1]) / safe
    t_par = np.where(len2 > 0, np.minimum(t_e0, t_e1), 0.0)
    t = np.clip(np.where(crossing, t_cross, t_par), 0.0, 1.0)
    # The same point's parameter along a's segment (its projection).
    point = p + t[:, None] * d
    e_len2 = e[:, 0] ** 2 + e[:, 1] ** 2
    ok = e_len2 > 0
    u = np.where(ok, ((point - e0) * e).sum(axis=1) / np.where(ok, e_len2, 1.0), 0.0)
    np.clip(u, 0.0, 1.0, out=u)
    cb_arc = b.cum[mb[pair], cb[pair]]  # (n, K+1)
    ca_arc = a.cum[0, ca[pair]]
    k = np.arange(pair.size)
    s_b = cb_arc[k, ib] + t * (cb_arc[k, ib + 1] - cb_arc[k, ib])
    s_a = ca_arc[k, ia] + u * (ca_arc[k, ia + 1] - ca_arc[k, ia])
    owner = mb[pair]
    # Smallest arc along b per row (ties: smallest arc along a).
    order = np.lexsort((s_a, s_b, owner))
    owner_sorted = owner[order]
    first = order[np.r_[True, owner_sorted[1:] != owner_sorted[:-1]]]
    arc_b[owner[first]] = s_b[first]
    arc_a[owner[first]] = s_a[first]
    return arc_b, arc_a
