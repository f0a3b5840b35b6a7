"""The kernel's code: the compiled production path of :func:`risk.evaluate` and of the
fused cascade. :mod:`risk.kernel` loads it (compiled ahead of time by
:mod:`risk.kernel_aot`, or just in time here); call it through that module.

One pass per agent row: for each path candidate of each requested agent the kernel

1. extends the path straight to ``v T`` (and cuts it at ``v T`` when trajectory distance
   is asked for);
2. predicts it at constant speed along the path, with the per-kind covariances;
3. runs every requested model against every ego candidate: exact segment distances
   pruned by chunk bounding boxes, the closest encounter, headway and 2D headway, the
   circles, and one loop for the Gaussian overlap and survival analysis.

Everything per row lives in scratch buffers of one path or one horizon (a few kB), so
nothing grows with ``N^2`` and memory stays cache-sized; only the ego's candidates are
kept for the whole call. The maths follows the vectorised numpy modules
(:mod:`risk.distance`, :mod:`risk.temporal`, :mod:`risk.stochastic`, :mod:`risk.prediction`)
operation by operation, including numpy's pairwise summation, so that the results agree
with them within a few ulps, mostly bit for bit (numpy's AVX-512 ``exp`` differs from the C
library's in the last bit; the pruned distance search may round a least distance another
way; tests/exactness.py); those modules and :mod:`risk.reference` are the oracles the
tests compare with.

Compile cost: every function is ``@njit(cache=True)`` and none is recursive (a recursive
cached function crashed on cache load). The cache folder is ``NUMBA_CACHE_DIR`` when set,
else a per-user folder (``$XDG_CACHE_HOME/riskreplay/numba`` or
``~/.cache/riskreplay/numba``; :func:`risk.kernel_shared.cache_dir`). A cold start logs
one warning that it is compiling.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import pathlib
import sys

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, event, types
from numba.extending import intrinsic

from risk.kernel_shared import (
    CIRC,
    CUR,
    ENC,
    EXP_ZERO,
    F_DT_TAU,
    F_EPS,
    F_LIM_ENC,
    F_LIM_H2D,
    F_LIM_HW,
    F_SCALE_CIRC,
    F_TAU_H2D,
    F_TAU_HW,
    F_TOL_H2D,
    F_TOL_HW,
    GAUSS,
    H2D,
    HW,
    I_NCIRC,
    I_RADIUS_RULE,
    INF,
    N_MODELS,
    PATH,
    PW_BLOCK,
    SURV,
    TIE,
    TRAJ,
    K,
    cache_dir,
    cache_problem,
)

log = logging.getLogger("risk")


CACHE_DIR = cache_dir()
numba.config.CACHE_DIR = CACHE_DIR  # type: ignore[attr-defined]  # read by the decorators
#: Why the cache folder cannot be written (None: it can); the compile notice says so.
CACHE_PROBLEM = cache_problem(CACHE_DIR)


def _answer_numba_blas_probe() -> bool:
    """Spare each process numba's BLAS probe: 0.3-0.6 s of importing ``scipy.linalg``.

    When the first kernel loads, numba's target set-up imports ``numba.np.arraymath``,
    which imports ``scipy.linalg.cython_blas`` only to learn whether ``np.dot`` and
    friends can be compiled. The kernels use no BLAS. This imports ``arraymath`` with the
    probe answered from the installed files instead (the same yes or no), then puts the
    real probe back, so that compiling code that does use BLAS still imports scipy's
    BLAS as numba expects. Does nothing (and returns False) when numba's layout differs.
    """
    if "numba.np.arraymath" in sys.modules:
        return False
    try:
        from numba.np import linalg as numba_linalg
    except ImportError:
        return False
    real_probe = getattr(numba_linalg, "ensure_blas", None)
    if real_probe is None:
        return False
    spec = importlib.util.find_spec("scipy")
    folders = list(spec.submodule_search_locations or []) if spec else []
    have_blas = any(any((pathlib.Path(f) / "linalg").glob("cython_blas.*")) for f in folders)

    def installed_probe() -> None:
        if not have_blas:
            raise ImportError("scipy 0.16+ is required for linear algebra")

    numba_linalg.ensure_blas = installed_probe
    try:
        from numba.np import arraymath
    finally:
        numba_linalg.ensure_blas = real_probe
    if getattr(arraymath, "ensure_blas", None) is installed_probe:
        arraymath.ensure_blas = real_probe
    return True


_answer_numba_blas_probe()


class _CompileNotice(event.Listener):
    """Logs once per process that the kernels are being compiled (a cache miss)."""

    said = False

    def on_start(self, ev: event.Event) -> None:
        if not _CompileNotice.said:
            _CompileNotice.said = True
            if CACHE_PROBLEM is None:
                log.warning(
                    "riskreplay: compiling the risk kernels once (about 20-25 s on two cores); "
                    "later runs load them from %s",
                    CACHE_DIR,
                )
            else:
                log.warning(
                    "riskreplay: compiling the risk kernels (about 20-25 s on two cores) in "
                    "every run: the cache folder %s cannot be written (%s); set "
                    "NUMBA_CACHE_DIR to a writable folder",
                    CACHE_DIR,
                    CACHE_PROBLEM,
                )

    def on_end(self, ev: event.Event) -> None:
        pass


event.register("numba:compile", _CompileNotice())

#: Every kernel function: cached; numpy's error model (a float division by zero gives
#: inf or NaN, as in the numpy oracle, instead of a Python ZeroDivisionError check
#: around every division).
_jit = numba.njit(cache=True, error_model="numpy")
#: The same for the inner functions, which only kernel code calls: without the Python and
#: C wrappers that numba otherwise generates and optimises for every function (0.05-0.15 s
#: of cold compile each, 3-4 s in all). Python compiles them with :func:`compile_like`.
#: (numba's own type hints leave out these two of its options.)
_inner = numba.njit(  # type: ignore[call-overload]
    cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True
)
# A bare literal passed to a kernel function (or a variable that starts as one) makes
# numba compile the callee once more, for Literal[int](0) or Literal[bool](False): seconds
# of cold compile. Where the callee is compiled for int64/bool anyway, such constants are
# written np.int64(0) / np.bool_(False). Two literal calls stay (_pw_leaf(a, 0, n) in
# np_sum, _interp(..., 0) in _cut): their speed against the plain form was within noise.


def compile_like(function: numba.core.registry.CPUDispatcher, *args: object) -> None:
    """Compile (or load from the cache) ``function`` for the types that a call with
    ``args`` would have, without calling it (an inner function cannot be called from
    Python: it has no Python wrapper)."""
    function.compile(tuple(numba.typeof(a) for a in args))


# ---------------------------------------------------------------------- summation
@_inner
def _pw_leaf(a: np.ndarray, s: int, n: int) -> float:
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[s + i]
        return res
    r0, r1, r2, r3 = a[s], a[s + 1], a[s + 2], a[s + 3]
    r4, r5, r6, r7 = a[s + 4], a[s + 5], a[s + 6], a[s + 7]
    i = 8
    stop = n - (n % 8)
    while i < stop:
        r0 += a[s + i]
        r1 += a[s + i + 1]
        r2 += a[s + i + 2]
        r3 += a[s + i + 3]
        r4 += a[s + i + 4]
        r5 += a[s + i + 5]
        r6 += a[s + i + 6]
        r7 += a[s + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[s + i]
        i += 1
    return res


@_inner
def np_sum(a: np.ndarray, n: int) -> float:
    """``a[:n].sum()`` exactly as numpy adds (pairwise), without recursion."""
    if n <= PW_BLOCK:
        return _pw_leaf(a, 0, n)
    fs = np.empty(64, np.int64)
    fn = np.empty(64, np.int64)
    stage = np.empty(64, np.int64)
    vals = np.empty(64)
    top, vtop = 0, 0
    fs[0], fn[0], stage[0] = 0, n, 0
    while top >= 0:
        s, m = fs[top], fn[top]
        if m <= PW_BLOCK:
            vals[vtop] = _pw_leaf(a, s, m)
            vtop += 1
            top -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        if stage[top] == 0:
            stage[top] = 1
            top += 1
            fs[top], fn[top], stage[top] = s, n2, 0
        elif stage[top] == 1:
            stage[top] = 2
            top += 1
            fs[top], fn[top], stage[top] = s + n2, m - n2, 0
        else:
            vtop -= 1
            vals[vtop - 1] = vals[vtop - 1] + vals[vtop]
            top -= 1
    return vals[0]


# ---------------------------------------------------------------------- paths
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


# ---------------------------------------------------------------------- prediction
@_inner
def _predict(
    ex, ey, ecum, eux, euy, v, steps, unc, kind, row, tx, ty, dxs, dys, slon, cxx, cxy, cyy
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
        x, y, seg, j = _interp(ex, ey, ecum, travelled, j)
        tx[row, k], ty[row, k] = x, y
        c, s = eux[seg], euy[seg]
        dxs[row, k], dys[row, k] = c, s
        lon = min(u0 + u2 * travelled + u6 * t, u4)
        lat = min(u1 + u3 * travelled + u7 * t, u5)
        slon[row, k] = lon
        a = lon * lon
        b = lat * lat
        cc = c * c
        ss = s * s
        cxx[row, k] = a * cc + b * ss
        cxy[row, k] = (a - b) * c * s
        cyy[row, k] = a * ss + b * cc


@_inner
def _escape_track(ns, dt_tau, sl, se):
    """``sl[k]``: the survival loop's ``log_s`` before step ``k`` when every earlier
    ``P_o + dt/tau`` rounds to ``dt/tau`` (always so far from the ego); ``se[k] =
    exp(-sl[k])``. The loop looks ``exp(-log_s)`` up here whenever ``log_s == sl[k]``
    (the same argument, so the same value) instead of computing it."""
    log_s = 0.0
    for k in range(ns):
        sl[k] = log_s
        se[k] = math.exp(-log_s)
        log_s += 0.0 + dt_tau


@_inner
def _pair_q(tx, ty, cxx, cxy, cyy, m, g_tx, g_ty, g_xx, g_xy, g_yy, e, ns, qs, dets):
    """The exponent ``q_k = -1/2 dmu^T S^-1 dmu`` and ``det S`` of the Gaussian overlap
    at every step of one prediction pair (the agent's row ``m``, the ego's row ``e``;
    ``S`` the summed covariance), as
    risk.stochastic._overlap computes them; returns the least ``det`` (NaN ignored).
    The loop has no reduction, so it compiles to SIMD code."""
    for k in range(ns):
        rx = tx[m, k] - g_tx[e, k]
        ry = ty[m, k] - g_ty[e, k]
        sxx = cxx[m, k] + g_xx[e, k]
        sxy = cxy[m, k] + g_xy[e, k]
        syy = cyy[m, k] + g_yy[e, k]
        det = sxx * syy - sxy * sxy
        q = syy * (rx * rx) - 2.0 * (sxy * (rx * ry))
        qs[k] = (q + sxx * (ry * ry)) / det * -0.5
        dets[k] = det
    m0, m1, m2, m3 = INF, INF, INF, INF  # four chains: the minimum is latency-bound
    k = 0
    while k + 4 <= ns:
        m0 = dets[k] if dets[k] < m0 else m0
        m1 = dets[k + 1] if dets[k + 1] < m1 else m1
        m2 = dets[k + 2] if dets[k + 2] < m2 else m2
        m3 = dets[k + 3] if dets[k + 3] < m3 else m3
        k += 4
    while k < ns:
        m0 = dets[k] if dets[k] < m0 else m0
        k += 1
    return min(min(m0, m1), min(m2, m3))


@_inner
def _overlap_risks(qs, dets, dmin, ns, dt_tau, terms, sl, se, lsk, defer, want_g, want_s):
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
       out count as 0; each is below ``1e-20`` of the sum, together below ``ns 1e-20``
       of it, under the sum's own rounding for any horizon below 10^4 steps.

    Without a positive finite ``min det`` every step is computed. Returns the Gaussian
    risk (meaningless when not requested) and leaves the survival terms in ``terms``:
    the survival risk is ``np_sum(terms, ns)``, summed by the caller (numba keeps an
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
    for k in range(ns):
        q = qs[k]
        if q < qa:
            defer[nd] = k
            nd += 1
            lsk[k] = log_s
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
                t = po * (se[k] if log_s == sl[k] else math.exp(-log_s))
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
            ls = lsk[kz]
            t = math.exp(q) / (math.sqrt(dets[kz]) * two_pi)
            gmax = max(gmax, t)
            t *= se[kz] if ls == sl[kz] else math.exp(-ls)
            terms[kz] = t
            tmax = max(tmax, t)
        sthr = math.log(tmax) + log2pil - 46.0 if tmax > 0 else -INF
    for d in range(nd):
        k = defer[d]
        q = qs[k]
        if q < EXP_ZERO or (want_s and k == kz):  # (kz: computed above)
            continue
        ls = lsk[k]
        need_s = want_s and q - ls >= sthr
        if not (need_s or q >= gthr):
            continue
        po = math.exp(q) / (math.sqrt(dets[k]) * two_pi)
        gmax = max(gmax, po)
        if need_s:
            terms[k] = po * (se[k] if ls == sl[k] else math.exp(-ls))
    return gmax


@_inner
def _time_gap(arc, l1, v1):
    """(l2 - l1) / v1 ahead of the ego, inf behind it, for NaN or a standing ego."""
    if v1 <= 0:
        return INF
    gap = arc - l1
    if gap >= 0:
        return gap / v1
    return INF


# ---------------------------------------------------------------------- the kernel
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
    xy, heading, speed, kinds, paths, path_points, ego, e0, ne, steps, unc, seg, nch
):
    """The ego's path candidates, shared by :func:`evaluate_agents` and
    :func:`cascade_agents`: each extended to ``v T``, cut at ``v T``, boxed by chunks and
    predicted with its covariances, with its segment data and the ego's arc position on
    it."""
    p = paths.shape[1]
    p1 = p + 1
    ns = steps.shape[0]
    horizon = steps[ns - 1]
    gx = np.empty((ne, p1))
    gy = np.empty((ne, p1))
    gcum = np.empty((ne, p1))
    gux = np.empty((ne, p1))
    guy = np.empty((ne, p1))
    gn = np.empty(ne, np.int64)
    gbox = np.empty((ne, nch, 4))
    gnb = np.empty(ne, np.int64)
    kx = np.empty((ne, p1))
    ky = np.empty((ne, p1))
    kn = np.empty(ne, np.int64)
    kbox = np.empty((ne, nch, 4))
    knb = np.empty(ne, np.int64)
    g_tx = np.empty((ne, ns))
    g_ty = np.empty((ne, ns))
    g_dx = np.empty((ne, ns))
    g_dy = np.empty((ne, ns))
    g_sl = np.empty((ne, ns))
    g_xx = np.empty((ne, ns))
    g_xy = np.empty((ne, ns))
    g_yy = np.empty((ne, ns))
    g_l1 = np.empty(ne)
    g_inv2 = np.empty((ne, p1))
    g_len = np.empty((ne, p1))
    v_e = speed[ego]
    for e in range(ne):
        r = e0 + e
        _segment_lengths(paths, r, seg)
        gn[e] = _extend(
            paths, r, path_points[r], heading[ego], v_e * horizon, seg, np_sum(seg, p - 1),
            gx, gy, gcum, gux, guy, e,
        )  # fmt: skip
        gnb[e] = _boxes(gx[e], gy[e], gn[e], gbox[e])
        kn[e] = _cut(gx[e], gy[e], gcum[e], v_e * horizon, kx[e], ky[e])
        knb[e] = _boxes(kx[e], ky[e], kn[e], kbox[e])
        _predict(
            gx[e], gy[e], gcum[e], gux[e], guy[e], v_e, steps, unc, kinds[ego], e,
            g_tx, g_ty, g_dx, g_dy, g_sl, g_xx, g_xy, g_yy,
        )  # fmt: skip
        _segments(gx[e], gy[e], gn[e], g_inv2[e], g_len[e])
        g_l1[e] = _project(
            xy[ego, 0], xy[ego, 1], gx, gy, gcum, gn[e], g_inv2, g_len, gbox, gnb[e], e
        )[1]
    return (
        gx, gy, gcum, gux, guy, gn, gbox, gnb, kx, ky, kn, kbox, knb,
        g_tx, g_ty, g_dx, g_dy, g_sl, g_xx, g_xy, g_yy, g_l1, g_inv2, g_len,
    )  # fmt: skip


@_jit
def evaluate_agents(
    xy, heading, speed, length, width, kinds, valid, paths, path_points, path_agent, ego,
    agents, steps, unc, want, fp, ip, stop2, cut2,
):  # fmt: skip
    """Risks ``(9, N)`` of the requested models (``want``) for ``agents`` (an empty array:
    every valid agent but the ego); NaN elsewhere.

    ``stop2`` / ``cut2`` (9,): squared distances for the keep/drop mode of the distance
    models (the cascade): stop at ``stop2``, prune beyond ``cut2``; ``-1`` / ``inf`` for
    exact values."""
    n = xy.shape[0]
    if agents.shape[0] == 0:
        agents = _others(valid, ego)
    p = paths.shape[1]
    p1 = p + 1
    ns = steps.shape[0]
    horizon = steps[ns - 1]
    nch = (p1 - 1 + K - 1) // K + 1
    out = np.full((N_MODELS, n), np.nan)
    starts = _row_starts(path_agent, n)
    want_path = want[PATH] or want[H2D]
    want_pred = want[ENC] or want[HW] or want[H2D] or want[CIRC] or want[GAUSS] or want[SURV]
    exact_path = want[H2D] or stop2[PATH] < 0
    traj_exact = stop2[TRAJ] < 0 and cut2[TRAJ] == INF
    # ------------------------------------------------ ego candidates
    e0, e1 = starts[ego], starts[ego + 1]
    ne = e1 - e0
    seg = np.empty(max(p - 1, 1))
    v_e = speed[ego]
    (
        gx, gy, gcum, _, _, gn, gbox, gnb, kx, ky, kn, kbox, knb,
        g_tx, g_ty, _, _, g_sl, g_xx, g_xy, g_yy, g_l1, g_inv2, g_len,
    ) = _ego_candidates(
        xy, heading, speed, kinds, paths, path_points, ego, e0, ne, steps, unc, seg, nch
    )  # fmt: skip
    # ------------------------------------------------ per-row scratch
    # one row each, for the functions that take rows (ex2 ... with row 0), and that row's
    # views for the others (made once per call: each view costs an atomic reference count)
    ex2, ey2, ecum2 = np.empty((1, p1)), np.empty((1, p1)), np.empty((1, p1))
    eux2, euy2 = np.empty((1, p1)), np.empty((1, p1))
    cx2, cy2 = np.empty((1, p1)), np.empty((1, p1))
    ebox3, cbox3 = np.empty((1, nch, 4)), np.empty((1, nch, 4))
    ex, ey, ecum, eux, euy = ex2[0], ey2[0], ecum2[0], eux2[0], euy2[0]
    cx, cy, ebox, cbox = cx2[0], cy2[0], ebox3[0], cbox3[0]
    gaps = np.empty(nch * nch)
    tx = np.empty((1, ns))  # (one row: the functions shared with cascade_agents index rows)
    row = np.int64(0)  # (that row; not a literal 0: see _jit)
    ty = np.empty((1, ns))
    dxs = np.empty((1, ns))
    dys = np.empty((1, ns))
    slon = np.empty((1, ns))
    cxx = np.empty((1, ns))
    cxy = np.empty((1, ns))
    cyy = np.empty((1, ns))
    terms = np.empty(ns)
    qs = np.empty(ns)
    dets = np.empty(ns)
    lsk = np.empty(ns)
    defer = np.empty(ns, np.int64)
    n_circ = ip[I_NCIRC]
    scale = fp[F_SCALE_CIRC]
    dt_tau = fp[F_DT_TAU]
    surv_l = np.empty(ns)
    surv_e = np.empty(ns)
    if want[SURV]:
        _escape_track(ns, dt_tau, surv_l, surv_e)
    lateral = np.empty(ne)
    arc_on = np.empty(ne)
    o2 = np.empty(max(n_circ, 1))
    oo = np.empty(max(n_circ, 1))
    best = np.empty(N_MODELS)
    cn, cnb = 0, 0
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        best[:] = -INF
        if want[CUR]:
            d = math.hypot(xy[i, 0] - xy[ego, 0], xy[i, 1] - xy[ego, 1])
            best[CUR] = fp[F_EPS + CUR] / (fp[F_EPS + CUR] + d)
        if want[HW] or want[H2D]:
            for e in range(ne):
                lateral[e], arc_on[e] = _project(
                    xy[i, 0], xy[i, 1], gx, gy, gcum, gn[e], g_inv2, g_len, gbox, gnb[e], e
                )
        v = speed[i]
        path_done = False
        traj_done = False
        if (want[PATH] and not exact_path) or (want[TRAJ] and stop2[TRAJ] >= 0):
            # Keep/drop mode: the paths' first points bound both distances from above, so
            # an agent whose path starts near an ego path start is kept in O(1).
            d0 = INF
            for r in range(starts[i], starts[i + 1]):
                for e in range(ne):
                    ddx = paths[r, 0, 0] - paths[e0 + e, 0, 0]
                    ddy = paths[r, 0, 1] - paths[e0 + e, 0, 1]
                    d0 = min(d0, ddx * ddx + ddy * ddy)
            for slot in (PATH, TRAJ):
                if want[slot] and d0 <= stop2[slot]:
                    eps = fp[F_EPS + slot]
                    best[slot] = eps / (eps + math.sqrt(d0))
                    if slot == PATH:
                        path_done = True
                    else:
                        traj_done = True
        for r in range(starts[i], starts[i + 1]):
            if not ((want_path and not path_done) or (want[TRAJ] and not traj_done) or want_pred):
                break
            _segment_lengths(paths, r, seg)
            en = _extend(
                paths, r, path_points[r], heading[i], v * horizon, seg, np_sum(seg, p - 1),
                ex2, ey2, ecum2, eux2, euy2, row,
            )  # fmt: skip
            nb = _boxes(ex, ey, en, ebox) if want_path else 0
            if want[TRAJ] and not traj_done:
                cn = _cut(ex, ey, ecum, v * horizon, cx, cy)
                if want_path:
                    cnb = _cut_boxes(cx, cy, cn, ecum, v * horizon, ebox, en, cbox)
                else:
                    cnb = _boxes(cx, cy, cn, cbox)
            if want_pred:
                _predict(
                    ex, ey, ecum, eux, euy, v, steps, unc, kinds[i], row,
                    tx, ty, dxs, dys, slon, cxx, cxy, cyy,
                )  # fmt: skip
            for e in range(ne):
                d_path = INF
                d_traj = INF
                if want[TRAJ] and not traj_done:
                    d_traj = _polyline_distance(
                        kx, ky, e, kn[e], kbox, knb[e], cx2, cy2, row, cn, cbox3, cnb, gaps,
                        stop2[TRAJ], cut2[TRAJ], INF,
                    )  # fmt: skip
                    eps = fp[F_EPS + TRAJ]
                    best[TRAJ] = max(best[TRAJ], eps / (eps + d_traj))
                    if stop2[TRAJ] >= 0 and d_traj * d_traj <= stop2[TRAJ]:
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
                        gx, gy, e, gn[e], gbox, gnb[e], ex2, ey2, row, en, ebox3, nb, gaps,
                        -1.0 if exact_path else stop2[PATH], INF if exact_path else cut2[PATH],
                        bound,
                    )  # fmt: skip
                    if want[PATH]:
                        eps = fp[F_EPS + PATH]
                        best[PATH] = max(best[PATH], eps / (eps + d_path))
                        if not exact_path and d_path * d_path <= stop2[PATH]:
                            path_done = True
                if not want_pred:
                    continue
                # closest encounter and circles in one loop; the Gaussian overlap and
                # survival from the exponents of a second one (exp where it matters)
                r_ego = 0.5 * (length[ego] if ip[I_RADIUS_RULE] == 0 else width[ego])
                d2min = INF
                circ = INF
                gmax, rsurv = -INF, 0.0
                # loop invariants in registers, the circles' offsets once per agent; the
                # ego's rows indexed in place (a row view costs an atomic reference count)
                w_circ, w_stoch, w_surv = want[CIRC], want[GAUSS] or want[SURV], want[SURV]
                half_w = 0.5 * width[i]
                if w_circ:
                    for c in range(n_circ):
                        o = length[i] * ((c + 0.5) / n_circ - 0.5)
                        o2[c] = 2.0 * o
                        oo[c] = o * o
                for k in range(ns):
                    rx = tx[0, k] - g_tx[e, k]
                    ry = ty[0, k] - g_ty[e, k]
                    d2 = rx * rx + ry * ry
                    d2min = min(d2min, d2)
                    if w_circ and circ > 0.0:  # (once <= 0, the risk is 1)
                        reach = (r_ego + scale * g_sl[e, k]) + (half_w + scale * slon[0, k])
                        along = rx * dxs[0, k] + ry * dys[0, k]
                        c2min = INF
                        for c in range(n_circ):
                            c2min = min(c2min, d2 + o2[c] * along + oo[c])
                        # sqrt is monotone: one root per step gives the same minimum; a
                        # step certainly no nearer than the best (a margin for rounding)
                        # skips it
                        lim = circ + reach
                        if lim > 0.0 and c2min <= lim * lim * (1.0 + 1e-9):
                            circ = min(circ, math.sqrt(max(c2min, 0.0)) - reach)
                if w_stoch:
                    dmin = _pair_q(
                        tx, ty, cxx, cxy, cyy, row, g_tx, g_ty, g_xx, g_xy, g_yy, e, ns, qs, dets
                    )
                    gmax = _overlap_risks(
                        qs, dets, dmin, ns, dt_tau, terms, surv_l, surv_e, lsk, defer,
                        want[GAUSS], w_surv,
                    )  # fmt: skip
                    if w_surv:
                        rsurv = np_sum(terms, ns)
                if want[ENC] or want[HW] or want[H2D]:
                    d_e = math.sqrt(d2min)
                    tie = (d_e + TIE) ** 2
                    k_e = 0
                    for k in range(ns):
                        rx = tx[0, k] - g_tx[e, k]
                        ry = ty[0, k] - g_ty[e, k]
                        if rx * rx + ry * ry <= tie:
                            k_e = k
                            break
                    for slot, lim in ((ENC, F_LIM_ENC), (HW, F_LIM_HW), (H2D, F_LIM_H2D)):
                        if want[slot]:
                            eps = fp[F_EPS + slot]
                            r_enc = eps / (eps + d_e) if steps[k_e] < fp[lim] else 0.0
                            best[slot] = max(best[slot], r_enc)
                if want[HW]:
                    th = INF
                    if lateral[e] <= fp[F_TOL_HW]:
                        th = _time_gap(arc_on[e], g_l1[e], v_e)
                    tau = fp[F_TAU_HW]
                    best[HW] = max(best[HW], tau / (tau + th))
                if want[H2D]:
                    th = INF
                    if lateral[e] <= fp[F_TOL_H2D]:
                        th = _time_gap(arc_on[e], g_l1[e], v_e)
                    elif d_path == 0.0:
                        s_b, s_a = _first_crossing(
                            ex, ey, ecum, en, ebox, nb, gx[e], gy[e], gcum[e], gn[e],
                            gbox[e], gnb[e],
                        )  # fmt: skip
                        th = _time_gap(s_a - s_b, g_l1[e], v_e)
                    tau = fp[F_TAU_H2D]
                    best[H2D] = max(best[H2D], tau / (tau + th))
                if want[CIRC]:
                    eps = fp[F_EPS + CIRC]
                    best[CIRC] = max(best[CIRC], eps / (eps + max(circ, 0.0)))
                if want[GAUSS]:
                    best[GAUSS] = max(best[GAUSS], gmax)
                if want[SURV]:
                    best[SURV] = max(best[SURV], rsurv)
        for slot in range(N_MODELS):
            if want[slot]:
                out[slot, i] = best[slot]
    return out


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
def _reach_keep(paths, starts, i, ego, speed, kinds, horizon, max_speed, limits):
    """The reachability bound for agent ``i`` (see :func:`reachable`), with the limits of
    :func:`_reach_limits`: O(1) per pair of path rows."""
    d2 = INF
    for r in range(starts[i], starts[i + 1]):
        for re in range(starts[ego], starts[ego + 1]):
            dx = paths[r, 0, 0] - paths[re, 0, 0]
            dy = paths[r, 0, 1] - paths[re, 0, 1]
            d2 = min(d2, dx * dx + dy * dy)
    w = max(speed[i], max_speed[kinds[i]]) + speed[ego]
    d = max(math.sqrt(d2) - w * horizon, 0.0)
    return d * d <= limits[kinds[i]]


@_jit
def reachable(
    paths, path_agent, speed, kinds, ego, agents, horizon, n_steps, unc, max_speed, threshold
):
    """The reachability bound of the cascade: False for agents of ``agents`` whose survival
    risk is certainly below ``threshold``; O(1) per path row.

    Positions along a path lie within ``v s`` of its first point, so the centre distance at
    any step is at least ``d = max(D0 - (w_i + v_ego) T, 0)``, ``D0`` the least distance of
    the candidates' first points and ``w_i = max(v_i, max_speed[kind])``. With ``S`` the
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
            paths, starts, agents[a_idx], ego, speed, kinds, horizon, max_speed, limits
        )
    return keep


# ---------------------------------------------------------------------- fused cascade


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
def _gauss_reaches(qs, dets, ns, thr, qcut):
    """Whether the Gaussian overlap of one prediction pair reaches ``thr`` at some step,
    from its ``q_k`` and ``det_k`` (:func:`_pair_q`; ``P_o`` as :func:`_overlap_risks`
    computes it). Steps with ``q < qcut`` are skipped without ``exp``: there
    ``P_o < thr`` certainly (see :func:`cascade_agents`)."""
    for k in range(ns):
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
    xy, heading, speed, length, width, kinds, valid, paths, path_points, path_agent, ego,
    agents, steps, unc, fp, ip, st_slot, st_thr, st_stop2, st_cut2, use_reach, max_speed,
    base_thr, surv_all, tier_min, tier_cap,
):  # fmt: skip
    """The fused cascade: one pass per agent of ``agents`` through the reachability bound
    (when ``use_reach``) and the stages (model slot ``st_slot[s]``, one of PATH, TRAJ,
    GAUSS; kept when its risk reaches ``st_thr[s]``), then survival analysis for the
    survivors and their tiers (:func:`tiers`, with ``tier_min``, ``tier_cap``). Each
    agent's path is extended once and predicted once, whatever the stages.

    Distance stages are keep/drop tests (``st_stop2``, ``st_cut2``: see
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
    baseline (N,) bool (``surv_all >= base_thr``, the survival risk of every agent, for
    agents of ``agents`` only) and the false negatives (S,) int64 (baseline agents not
    kept after stage ``s``)."""
    n = xy.shape[0]
    n_st = st_slot.shape[0]
    if agents.shape[0] == 0:
        agents = _others(valid, ego)
    code = np.full(n, -2, np.int64)
    surv_out = np.full(n, np.nan)
    cyc = np.zeros(n_st + 3, np.int64)
    t_prev = _cycles()
    p = paths.shape[1]
    p1 = p + 1
    ns = steps.shape[0]
    horizon = steps[ns - 1]
    nch = (p1 - 1 + K - 1) // K + 1
    starts = _row_starts(path_agent, n)
    rmax = 1
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        rmax = max(rmax, starts[i + 1] - starts[i])
    # ------------------------------------------------ ego candidates
    e0, e1 = starts[ego], starts[ego + 1]
    ne = e1 - e0
    seg = np.empty(max(p - 1, 1))
    u_e = unc[kinds[ego]]
    (
        gx, gy, _, _, _, gn, gbox, gnb, kx, ky, kn, kbox, knb,
        g_tx, g_ty, _, _, _, g_xx, g_xy, g_yy, _, _, _,
    ) = _ego_candidates(
        xy, heading, speed, kinds, paths, path_points, ego, e0, ne, steps, unc, seg, nch
    )  # fmt: skip
    s0_e = min(min(u_e[0], u_e[4]), min(u_e[1], u_e[5]))
    # ------------------------------------------------ per-agent scratch (rmax rows)
    ex = np.empty((rmax, p1))
    ey = np.empty((rmax, p1))
    ecum = np.empty((rmax, p1))
    eux = np.empty((rmax, p1))
    euy = np.empty((rmax, p1))
    en = np.empty(rmax, np.int64)
    ebox = np.empty((rmax, nch, 4))
    nb = np.empty(rmax, np.int64)
    cx2, cy2, cbox3 = np.empty((1, p1)), np.empty((1, p1)), np.empty((1, nch, 4))
    cx, cy, cbox = cx2[0], cy2[0], cbox3[0]  # (row 0, also viewed once)
    row = np.int64(0)  # (their row)
    gaps = np.empty(nch * nch)
    tx = np.empty((rmax, ns))
    ty = np.empty((rmax, ns))
    dxs = np.empty((rmax, ns))
    dys = np.empty((rmax, ns))
    slon = np.empty((rmax, ns))
    cxx = np.empty((rmax, ns))
    cxy = np.empty((rmax, ns))
    cyy = np.empty((rmax, ns))
    terms = np.empty(ns)
    qs = np.empty(ns)
    dets = np.empty(ns)
    lsk = np.empty(ns)
    defer = np.empty(ns, np.int64)
    extended = np.zeros(rmax, np.bool_)
    predicted = np.zeros(rmax, np.bool_)
    surv_l = np.empty(ns)
    surv_e = np.empty(ns)
    _escape_track(ns, fp[F_DT_TAU], surv_l, surv_e)
    limits = _reach_limits(unc, kinds, ego, ns, base_thr)
    t = _cycles()
    cyc[0] += t - t_prev
    t_prev = t
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        if use_reach and base_thr > 0:
            ok = _reach_keep(paths, starts, i, ego, speed, kinds, horizon, max_speed, limits)
            t = _cycles()
            cyc[1] += t - t_prev
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
        q_pair = -1  # the pair (m ne + e) whose q and det qs, dets hold; -1: none
        q_dmin = INF
        code[i] = n_st
        for s in range(n_st):
            slot = st_slot[s]
            thr = st_thr[s]
            keep = False
            if slot in (PATH, TRAJ):
                stop2 = st_stop2[s]
                cut2 = st_cut2[s]
                eps = fp[F_EPS + slot]
                if stop2 >= 0:  # O(1): the paths' first points bound the distance
                    d0 = INF
                    for r in range(r0, r1):
                        for e in range(ne):
                            ddx = paths[r, 0, 0] - paths[e0 + e, 0, 0]
                            ddy = paths[r, 0, 1] - paths[e0 + e, 0, 1]
                            d0 = min(d0, ddx * ddx + ddy * ddy)
                    keep = d0 <= stop2 and eps / (eps + math.sqrt(d0)) >= thr
                for r in range(r0, r1):
                    if keep:
                        break
                    m = r - r0
                    if not extended[m]:
                        _segment_lengths(paths, r, seg)
                        en[m] = _extend(
                            paths, r, path_points[r], heading[i], v * horizon, seg,
                            np_sum(seg, p - 1), ex, ey, ecum, eux, euy, m,
                        )  # fmt: skip
                        nb[m] = _boxes(ex[m], ey[m], en[m], ebox[m])
                        extended[m] = True
                    if slot == TRAJ:
                        cn = _cut(ex[m], ey[m], ecum[m], v * horizon, cx, cy)
                        cnb = _cut_boxes(cx, cy, cn, ecum[m], v * horizon, ebox[m], en[m], cbox)
                    for e in range(ne):
                        if slot == PATH:
                            d = _polyline_distance(
                                gx, gy, e, gn[e], gbox, gnb[e], ex, ey, m, en[m], ebox, nb[m],
                                gaps, stop2, cut2, INF,
                            )  # fmt: skip
                        else:
                            d = _polyline_distance(
                                kx, ky, e, kn[e], kbox, knb[e], cx2, cy2, row, cn, cbox3, cnb,
                                gaps, stop2, cut2, INF,
                            )  # fmt: skip
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
                        en[m] = _extend(
                            paths, r, path_points[r], heading[i], v * horizon, seg,
                            np_sum(seg, p - 1), ex, ey, ecum, eux, euy, m,
                        )  # fmt: skip
                        nb[m] = _boxes(ex[m], ey[m], en[m], ebox[m])
                        extended[m] = True
                    if not predicted[m]:
                        _predict(
                            ex[m], ey[m], ecum[m], eux[m], euy[m], v, steps, unc, kinds[i], m,
                            tx, ty, dxs, dys, slon, cxx, cxy, cyy,
                        )  # fmt: skip
                        predicted[m] = True
                    for e in range(ne):
                        # q and det at every step, kept for survival when this pair is
                        # the first it computes (then the two models share this loop)
                        q_dmin = _pair_q(
                            tx, ty, cxx, cxy, cyy, m, g_tx, g_ty, g_xx, g_xy, g_yy, e, ns, qs,
                            dets,
                        )  # fmt: skip
                        q_pair = m * ne + e
                        if _gauss_reaches(qs, dets, ns, thr, qcut):
                            keep = True
                            break
            t = _cycles()
            cyc[2 + s] += t - t_prev
            t_prev = t
            if not keep:
                code[i] = s
                break
        if code[i] != n_st:
            continue
        best = -INF
        for r in range(r0, r1):
            m = r - r0
            if not extended[m]:
                _segment_lengths(paths, r, seg)
                en[m] = _extend(
                    paths, r, path_points[r], heading[i], v * horizon, seg,
                    np_sum(seg, p - 1), ex, ey, ecum, eux, euy, m,
                )  # fmt: skip
                extended[m] = True
            if not predicted[m]:
                _predict(
                    ex[m], ey[m], ecum[m], eux[m], euy[m], v, steps, unc, kinds[i], m,
                    tx, ty, dxs, dys, slon, cxx, cxy, cyy,
                )  # fmt: skip
                predicted[m] = True
            for e in range(ne):
                if m * ne + e == q_pair:  # q and det of this pair are still in qs, dets
                    dmin = q_dmin
                else:
                    dmin = _pair_q(
                        tx, ty, cxx, cxy, cyy, m, g_tx, g_ty, g_xx, g_xy, g_yy, e, ns, qs,
                        dets,
                    )  # fmt: skip
                    q_pair = m * ne + e
                _overlap_risks(
                    qs, dets, dmin, ns, fp[F_DT_TAU], terms, surv_l, surv_e, lsk, defer,
                    np.bool_(False), np.bool_(True),
                )  # fmt: skip
                rsurv = np_sum(terms, ns)
                best = max(best, rsurv)
        surv_out[i] = best
        t = _cycles()
        cyc[n_st + 2] += t - t_prev
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
    cyc[n_st + 2] += _cycles() - t_prev
    baseline = np.zeros(n, np.bool_)
    false_neg = np.zeros(n_st, np.int64)
    for a_idx in range(agents.shape[0]):
        i = agents[a_idx]
        if surv_all[i] >= base_thr:  # (False for NaN)
            baseline[i] = True
            for s in range(n_st):
                if not kept[s, i]:
                    false_neg[s] += 1
    return kept, dropped_at, unreachable, survivors, surv_out, cyc, tier, baseline, false_neg
