"""Oriented boxes (agents' recorded footprints) and forward windows over time: the
geometry of the hindsight truth (:mod:`risk.hindsight`), also used by the closed loop.

Pure numpy: exact rectangle-to-rectangle distance (:func:`box_gap`), overlap by the
separating axis test (:func:`boxes_overlap`), and sliding minima and sums over the next
``length`` steps.
"""

from __future__ import annotations

import numpy as np

from risk.errors import RiskError

#: Boxes closer than this (m) touch: absorbs rounding in the separating-axis test.
TOUCH_M = 1e-9


# ---------------------------------------------------------------------- box geometry
def box_corners(
    x: np.ndarray, y: np.ndarray, heading: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """Corners ``(..., 4, 2)`` of oriented boxes (counter-clockwise), broadcasting."""
    c, s = np.cos(heading), np.sin(heading)
    hl, hw = np.asarray(length) / 2.0, np.asarray(width) / 2.0
    sl = np.array([1.0, -1.0, -1.0, 1.0])
    sw = np.array([1.0, 1.0, -1.0, -1.0])
    ex = (hl * c)[..., None] * sl - (hw * s)[..., None] * sw
    ey = (hl * s)[..., None] * sl + (hw * c)[..., None] * sw
    return np.stack([np.asarray(x)[..., None] + ex, np.asarray(y)[..., None] + ey], axis=-1)


def boxes_overlap(
    xa: np.ndarray,
    ya: np.ndarray,
    ha: np.ndarray,
    la: np.ndarray,
    wa: np.ndarray,
    xb: np.ndarray,
    yb: np.ndarray,
    hb: np.ndarray,
    lb: np.ndarray,
    wb: np.ndarray,
) -> np.ndarray:
    """Whether two oriented boxes touch or overlap (separating-axis test), broadcasting.
    Boxes within :data:`TOUCH_M` of each other touch.

    Box = centre ``(x, y)``, heading (rad), length along the heading, width across it.
    """
    dx, dy = np.subtract(xb, xa), np.subtract(yb, ya)
    ca, sa, cb, sb = np.cos(ha), np.sin(ha), np.cos(hb), np.sin(hb)
    hla, hwa = np.asarray(la) / 2.0, np.asarray(wa) / 2.0
    hlb, hwb = np.asarray(lb) / 2.0, np.asarray(wb) / 2.0
    # |u_a . u_b| and the other three products between the boxes' unit axes.
    uu = np.abs(ca * cb + sa * sb)  # u_a . u_b  (= v_a . v_b)
    uv = np.abs(-ca * sb + sa * cb)  # u_a . v_b  (= v_a . u_b up to sign)
    overlap = np.abs(dx * ca + dy * sa) <= hla + hlb * uu + hwb * uv + TOUCH_M  # axis u_a
    overlap &= np.abs(-dx * sa + dy * ca) <= hwa + hlb * uv + hwb * uu + TOUCH_M  # axis v_a
    overlap &= np.abs(dx * cb + dy * sb) <= hlb + hla * uu + hwa * uv + TOUCH_M  # axis u_b
    overlap &= np.abs(-dx * sb + dy * cb) <= hwb + hla * uv + hwa * uu + TOUCH_M  # axis v_b
    return overlap


def _corners_to_box(
    x: np.ndarray,
    y: np.ndarray,
    h: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    xb: np.ndarray,
    yb: np.ndarray,
    hb: np.ndarray,
    lb: np.ndarray,
    wb: np.ndarray,
) -> np.ndarray:
    """Least distance from the 4 corners of box A to box B (as a filled rectangle):
    each corner in B's frame, then the distance to an axis-aligned rectangle."""
    corners = box_corners(x, y, h, length, width)  # (..., 4, 2)
    dx = corners[..., 0] - xb[..., None]
    dy = corners[..., 1] - yb[..., None]
    c, s = np.cos(hb)[..., None], np.sin(hb)[..., None]
    u = np.abs(dx * c + dy * s) - lb[..., None] / 2.0
    v = np.abs(-dx * s + dy * c) - wb[..., None] / 2.0
    d2 = np.maximum(u, 0.0) ** 2 + np.maximum(v, 0.0) ** 2
    return np.sqrt(d2.min(axis=-1))


def box_gap(
    xa: np.ndarray,
    ya: np.ndarray,
    ha: np.ndarray,
    la: np.ndarray,
    wa: np.ndarray,
    xb: np.ndarray,
    yb: np.ndarray,
    hb: np.ndarray,
    lb: np.ndarray,
    wb: np.ndarray,
) -> np.ndarray:
    """Exact clearance (m) between two oriented boxes, 0 when they touch or overlap.

    Arguments broadcast. Two disjoint convex polygons are nearest between a corner of one
    and an edge of the other, so the gap is the least distance from a corner of either box
    to the other box (8 point-to-rectangle distances, each in the rectangle's own frame).
    """
    shape = np.broadcast_shapes(*(np.shape(a) for a in (xa, ya, ha, la, wa, xb, yb, hb, lb, wb)))
    args = [np.broadcast_to(np.asarray(a, dtype=np.float64), shape) for a in (xa, ya, ha, la, wa)]
    brgs = [np.broadcast_to(np.asarray(a, dtype=np.float64), shape) for a in (xb, yb, hb, lb, wb)]
    overlap = boxes_overlap(*args, *brgs)
    out = np.zeros(shape)
    apart = ~overlap
    if apart.any():
        a_ = [a[apart] for a in args]
        b_ = [b[apart] for b in brgs]
        out[apart] = np.minimum(_corners_to_box(*a_, *b_), _corners_to_box(*b_, *a_))
    return out


# ---------------------------------------------------------------------- windows
def forward_window_min(a: np.ndarray, length: int) -> np.ndarray:
    """``out[f] = min(a[f : f + length])`` along axis 0 (the window is cut at the end).

    Sparse-table doubling: O(T log length) vectorised passes over the other axes.
    """
    if length < 1:
        raise RiskError(f"window length must be >= 1, got {length}")
    a = np.asarray(a, dtype=np.float64)
    t = a.shape[0]
    # A window longer than the array ends at its end either way: the same minimum, and
    # no padding sized by a huge horizon (--truth-horizon 1e9 asked for 7 TiB).
    length = min(length, max(t, 1))
    pad = np.full((length, *a.shape[1:]), np.inf)
    m = np.concatenate([a, pad])  # m[f] = min(a[f : f + w]) for the current w
    w = 1
    while 2 * w <= length:
        m = np.minimum(m, np.concatenate([m[w:], pad[:w]]))
        w *= 2
    rest = length - w  # 0 <= rest < w: cover [f, f + length) with two windows of w
    if rest:
        m = np.minimum(m, np.concatenate([m[rest:], pad[:rest]]))
    return m[:t]


def forward_window_sum(a: np.ndarray, length: int) -> np.ndarray:
    """``out[f] = sum(a[f : f + length])`` along axis 0 (cut at the end), exact for ints."""
    a = np.asarray(a)
    c = np.concatenate([np.zeros((1, *a.shape[1:]), dtype=np.int64), np.cumsum(a, axis=0)])
    t = a.shape[0]
    end = np.minimum(np.arange(t) + length, t)
    return c[end] - c[:t]
