"""The kernel's path geometry: extending and cutting a path candidate, the chunk
bounding boxes that prune the segment searches, the exact least distance between two
polylines, a point's projection onto a polyline and the first crossing of two (as
:mod:`risk.geometry` computes them, operation by operation)."""

from __future__ import annotations

import math

import numpy as np

from risk.kernel_jit import _inner
from risk.kernel_shared import INF, K


@_inner
def _segment_lengths(paths, m, seg):
    """``seg[j]``: the length of segment ``j`` of path row ``m`` (for :func:`_extend`)."""
    p = paths.shape[1]
    for j in range(p - 1):  # (a loop of plain arithmetic: vectorised)
        dx = paths[m, j + 1, 0] - paths[m, j, 0]
        dy = paths[m, j + 1, 1] - paths[m, j, 1]
        seg[j] = math.sqrt(dx * dx + dy * dy)


@_inner
def _extend(paths, m, npts, heading, min_len, seg, total, ex_rows, ey_rows, ecum_rows,
            eux_rows, euy_rows, row):  # fmt: skip
    """risk.geometry.extend_paths, cumulative_lengths and segment_unit_vectors for row m,
    from its segment lengths ``seg`` (:func:`_segment_lengths`) and their sum ``total``
    (:func:`np_sum`).

    Writes the padded extended path (P+1 points) into row ``row`` of the ``*_rows``
    (rows, not row views: see :func:`_polyline_distance`) and returns its real point
    count. The unit vectors are written only for the segments that start within
    ``min_len`` (the prediction's reach, ``v T``): the prediction reads no others.

    The caller sums: numba keeps an atomic reference-count increment and decrement per
    array argument around each call that LLVM does not inline (such as np_sum)."""
    ex, ey, ecum = ex_rows[row], ey_rows[row], ecum_rows[row]
    eux, euy = eux_rows[row], euy_rows[row]
    p = paths.shape[1]
    p1 = p + 1
    last = p - 2
    while last >= 0 and not seg[last] > 0:
        last -= 1  # the last segment of non-zero length (padding has none)
    if last >= 0:
        dirx = (paths[m, last + 1, 0] - paths[m, last, 0]) / seg[last]
        diry = (paths[m, last + 1, 1] - paths[m, last, 1]) / seg[last]
    else:
        dirx, diry = math.cos(heading), math.sin(heading)
    extra = max(min_len - total, 0.0)
    endx = paths[m, npts - 1, 0] + dirx * extra
    endy = paths[m, npts - 1, 1] + diry * extra
    for j in range(p1):
        if j < npts:
            ex[j], ey[j] = paths[m, j, 0], paths[m, j, 1]
        else:
            ex[j], ey[j] = endx, endy
    ecum[0] = 0.0
    have = False
    hx, hy = math.cos(heading), math.sin(heading)
    lx, ly = hx, hy
    c = 0.0  # ecum[j + 1], kept in a register
    for j in range(p1 - 1):
        start = c
        # the given segments keep their lengths (same points, same root)
        if j < npts - 1:
            length = seg[j]
            c = start + length
            ecum[j + 1] = c
            if start > min_len:
                continue  # beyond the prediction's reach: no unit vector needed
            dx = paths[m, j + 1, 0] - paths[m, j, 0]
            dy = paths[m, j + 1, 1] - paths[m, j, 1]
        else:
            dx = ex[j + 1] - ex[j]
            dy = ey[j + 1] - ey[j]
            length = math.sqrt(dx * dx + dy * dy)
            c = start + length
            ecum[j + 1] = c
            if start > min_len:
                continue
        if length > 0:
            inv = 1.0 / length
            lx, ly = dx * inv, dy * inv
            have = True
        if have:
            eux[j], euy[j] = lx, ly
        else:
            eux[j], euy[j] = hx, hy
    return npts + 1


@_inner
def _interp(ex, ey, ecum, s, j):
    """Point at arc ``s`` of a padded path (risk.geometry.interpolate_components).

    ``j`` is a start index for the search (any index with ``ecum[j] <= s``). Returns x,
    y, the segment index and the last point index with ``ecum <= s``."""
    p1 = ex.shape[0]
    s = min(max(s, 0.0), ecum[p1 - 1])
    while j + 1 < p1 and ecum[j + 1] <= s:
        j += 1
    seg = min(j, p1 - 2)
    c0 = ecum[seg]
    length = ecum[seg + 1] - c0
    frac = (s - c0) / length if length > 0 else 0.0
    frac = min(max(frac, 0.0), 1.0)
    x = (ex[seg + 1] - ex[seg]) * frac + ex[seg]
    y = (ey[seg + 1] - ey[seg]) * frac + ey[seg]
    return x, y, seg, j


@_inner
def _cut(ex, ey, ecum, length_m, cx, cy):
    """risk.geometry.cut_paths for one padded path; returns the cut's point count."""
    p1 = ex.shape[0]
    length = min(length_m, ecum[p1 - 1])
    endx, endy, _, _ = _interp(ex, ey, ecum, length, 0)
    keep = 0
    for j in range(p1):
        if ecum[j] <= length:
            keep += 1
    n = min(keep + 1, p1)
    for j in range(n):
        if j < keep:
            cx[j], cy[j] = ex[j], ey[j]
        else:
            cx[j], cy[j] = endx, endy
    return n


@_inner
def _cut_boxes(cx, cy, cn, ecum, length_m, ebox, en, box):
    """:func:`_boxes` of a cut made by :func:`_cut` from a path with chunk boxes ``ebox``
    (``en`` points): a chunk whose points are all points of that path, at the same
    indices, has the same box and is copied."""
    p1 = ecum.shape[0]
    length = min(length_m, ecum[p1 - 1])
    keep = 0
    for j in range(p1):
        if ecum[j] <= length:
            keep += 1
    nseg = max(cn - 1, 1)
    nc = (nseg + K - 1) // K
    for ci in range(nc):
        j0 = ci * K
        j1 = min(j0 + K, cn - 1)
        if j1 == j0 + K and j1 < keep and j1 <= en - 1:
            box[ci, 0], box[ci, 1], box[ci, 2], box[ci, 3] = (
                ebox[ci, 0], ebox[ci, 1], ebox[ci, 2], ebox[ci, 3]
            )  # fmt: skip
            continue
        _chunk_box(cx, cy, j0, j1, box, ci)
    return nc


@_inner
def _boxes(x, y, n, box):
    """Bounding boxes (lox, loy, hix, hiy) of chunks of K segments; returns the count."""
    nseg = max(n - 1, 1)
    c = (nseg + K - 1) // K
    for ci in range(c):
        j0 = ci * K
        _chunk_box(x, y, j0, min(j0 + K, n - 1), box, ci)
    return c


@_inner
def _chunk_box(x, y, j0, j1, box, ci):
    """``box[ci]`` = the bounding box (lox, loy, hix, hiy) of points ``j0 .. j1``."""
    lox, loy, hix, hiy = x[j0], y[j0], x[j0], y[j0]
    for j in range(j0 + 1, j1 + 1):
        lox = min(lox, x[j])
        hix = max(hix, x[j])
        loy = min(loy, y[j])
        hiy = max(hiy, y[j])
    box[ci, 0], box[ci, 1], box[ci, 2], box[ci, 3] = lox, loy, hix, hiy


@_inner
def _gap2(a, ia, b, ib):
    gx = max(max(b[ib, 0] - a[ia, 2], a[ia, 0] - b[ib, 2]), 0.0)
    gy = max(max(b[ib, 1] - a[ia, 3], a[ia, 1] - b[ib, 3]), 0.0)
    return gx * gx + gy * gy


@_inner
def _sign(v):
    return 1.0 if v > 0 else (-1.0 if v < 0 else 0.0)


@_inner
def _pseg2(px, py, ox, oy, sx, sy, inv2):
    """Squared distance from a point to a segment (as risk.geometry._side_and_distance2)."""
    rx = px - ox
    ry = py - oy
    t = (rx * sx + ry * sy) * inv2
    t = min(max(t, 0.0), 1.0)
    rx -= t * sx
    ry -= t * sy
    return rx * rx + ry * ry


@_inner
def _polyline_distance(
    ax_rows, ay_rows, ra, an, abox_rows, nca, bx_rows, by_rows, rb, bn, bbox_rows, ncb, gaps,
    stop2, cut2, above,
):  # fmt: skip
    """Exact least distance between polylines a and b (risk.geometry.polyline_distances):
    a is row ``ra`` of ``ax_rows``, ``ay_rows`` (its chunk boxes ``abox_rows[ra]``), b
    row ``rb`` of the others. The caller passes rows, not row views: a view made there
    costs an atomic reference-count increment and decrement per call, while the views
    made here are pruned (no call in between).

    Chunk pairs whose boxes are farther apart than the best distance found so far (or than
    ``sqrt(cut2)``) are skipped, which never loses the minimum below ``sqrt(cut2)``. Returns
    early once the squared distance is at most ``stop2`` (pass -1 for the exact value),
    then with an upper bound of the distance (the distance of two points) at most
    ``sqrt(stop2)``, not the minimum.
    ``above``: a squared distance known to lie above the minimum (inf if none), to prune
    with from the start; should nothing be nearer after all, the search runs again
    without it.

    No calls that LLVM does not inline, and one return at the end: otherwise numba keeps
    an atomic reference-count increment and decrement per array argument per call (its
    pruning pass gives up on such control flow), which cost more than the search of a
    typical chunk pair. (Counted in the LLVM code: ``inspect_llvm``, ``NRT_incref``.)"""
    ax, ay, abox = ax_rows[ra], ay_rows[ra], abox_rows[ra]
    bx, by, bbox = bx_rows[rb], by_rows[rb], bbox_rows[rb]
    # b's whole box, then a lower bound per chunk of a (its gap to that box): rows of
    # chunk pairs are skipped whole, and the pair to start from is found without the
    # full table of box gaps
    blox, bloy, bhix, bhiy = bbox[0, 0], bbox[0, 1], bbox[0, 2], bbox[0, 3]
    for j in range(1, ncb):
        blox = min(blox, bbox[j, 0])
        bloy = min(bloy, bbox[j, 1])
        bhix = max(bhix, bbox[j, 2])
        bhiy = max(bhiy, bbox[j, 3])
    rmin, amin = INF, np.int64(0)
    for i in range(nca):
        gx = max(max(blox - abox[i, 2], abox[i, 0] - bhix), 0.0)
        gy = max(max(bloy - abox[i, 3], abox[i, 1] - bhiy), 0.0)
        g = gx * gx + gy * gy
        gaps[i] = g
        if g < rmin:
            rmin, amin = g, i
    out = -1.0  # the result once set
    if rmin > cut2:
        out = math.sqrt(rmin)  # a lower bound beyond the cut: the caller drops
    if out < 0:  # (not "else": then numba keeps the reference counts, see above)
        gmin, bmin = INF, np.int64(0)
        for j in range(ncb):
            g = _gap2(abox, amin, bbox, j)
            if g < gmin:
                gmin, bmin = g, j
        if stop2 >= 0 and gmin <= stop2:
            # Keep/drop mode: any two points bound the distance from above, so the ends of
            # the nearest chunks, when close enough, settle "keep" without a search.
            w2 = INF
            for ia in (amin * K, min(amin * K + K // 2, an - 1), min(amin * K + K, an - 1)):
                for jb in (bmin * K, min(bmin * K + K // 2, bn - 1), min(bmin * K + K, bn - 1)):
                    dx = ax[ia] - bx[jb]
                    dy = ay[ia] - by[jb]
                    w2 = min(w2, dx * dx + dy * dy)
            if w2 <= stop2:
                out = math.sqrt(w2)
        start = above
        while out < 0:
            best = start
            # The chunk pairs in search order: (amin, bmin) when within the cut, then the
            # others row by row, each only while its box gap is below the best so far.
            ca, cb, g = amin, bmin, gmin
            first = True
            run = gmin <= cut2
            ri, rj = np.int64(0), np.int64(0)  # the row-by-row scan's next pair
            while True:
                if run:
                    # As risk.geometry._fine: 0 when two segments cross; else the least
                    # distance of two segments is the least of their vertex-to-segment
                    # distances, so each vertex-segment distance is computed once per chunk
                    # pair, not once per segment pair (a's segments to b's vertices, then
                    # the other way unless already at most stop2).
                    crossed = False
                    if g == 0.0:  # (chunk boxes apart: no segments can cross)
                        # A segment of chunk ca of a crosses or touches one of chunk cb of b
                        # by the orientation test of _fine (collinear overlaps excluded:
                        # their distance is 0 anyway); only pairs whose boxes touch.
                        for i in range(ca * K, min(ca * K + K, max(an - 1, 1))):
                            i1 = min(i + 1, an - 1)
                            p1x, p1y = ax[i], ay[i]
                            q1x, q1y = ax[i1], ay[i1]
                            s1x, s1y = q1x - p1x, q1y - p1y
                            lo1x, hi1x = min(p1x, q1x), max(p1x, q1x)
                            lo1y, hi1y = min(p1y, q1y), max(p1y, q1y)
                            for j in range(cb * K, min(cb * K + K, max(bn - 1, 1))):
                                j1 = min(j + 1, bn - 1)
                                p2x, p2y = bx[j], by[j]
                                q2x, q2y = bx[j1], by[j1]
                                if min(p2x, q2x) > hi1x or lo1x > max(p2x, q2x):
                                    continue
                                if min(p2y, q2y) > hi1y or lo1y > max(p2y, q2y):
                                    continue
                                s2x, s2y = q2x - p2x, q2y - p2y
                                o1 = _sign(s1x * (p2y - p1y) - s1y * (p2x - p1x))
                                o2 = _sign(s1x * (q2y - p1y) - s1y * (q2x - p1x))
                                if o1 * o2 > 0:
                                    continue
                                o3 = _sign(s2x * (p1y - p2y) - s2y * (p1x - p2x))
                                o4 = _sign(s2x * (q1y - p2y) - s2y * (q1x - p2x))
                                collinear = o1 == 0 and o2 == 0 and o3 == 0 and o4 == 0
                                if o3 * o4 <= 0 and not collinear:
                                    crossed = True
                                    break
                            if crossed:
                                break
                    d = 0.0
                    if not crossed:
                        d = best
                        for side in range(2):
                            if side == 1 and d <= stop2:
                                break  # the caller stops here
                            ux, uy, un, cu, vx, vy, vn, cv = ax, ay, an, ca, bx, by, bn, cb
                            vlox, vloy, vhix, vhiy = (
                                bbox[cb, 0],
                                bbox[cb, 1],
                                bbox[cb, 2],
                                bbox[cb, 3],
                            )
                            if side == 1:
                                ux, uy, un, cu, vx, vy, vn, cv = bx, by, bn, cb, ax, ay, an, ca
                                vlox, vloy, vhix, vhiy = (
                                    abox[ca, 0],
                                    abox[ca, 1],
                                    abox[ca, 2],
                                    abox[ca, 3],
                                )
                            # the vertices of chunk cv of v to the segments of chunk cu of u
                            su = max(un - 1, 1)
                            j0 = cv * K
                            j1 = min(cv * K + K, max(vn - 1, 1))  # (its last segment's end)
                            for i in range(cu * K, min(cu * K + K, su)):
                                i1 = min(i + 1, un - 1)
                                ox, oy = ux[i], uy[i]
                                qx, qy = ux[i1], uy[i1]
                                lox, hix = min(ox, qx), max(ox, qx)
                                loy, hiy = min(oy, qy), max(oy, qy)
                                # The chunk's vertices lie in its box (whose bounds are
                                # vertices), so each one's gap below is at least this one
                                # (rounding is monotone): a segment this far from the box is
                                # skipped whole, as each of its vertices would be.
                                hx = max(max(lox - vhix, vlox - hix), 0.0)
                                hy = max(max(loy - vhiy, vloy - hiy), 0.0)
                                if hx * hx + hy * hy > d:
                                    continue
                                sx, sy = qx - ox, qy - oy
                                len2 = sx * sx + sy * sy
                                inv2 = 1.0 / len2 if len2 > 1e-300 else 0.0
                                for j in range(j0, j1 + 1):
                                    jj = min(j, vn - 1)
                                    px, py = vx[jj], vy[jj]
                                    hx = max(max(lox - px, px - hix), 0.0)
                                    hy = max(max(loy - py, py - hiy), 0.0)
                                    if hx * hx + hy * hy > d:
                                        continue  # no nearer than the box: skipped
                                    d = min(d, _pseg2(px, py, ox, oy, sx, sy, inv2))
                    if first or d < best:
                        best = d
                        if best == 0.0 or best <= stop2:
                            out = math.sqrt(best)
                            break
                first = False
                run = False
                while ri < nca:
                    if rj == 0 and (gaps[ri] >= best or gaps[ri] > cut2):
                        ri += 1
                        continue  # no pair of this row is nearer than the best
                    if rj == ncb:
                        ri, rj = ri + 1, np.int64(0)
                        continue
                    ca, cb = ri, rj
                    rj += 1
                    g = _gap2(abox, ca, bbox, cb)
                    if not (g >= best or g > cut2 or (ca == amin and cb == bmin)):
                        run = True  # (a pair no nearer than the best cannot lower it)
                        break
                if not run:
                    break
            if out < 0 and (best < start or start == INF):
                out = math.sqrt(best)  # found below the bound: the minimum
            start = INF  # nothing nearer than the bound after all: again without it
    return out


@_inner
def _segments(ex, ey, n, inv2, slen):
    """Per segment of a polyline: ``1 / length^2`` (0 for a zero-length one) and the
    length, as risk.geometry.project_points computes them."""
    for j in range(n - 1):
        abx = ex[j + 1] - ex[j]
        aby = ey[j + 1] - ey[j]
        len2 = abx * abx + aby * aby
        inv2[j] = 1.0 / len2 if len2 > 0 else 0.0
        slen[j] = math.sqrt(len2)


@_inner
def _project(px, py, ex, ey, ecum, n, inv2, slen, box, nb, e):
    """Distance from a point to a polyline and the arc length of the nearest point, the
    first along the path on ties (risk.geometry.project_points), for the polyline in row
    ``e`` of the array arguments (indexed in place: a row view costs an atomic reference
    count where it outlives a call). ``inv2``, ``slen``: from :func:`_segments`; ``box``,
    ``nb``: the chunk boxes. Chunks are walked in order and
    one whose box is farther than the best so far is skipped (it holds no nearer point,
    and a later tie never wins).

    A bound first: the least distance ``b`` to the segments of the chunk whose box is
    nearest. A chunk whose box is farther than ``b + 1 um`` holds no point as near as the
    minimum (the margin covers the rounding of both distances for coordinates up to about
    1e8 m), so it is skipped from the start: the same chunks decide the result, in the
    same order."""
    cb, gb = np.int64(0), INF
    for c in range(nb):
        gx = max(max(box[e, c, 0] - px, px - box[e, c, 2]), 0.0)
        gy = max(max(box[e, c, 1] - py, py - box[e, c, 3]), 0.0)
        if gx * gx + gy * gy < gb:
            cb, gb = c, gx * gx + gy * gy
    bound = INF
    for j in range(cb * K, min(cb * K + K, n - 1)):
        ox, oy = ex[e, j], ey[e, j]
        sx, sy = ex[e, j + 1] - ox, ey[e, j + 1] - oy
        bound = min(bound, _pseg2(px, py, ox, oy, sx, sy, inv2[e, j]))
    bound = (math.sqrt(bound) + 1e-6) ** 2
    best, arc = INF, 0.0
    for c in range(nb):
        gx = max(max(box[e, c, 0] - px, px - box[e, c, 2]), 0.0)
        gy = max(max(box[e, c, 1] - py, py - box[e, c, 3]), 0.0)
        if gx * gx + gy * gy > best or gx * gx + gy * gy > bound:
            continue
        for j in range(c * K, min(c * K + K, n - 1)):
            abx = ex[e, j + 1] - ex[e, j]
            aby = ey[e, j + 1] - ey[e, j]
            rx = px - ex[e, j]
            ry = py - ey[e, j]
            t = min(max((rx * abx + ry * aby) * inv2[e, j], 0.0), 1.0)
            rx -= t * abx
            ry -= t * aby
            d2 = rx * rx + ry * ry
            if d2 < best:
                best = d2
                arc = ecum[e, j] + t * slen[e, j]
    return math.sqrt(best), arc


@_inner
def _touch0(px, py, ax, ay, bx, by):
    """Whether risk.geometry._point_segment_distance is exactly 0."""
    abx = bx - ax
    aby = by - ay
    len2 = abx * abx + aby * aby
    rx = px - ax
    ry = py - ay
    t = (rx * abx + ry * aby) / len2 if len2 > 0 else 0.0
    t = min(max(t, 0.0), 1.0)
    return rx - t * abx == 0.0 and ry - t * aby == 0.0


@_inner
def _first_crossing(bx, by, bcum, bn, bbox, ncb, ax, ay, acum, an, abox, nca):
    """Arc lengths (along b, along a) of the first point along polyline b that lies on a
    (risk.geometry.first_intersections); NaN, NaN when they never meet."""
    best_b, best_a = INF, INF
    for cb in range(ncb):
        if bcum[min(cb * K, bn - 1)] > best_b:
            break  # every later segment starts beyond the crossing found
        for ca in range(nca):
            if _gap2(abox, ca, bbox, cb) != 0.0:
                continue
            for i in range(cb * K, min(cb * K + K, bn - 1)):
                if bcum[i] > best_b:
                    break  # any point of this segment lies beyond the crossing found
                px, py = bx[i], by[i]
                qx, qy = bx[i + 1], by[i + 1]
                dx, dy = qx - px, qy - py
                lox, hix = min(px, qx), max(px, qx)
                loy, hiy = min(py, qy), max(py, qy)
                for j in range(ca * K, min(ca * K + K, an - 1)):
                    e0x, e0y = ax[j], ay[j]
                    e1x, e1y = ax[j + 1], ay[j + 1]
                    if min(e0x, e1x) > hix or lox > max(e0x, e1x):
                        continue  # the segments' boxes do not touch: they cannot meet
                    if min(e0y, e1y) > hiy or loy > max(e0y, e1y):
                        continue
                    ex_, ey_ = e1x - e0x, e1y - e0y
                    o1 = _sign(ex_ * (py - e0y) - ey_ * (px - e0x))
                    o2 = _sign(ex_ * (qy - e0y) - ey_ * (qx - e0x))
                    o3 = _sign(dx * (e0y - py) - dy * (e0x - px))
                    o4 = _sign(dx * (e1y - py) - dy * (e1x - px))
                    collinear = o1 == 0 and o2 == 0 and o3 == 0 and o4 == 0
                    hit = o1 * o2 <= 0 and o3 * o4 <= 0 and not collinear
                    if not hit and ex_ * dy - ey_ * dx == 0:
                        hit = (
                            _touch0(e0x, e0y, px, py, qx, qy)
                            or _touch0(e1x, e1y, px, py, qx, qy)
                            or _touch0(px, py, e0x, e0y, e1x, e1y)
                            or _touch0(qx, qy, e0x, e0y, e1x, e1y)
                        )
                    if not hit:
                        continue
                    wx, wy = e0x - px, e0y - py
                    denom = dx * ey_ - dy * ex_
                    len2 = dx * dx + dy * dy
                    if denom != 0:
                        t = (wx * ey_ - wy * ex_) / denom
                    elif len2 > 0:
                        t0 = (wx * dx + wy * dy) / len2
                        t1 = ((e1x - px) * dx + (e1y - py) * dy) / len2
                        t = min(t0, t1)
                    else:
                        t = 0.0
                    t = min(max(t, 0.0), 1.0)
                    ptx = px + t * dx
                    pty = py + t * dy
                    el2 = ex_ * ex_ + ey_ * ey_
                    u = ((ptx - e0x) * ex_ + (pty - e0y) * ey_) / el2 if el2 > 0 else 0.0
                    u = min(max(u, 0.0), 1.0)
                    s_b = bcum[i] + t * (bcum[i + 1] - bcum[i])
                    s_a = acum[j] + u * (acum[j + 1] - acum[j])
                    if s_b < best_b or (s_b == best_b and s_a < best_a):
                        best_b, best_a = s_b, s_a
    if best_b == INF:
        return math.nan, math.nan
    return best_b, best_a
