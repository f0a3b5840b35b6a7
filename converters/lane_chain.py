"""Successor links for maps whose lanes carry none (nuScenes through ScenarioNet).

nuScenes lane centre lines come without ``exit_lanes``, but consecutive lanes share their
joint. Measured on the eight nuScenes scenes of the format's test data: 88-91 % of lane
ends have another lane starting within 1 m, over 99 % of those exactly at the end point
(the largest gap: 0.50 m), the heading across such joints changes by at most 0.16 rad
(9 degrees), and every other end is 1.27 m or more from the nearest lane start (the edge
of the cropped map, a pocket, or the opposite lane heading back). So lane *j* succeeds
lane *i* when *j*'s first point lies within ``max_gap_m`` of *i*'s last point and the
direction of *j*'s first segment is within ``max_heading_rad`` of *i*'s last segment. The links then feed the ordinary lane graph
(:class:`converters.lanegraph.LaneGraph`): matching, forks as candidates, straight
extension where a route ends.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from converters.lanegraph import dedupe, wrap_angle

MAX_GAP_M = 1.0
"""How far a lane's start may lie from its predecessor's end (m)."""
MAX_HEADING_RAD = math.pi / 6
"""How much the direction may turn across a joint (30 degrees)."""

_CHUNK = 2048  # lanes per block of the pairwise test (bounds memory on large maps)


def chain_successors(
    centerlines: Sequence[np.ndarray],
    *,
    max_gap_m: float = MAX_GAP_M,
    max_heading_rad: float = MAX_HEADING_RAD,
) -> list[tuple[int, ...]]:
    """Successor lane indices of each centre line ``(P, 2)``, from geometry alone.

    Lanes with fewer than two distinct points have no direction: they get no successors
    and succeed none. A lane never succeeds itself. Vectorised over lane pairs (in
    blocks of :data:`_CHUNK` predecessors).
    """
    n = len(centerlines)
    start = np.zeros((n, 2))
    end = np.zeros((n, 2))
    h_start = np.zeros(n)
    h_end = np.zeros(n)
    ok = np.zeros(n, dtype=bool)
    for i, line in enumerate(centerlines):  # once per lane: first and last segment
        pts = dedupe(np.asarray(line, dtype=np.float64).reshape(-1, 2))
        if len(pts) < 2:
            continue
        ok[i] = True
        start[i], end[i] = pts[0], pts[-1]
        d0, d1 = pts[1] - pts[0], pts[-1] - pts[-2]
        h_start[i], h_end[i] = math.atan2(d0[1], d0[0]), math.atan2(d1[1], d1[0])
    successors: list[tuple[int, ...]] = [() for _ in range(n)]
    for lo in range(0, n, _CHUNK):
        hi = min(n, lo + _CHUNK)
        gap = np.hypot(
            end[lo:hi, None, 0] - start[None, :, 0], end[lo:hi, None, 1] - start[None, :, 1]
        )
        turn = np.abs(wrap_angle(h_start[None, :] - h_end[lo:hi, None]))
        link = (gap <= max_gap_m) & (turn <= max_heading_rad) & ok[lo:hi, None] & ok[None, :]
        link[np.arange(hi - lo), np.arange(lo, hi)] = False
        rows, cols = np.nonzero(link)
        for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
            successors[lo + r] += (c,)
    return successors
