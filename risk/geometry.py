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

#: Segments per chunk for the bounding-box prefilter. On 150 m lane paths with 1.5 m point
#: spacing, 6 and 8 were fastest (4, 12 and 16 slower by 20-90%; measured on the frames of
#: benchmarks/bench_models.py).
CHUNK_SEGMENTS = 8

#: Largest float64 temporary, in elements, that the blocked loops below create. glibc
#: serves allocations above 128 KB with fresh pages from the OS, and the page faults cost
#: more than the arithmetic (measured: 8x slower on this project's 2-core VM); blocks of
#: 12000 elements (96 KB) stay under that threshold.
BLOCK_ELEMENTS = 12_000


def blocks(n_items: int, elements_per_item: int) -> list[slice]:
    """Slices covering ``range(n_items)`` with at most BLOCK_ELEMENTS elements per block."""
    step = max(1, BLOCK_ELEMENTS // max(elements_per_item, 1))
    return [slice(i, min(i + step, n_items)) for i in range(0, n_items, step)]


# ---------------------------------------------------------------------- parametrisation
def _norm(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Euclidean norm of components (``np.hypot`` is about 3x slower and not needed here)."""
    return np.sqrt(x * x + y * y)


def _row_base(m: int, width: int) -> np.ndarray:
    """Offsets ``(m, 1)`` of each row in a flattened ``(m, width)`` array."""
    return (np.arange(m) * width)[:, None]


def segment_lengths(paths: np.ndarray) -> np.ndarray:
    """Lengths ``(M, P-1)`` in m of the segments of ``paths`` ``(M, P, 2)``."""
    d = np.diff(paths, axis=1)
    return _norm(d[..., 0], d[..., 1])


def cumulative_lengths(paths: np.ndarray) -> np.ndarray:
    """Arc length ``(M, P)`` in m at every point of ``paths`` ``(M, P, 2)``; column 0 is 0.

    Padding points repeat the last arc length, so ``cum[:, -1]`` is each path's length.
    """
    cum = np.zeros(paths.shape[:2])
    np.cumsum(segment_lengths(paths), axis=1, out=cum[:, 1:])
    return cum


def _unit(heading: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(heading), np.sin(heading)], axis=-1)


def segment_unit_vectors(
    paths: np.ndarray, fallback_heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction components ``(M, P-1)`` x and y of every segment, degenerate filled.

    A zero-length segment (a repeated point or padding) takes the direction of the last
    non-degenerate segment before it; when there is none, the row's ``fallback_heading``
    ``(M,)`` in rad (the agent's heading). This is the path heading that prediction and the
    uncertainty model use.
    """
    m, p = paths.shape[:2]
    if p < 2:
        return np.empty((m, 0)), np.empty((m, 0))
    dx = np.diff(paths[..., 0], axis=1)
    dy = np.diff(paths[..., 1], axis=1)
    length = _norm(dx, dy)
    good = length > 0
    inv = 1.0 / np.where(good, length, 1.0)
    # Index of the last good segment at or before each segment (-1: none yet).
    last_good = np.where(good, np.arange(p - 1)[None, :], -1)
    np.maximum.accumulate(last_good, axis=1, out=last_good)
    src = np.maximum(last_good, 0) + _row_base(m, p - 1)
    none = last_good < 0
    ux = np.where(none, np.cos(fallback_heading)[:, None], np.take((dx * inv).ravel(), src))
    uy = np.where(none, np.sin(fallback_heading)[:, None], np.take((dy * inv).ravel(), src))
    return ux, uy


def segment_directions(paths: np.ndarray, fallback_heading: np.ndarray) -> np.ndarray:
    """:func:`segment_unit_vectors` stacked: ``(M, P-1, 2)``."""
    return np.stack(segment_unit_vectors(paths, fallback_heading), axis=-1)


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
    seg_len = segment_lengths(paths)  # (M, P-1); padding segments have length 0
    total = seg_len.sum(axis=1)
    direction = _unit(fallback_heading)
    if p >= 2:
        good = seg_len > 0
        has = np.asarray(good.any(axis=1))
        last = (p - 2) - np.argmax(good[:, ::-1], axis=1)
        vec = paths[rows, last + 1] - paths[rows, last]
        vec /= np.where(has, seg_len[rows, last], 1.0)[:, None]
        direction = np.where(has[:, None], vec, direction)
    extra = np.maximum(np.asarray(min_length_m, dtype=np.float64) - total, 0.0)
    end = paths[rows, path_points - 1] + direction * extra[:, None]
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
    base = _row_base(m, p)
    span = 2.0 * float(max(cum.max(initial=0.0), s.max(initial=0.0))) + 1.0
    offset = np.arange(m, dtype=np.float64)[:, None] * span
    flat = cum.ravel()
    found = np.searchsorted((cum + offset).ravel(), (s + offset).ravel(), side="right")
    idx = np.clip(found.reshape(s.shape) - 1 - base, 0, p - 1)
    runs = None
    for _ in range(p + 1):
        nxt = np.minimum(idx + 1, p - 1)
        too_high = (idx > 0) & (np.take(flat, idx + base) > s)
        too_low = (idx < p - 1) & (np.take(flat, nxt + base) <= s)
        if not (too_high.any() or too_low.any()):
            break
        if runs is None:
            runs = _tie_runs(cum)
        start, end = (r.ravel() for r in runs)
        idx = np.where(too_high, np.maximum(np.take(start, idx + base) - 1, 0), idx)
        idx = np.where(too_low, np.take(end, nxt + base), idx)
    return idx


def interpolate_components(
    px: np.ndarray, py: np.ndarray, cum: np.ndarray, s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`interpolate` on path components ``px``, ``py`` ``(M, P)``: returns the
    point components ``(M, K)`` x and y and the segment index ``(M, K)``."""
    m, p = cum.shape
    s = np.clip(s, 0.0, cum[:, -1:])
    seg = np.minimum(locate(cum, s), p - 2)
    g = seg + _row_base(m, p)
    flat_cum = cum.ravel()
    c0 = np.take(flat_cum, g)
    seg_len = np.take(flat_cum, g + 1) - c0
    ok = seg_len > 0
    frac = np.where(ok, (s - c0) / np.where(ok, seg_len, 1.0), 0.0)
    np.clip(frac, 0.0, 1.0, out=frac)
    out = []
    for comp in (px.ravel(), py.ravel()):
        a = np.take(comp, g)
        b = np.take(comp, g + 1)
        b -= a
        b *= frac
        b += a
        out.append(b)
    return out[0], out[1], seg


def interpolate(paths: np.ndarray, cum: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points at arc lengths ``s`` ``(M, K)`` along ``paths`` ``(M, P, 2)`` with ``P >= 2``.

    ``s`` is clipped to ``[0, length]`` (callers extend paths first). Returns the points
    ``(M, K, 2)`` in m and the index ``(M, K)`` of the segment each lies on (the segment
    starting at the last point at or before ``s``; at the very end, the last segment).
    """
    x, y, seg = interpolate_components(
        np.ascontiguousarray(paths[..., 0]), np.ascontiguousarray(paths[..., 1]), cum, s
    )
    return np.stack([x, y], axis=-1), seg


def cut_paths(
    paths: np.ndarray, cum: np.ndarray, length_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cut every path at arc length ``length_m`` ``(M,)``.

    Points beyond the cut are replaced by the cut point, so the result ``(M, P, 2)`` is
    the original path up to ``length_m`` followed by zero-length padding. A length of 0
    leaves a single point (a standing agent's trajectory); lengths beyond a path's end
    keep it whole. Also returns the number of real points ``(M,)`` of each cut path.
    """
    length = np.minimum(np.asarray(length_m, dtype=np.float64), cum[:, -1])
    flat = paths.reshape(-1, 2)
    m, p = cum.shape
    end_x, end_y, _ = interpolate_components(
        flat[:, 0].reshape(m, p), flat[:, 1].reshape(m, p), cum, length[:, None]
    )
    end = np.stack([end_x, end_y], axis=-1)  # (M, 1, 2)
    keep = cum <= length[:, None]
    return np.where(keep[..., None], paths, end), np.minimum(keep.sum(axis=1) + 1, cum.shape[1])


def project_points(
    points: np.ndarray, path: np.ndarray, cum: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project ``points`` ``(K, 2)`` onto one polyline ``path`` ``(P, 2)`` (``cum`` ``(P,)``).

    Returns the distance ``(K,)`` in m to the nearest point of the polyline and that
    point's arc length ``(K,)`` in m. When several segments are equally near, the first
    along the path wins (smallest arc length).
    """
    k = points.shape[0]
    if path.shape[0] < 2:
        d = _norm(points[:, 0] - path[0, 0], points[:, 1] - path[0, 1])
        return d, np.zeros(k)
    a = path[:-1]
    abx, aby = np.diff(path[:, 0]), np.diff(path[:, 1])  # (S,)
    len2 = abx * abx + aby * aby
    ok = len2 > 0
    inv2 = np.where(ok, 1.0 / np.where(ok, len2, 1.0), 0.0)
    seg_len = np.sqrt(len2)
    dist = np.empty(k)
    arc = np.empty(k)
    for blk in blocks(k, len(len2)):
        rx = points[blk, 0:1] - a[None, :, 0]  # (k_blk, S)
        ry = points[blk, 1:2] - a[None, :, 1]
        t = np.clip((rx * abx + ry * aby) * inv2, 0.0, 1.0)
        rx -= t * abx
        ry -= t * aby
        d2 = rx * rx + ry * ry
        best = np.argmin(d2, axis=1)
        rows = np.arange(best.size)
        dist[blk] = np.sqrt(d2[rows, best])
        arc[blk] = cum[best] + t[rows, best] * seg_len[best]
    return dist, arc


# ---------------------------------------------------------------------- segment maths
def _orient(ax, ay, bx, by, cx, cy):
    """Sign of the turn a -> b -> c: the cross product (b - a) x (c - a)."""
    return np.sign((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))


def point_segment_distance(px, py, ax, ay, bx, by):
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
            point_segment_distance(
                p1[..., 0], p1[..., 1], p2[..., 0], p2[..., 1], q2[..., 0], q2[..., 1]
            ),
            point_segment_distance(
                q1[..., 0], q1[..., 1], p2[..., 0], p2[..., 1], q2[..., 0], q2[..., 1]
            ),
        ),
        np.minimum(
            point_segment_distance(
                p2[..., 0], p2[..., 1], p1[..., 0], p1[..., 1], q1[..., 0], q1[..., 1]
            ),
            point_segment_distance(
                q2[..., 0], q2[..., 1], p1[..., 0], p1[..., 1], q1[..., 0], q1[..., 1]
            ),
        ),
    )
    return np.where(segments_intersect(p1, q1, p2, q2), 0.0, d)


# ---------------------------------------------------------------------- chunked polylines
@dataclass(frozen=True, eq=False)
class ChunkedPolylines:
    """Polylines cut into chunks of ``K`` segments, for the exact minimum distance.

    Chunk ``c`` of row ``m`` holds vertices ``c*K .. c*K+K`` (neighbouring chunks share
    their boundary vertex; rows are padded with their last point). Chunk ``(m, c)`` has
    the flat id ``m * C + c``. Per-vertex arrays are stored vertex-major, ``(K+1, M*C)``,
    so that after gathering candidate chunks the long axis is the last one and numpy's
    inner loops run over many chunks rather than over ``K`` (several times faster).

    - ``vx``, ``vy`` ``(K+1, M*C)``: vertices in m; ``cum`` ``(K+1, M*C)``: arc lengths;
    - ``sx``, ``sy`` ``(K, M*C)``: segment vectors; ``inv2`` ``(K, M*C)``: 1 / length^2
      (0 for zero-length segments, which then act as points);
    - ``lox``, ``loy``, ``hix``, ``hiy`` ``(M*C,)``: chunk bounding boxes;
    - ``active`` ``(M*C,)``: chunks holding at least one real segment (chunks made only
      of padding repeat the last point and are skipped).
    """

    n_rows: int
    n_chunks: int
    vx: np.ndarray
    vy: np.ndarray
    cum: np.ndarray
    sx: np.ndarray
    sy: np.ndarray
    inv2: np.ndarray
    lox: np.ndarray
    loy: np.ndarray
    hix: np.ndarray
    hiy: np.ndarray
    active: np.ndarray

    def row(self, m: int) -> ChunkedPolylines:
        """The chunks of row ``m`` alone."""
        c = self.n_chunks
        sl = slice(int(m) * c, int(m) * c + c)
        per_chunk = {name: getattr(self, name)[..., sl] for name in _CHUNK_FIELDS}
        return ChunkedPolylines(n_rows=1, n_chunks=c, **per_chunk)


_CHUNK_FIELDS = ("vx", "vy", "cum", "sx", "sy", "inv2", "lox", "loy", "hix", "hiy", "active")


def chunk_polylines(
    paths: np.ndarray,
    cum: np.ndarray | None = None,
    n_points: np.ndarray | None = None,
    k: int = CHUNK_SEGMENTS,
) -> ChunkedPolylines:
    """Chunk padded ``paths`` ``(M, P, 2)`` (any ``P >= 1``) for :func:`polyline_distances`.

    ``n_points`` ``(M,)``: real points per row (default all ``P``); chunks beyond them
    are marked inactive.
    """
    m, p = paths.shape[:2]
    if cum is None:
        cum = cumulative_lengths(paths)
    c = -(-max(p - 1, 1) // k)
    pad = c * k + 1 - p

    def vertex_major(a: np.ndarray) -> np.ndarray:
        """(M, P) per-point values -> (K+1, M*C): element [j, m*C + c] = a[m, c*K + j]."""
        a = np.concatenate([a, np.repeat(a[:, -1:], pad, axis=1)], axis=1)  # (M, C*K+1)
        a = np.ascontiguousarray(a)
        s_m, s_p = a.strides
        view = np.lib.stride_tricks.as_strided(
            a, shape=(k + 1, m, c), strides=(s_p, s_m, k * s_p), writeable=False
        )
        return view.reshape(k + 1, m * c)  # one copy

    vx, vy = vertex_major(paths[..., 0]), vertex_major(paths[..., 1])
    sx, sy = np.diff(vx, axis=0), np.diff(vy, axis=0)
    len2 = sx * sx + sy * sy
    # Segments shorter than 1e-150 m act as points (1 / len2 would overflow).
    real_seg = len2 > 1e-300
    inv2 = np.where(real_seg, 1.0 / np.where(real_seg, len2, 1.0), 0.0)
    real = np.full(m, p) if n_points is None else np.asarray(n_points)
    active = np.arange(c)[None, :] * k < np.maximum(real - 1, 1)[:, None]
    return ChunkedPolylines(
        n_rows=m,
        n_chunks=c,
        vx=vx,
        vy=vy,
        cum=vertex_major(cum),
        sx=sx,
        sy=sy,
        inv2=inv2,
        lox=vx.min(axis=0),
        loy=vy.min(axis=0),
        hix=vx.max(axis=0),
        hiy=vy.max(axis=0),
        active=active.ravel(),
    )


def _group_starts(owner: np.ndarray) -> np.ndarray:
    """Start index of each run of equal values in a sorted ``owner`` array."""
    return np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]]) if owner.size else owner


def _box_gaps2(a: ChunkedPolylines, b: ChunkedPolylines, cols: slice | np.ndarray) -> np.ndarray:
    """Squared distance ``(Ca, n_cols)`` between the boxes of a's chunks and b's chunks
    ``cols`` (flat ids; inf where either chunk is inactive): a lower bound for every
    segment pair in them."""
    col = np.s_[:, None]
    gx = np.maximum(np.maximum(b.lox[cols] - a.hix[col], a.lox[col] - b.hix[cols]), 0.0)
    gy = np.maximum(np.maximum(b.loy[cols] - a.hiy[col], a.loy[col] - b.hiy[cols]), 0.0)
    gx *= gx
    gy *= gy
    gx += gy
    gx[~(a.active[col] & b.active[cols])] = np.inf
    return gx


def _rowblocks(a: ChunkedPolylines, b: ChunkedPolylines) -> list[slice]:
    """Column slices of whole rows of ``b``, sized for BLOCK_ELEMENTS."""
    c = b.n_chunks
    return [slice(r.start * c, r.stop * c) for r in blocks(b.n_rows, a.n_chunks * c)]


def _candidate_pairs(
    a: ChunkedPolylines, b: ChunkedPolylines
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chunk pairs that may hold each row's minimum distance, pruned exactly.

    Stage 1: lower bound = box distance; upper bound per row = the least distance between
    the chunks' first vertices. Stage 2: for the survivors, upper bound = the least
    vertex-to-vertex distance inside the pairs (real points of both polylines, so within
    half a point spacing of the answer). A pair is dropped only when its lower bound
    exceeds an upper bound, so the minimum is never lost.

    Returns the flat chunk ids of b and of a for every pair (sorted by b's row), b's row
    of each pair, and ``zero`` ``(M,)``: rows already known to be at distance 0 (a shared
    vertex), whose pairs are dropped.
    """
    c = b.n_chunks
    found_b, found_a, found_lower = [], [], []
    for cols in _rowblocks(a, b):
        lower2 = _box_gaps2(a, b, cols)  # (Ca, n_cols)
        fx = b.vx[0, cols] - a.vx[0][:, None]
        fy = b.vy[0, cols] - a.vy[0][:, None]
        fx *= fx
        fy *= fy
        fx += fy
        fx[~np.isfinite(lower2)] = np.inf
        upper2 = fx.reshape(a.n_chunks, -1, c).min(axis=(0, 2))  # per row of the block
        fb, fa = np.nonzero((lower2 <= np.repeat(upper2, c)[None, :]).T)
        found_b.append(fb + cols.start)
        found_a.append(fa)
        found_lower.append(lower2[fa, fb])
    fb, fa, lower2 = (np.concatenate(x) for x in (found_b, found_a, found_lower))
    zero = np.zeros(b.n_rows, dtype=bool)
    if fb.size == 0:
        return fb, fa, fb, zero
    k1 = b.vx.shape[0]
    vv2 = np.empty(fb.size)
    for blk in blocks(fb.size, k1 * k1):
        ib, ia = fb[blk], fa[blk]
        dx = np.take(b.vx, ib, axis=1)[None, :, :] - np.take(a.vx, ia, axis=1)[:, None, :]
        dy = np.take(b.vy, ib, axis=1)[None, :, :] - np.take(a.vy, ia, axis=1)[:, None, :]
        dx *= dx
        dy *= dy
        dx += dy
        vv2[blk] = dx.min(axis=(0, 1))
    row = fb // c
    starts = _group_starts(row)
    row_upper2 = np.minimum.reduceat(vv2, starts)
    zero[row[starts]] = row_upper2 == 0.0
    counts = np.diff(np.r_[starts, row.size])
    keep = (lower2 <= np.repeat(row_upper2, counts)) & ~zero[row]
    return fb[keep], fa[keep], row[keep], zero


def _side_and_distance2(px, py, ox, oy, sx, sy, inv2):
    """Points ``(K+1, n)`` against segments starting at ``o`` with vectors ``s`` ``(K, n)``:
    orientation sign and squared distance, both ``(K, K+1, n)`` (segment, point, pair)."""
    rx = px[None, :, :] - ox[:, None, :]
    ry = py[None, :, :] - oy[:, None, :]
    sx3, sy3 = sx[:, None, :], sy[:, None, :]
    side = np.sign(sx3 * ry - sy3 * rx)
    t = (rx * sx3 + ry * sy3) * inv2[:, None, :]
    np.clip(t, 0.0, 1.0, out=t)
    rx -= t * sx3
    ry -= t * sy3
    return side, rx * rx + ry * ry


def _fine_block(
    a: ChunkedPolylines, b: ChunkedPolylines, fb: np.ndarray, fa: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_fine` for one block of pairs."""

    def take(c: ChunkedPolylines, name: str, ids: np.ndarray) -> np.ndarray:
        return np.take(getattr(c, name), ids, axis=1)

    avx, avy = take(a, "vx", fa), take(a, "vy", fa)
    bvx, bvy = take(b, "vx", fb), take(b, "vy", fb)
    o_ab, d2_ab = _side_and_distance2(
        bvx, bvy, avx[:-1], avy[:-1], take(a, "sx", fa), take(a, "sy", fa), take(a, "inv2", fa)
    )
    o_ba, d2_ba = _side_and_distance2(
        avx, avy, bvx[:-1], bvy[:-1], take(b, "sx", fb), take(b, "sy", fb), take(b, "inv2", fb)
    )
    o1, o2 = o_ab[:, :-1], o_ab[:, 1:]  # (Ka, Kb, n): b's segment ends vs a's segment
    o3 = o_ba[:, :-1].transpose(1, 0, 2)  # a's segment ends vs b's segment
    o4 = o_ba[:, 1:].transpose(1, 0, 2)
    collinear = (o1 == 0) & (o2 == 0) & (o3 == 0) & (o4 == 0)
    hit = (o1 * o2 <= 0) & (o3 * o4 <= 0) & ~collinear
    d2 = np.minimum(d2_ab.min(axis=(0, 1)), d2_ba.min(axis=(0, 1)))
    return np.where(hit.any(axis=(0, 1)), 0.0, np.sqrt(d2)), hit


def _fine(
    a: ChunkedPolylines, b: ChunkedPolylines, fb: np.ndarray, fa: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Exact minimum distance ``(n,)`` between the chunk pairs, and the intersection mask
    ``(Ka, Kb, n)`` (a's segment, b's segment, pair).

    The minimum over all segment pairs is 0 when any pair intersects, else the least
    vertex-to-segment distance in either direction; so each vertex-segment distance and
    orientation sign is computed once, not once per segment pair.
    """
    k = b.sx.shape[0]
    parts = [_fine_block(a, b, fb[blk], fa[blk]) for blk in blocks(fb.size, k * (k + 1))]
    if len(parts) == 1:
        return parts[0]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts], axis=2)


def polyline_distances(a: ChunkedPolylines, b: ChunkedPolylines) -> np.ndarray:
    """Exact minimum distance ``(M,)`` in m between polyline ``a`` (one row) and each row of ``b``.

    Segment to segment (not point sampling): 0 wherever the polylines cross or touch.
    """
    fb, fa, row, zero = _candidate_pairs(a, b)
    out = np.full(b.n_rows, np.inf)
    out[zero] = 0.0
    if fb.size:
        d, _ = _fine(a, b, fb, fa)
        starts = _group_starts(row)
        out[row[starts]] = np.minimum.reduceat(d, starts)
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
    c = b.n_chunks
    row_ids = np.arange(m) if rows is None else np.flatnonzero(rows)
    found_b, found_a = [], []
    for blk in blocks(row_ids.size, a.n_chunks * c):
        cols = (row_ids[blk, None] * c + np.arange(c)[None, :]).ravel()
        fb, fa = np.nonzero((_box_gaps2(a, b, cols) == 0.0).T)  # boxes touch
        found_b.append(cols[fb])
        found_a.append(fa)
    if not found_b:
        return arc_b, arc_a
    fb, fa = np.concatenate(found_b), np.concatenate(found_a)
    if fb.size == 0:
        return arc_b, arc_a
    _, hit = _fine(a, b, fb, fa)  # (Ka, Kb, n)
    av = np.stack([np.take(a.vx, fa, axis=1), np.take(a.vy, fa, axis=1)], axis=-1)
    bv = np.stack([np.take(b.vx, fb, axis=1), np.take(b.vy, fb, axis=1)], axis=-1)  # (K+1, n, 2)
    # Collinear overlaps are not flagged by the orientation test: among parallel segment
    # pairs, add those at distance 0.
    da = np.diff(av, axis=0)[:, None]  # (Ka, 1, n, 2)
    db = np.diff(bv, axis=0)[None, :]  # (1, Kb, n, 2)
    parallel = (da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]) == 0
    pa, pb, pi = np.nonzero(parallel & ~hit)
    touch = segment_distances(av[pa, pi], av[pa + 1, pi], bv[pb, pi], bv[pb + 1, pi]) == 0.0
    hit[pa[touch], pb[touch], pi[touch]] = True
    ia, ib, pair = np.nonzero(hit)
    if pair.size == 0:
        return arc_b, arc_a
    p, q = bv[ib, pair], bv[ib + 1, pair]  # b's segment (walking direction)
    e0, e1 = av[ia, pair], av[ia + 1, pair]  # a's segment
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
    b_id, a_id = fb[pair], fa[pair]
    s_b0, s_b1 = b.cum[ib, b_id], b.cum[ib + 1, b_id]
    s_a0, s_a1 = a.cum[ia, a_id], a.cum[ia + 1, a_id]
    s_b = s_b0 + t * (s_b1 - s_b0)
    s_a = s_a0 + u * (s_a1 - s_a0)
    owner = b_id // b.n_chunks
    # Smallest arc along b per row (ties: smallest arc along a).
    order = np.lexsort((s_a, s_b, owner))
    first = order[_group_starts(owner[order])]
    arc_b[owner[first]] = s_b[first]
    arc_a[owner[first]] = s_a[first]
    return arc_b, arc_a
