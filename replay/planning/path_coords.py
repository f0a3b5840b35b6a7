"""The agents' forecasts in the coordinates of the ego's reference path (vectorised).

For every agent and forecast time: the arc length of its centre's nearest point on the
reference, the lateral distance to it, the box's half extents along and across the path,
and whether it moves along the path. Both planners use these: IDM to find leaders and
conflict points, and ``may_matter`` to prove that an agent stays out of a planner's reach.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from replay.planning.types import AgentForecasts
from risk import geometry

#: An agent whose heading is within this angle of the path's direction moves along it
#: (a leader); others cross or come towards the ego (conflicts).
ALONG_ANGLE_RAD = math.radians(45.0)


@dataclass(frozen=True, eq=False)
class PathCoords:
    """Shapes ``(K, T)``: ``arc_m`` (along the reference, m), ``lateral_m`` (unsigned
    distance of the centre from the reference, m), ``half_along_m`` / ``half_across_m``
    (the rotated box's half extents along / across the path, m), ``along`` (bool: heading
    within ALONG_ANGLE_RAD of the path direction), ``speed_along_mps`` (rate of change of
    ``arc_m``; a finite difference of the forecast), ``offset_m`` (signed lateral offset,
    + to the left of the path's direction, m) and ``on_path`` (bool: the centre projects
    inside the reference, not beyond either end; beyond an end ``arc_m`` is clamped to
    it and says nothing about where the agent is along the path)."""

    arc_m: np.ndarray
    lateral_m: np.ndarray
    half_along_m: np.ndarray
    half_across_m: np.ndarray
    along: np.ndarray
    speed_along_mps: np.ndarray
    offset_m: np.ndarray
    on_path: np.ndarray

    def rows(self, which: np.ndarray) -> PathCoords:
        """The agents selected by a mask or index array ``(K,)``."""
        return PathCoords(
            arc_m=self.arc_m[which],
            lateral_m=self.lateral_m[which],
            half_along_m=self.half_along_m[which],
            half_across_m=self.half_across_m[which],
            along=self.along[which],
            speed_along_mps=self.speed_along_mps[which],
            offset_m=self.offset_m[which],
            on_path=self.on_path[which],
        )


def reference_arcs(reference: np.ndarray) -> np.ndarray:
    """Arc length ``(P,)`` in m at the reference's points."""
    return geometry.cumulative_lengths(reference[None])[0]


def project(reference: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance ``(n,)`` and arc length ``(n,)`` of ``points`` ``(n, 2)`` on the reference."""
    return geometry.project_points(points, reference, reference_arcs(reference))


def path_coords(reference: np.ndarray, agents: AgentForecasts) -> PathCoords:
    """Every agent at every forecast time in the reference's coordinates."""
    k, t = agents.n, agents.times_s.size
    cum = reference_arcs(reference)
    dist, arc = geometry.project_points(agents.xy.reshape(-1, 2), reference, cum)
    dist, arc = dist.reshape(k, t), arc.reshape(k, t)
    d = np.diff(reference, axis=0)
    seg_heading = np.arctan2(d[:, 1], d[:, 0])
    seg = np.clip(np.searchsorted(cum, arc, side="right") - 1, 0, len(d) - 1)
    rel = agents.heading_rad - seg_heading[seg]
    c, s = np.abs(np.cos(rel)), np.abs(np.sin(rel))
    half_l, half_w = agents.length_m[:, None] / 2.0, agents.width_m[:, None] / 2.0
    offset, on_path = _side_and_span(reference, cum, agents.xy, arc, seg, seg_heading)
    if t >= 2:
        # Forward differences, backward at the last step and where the next step is beyond
        # the reference's end (its clamped arc would make the agent seem to stop there).
        dt = np.diff(agents.times_s)
        rate = np.diff(arc, axis=1) / dt[None, :]
        fine = on_path[:, :-1] & on_path[:, 1:]
        forward = np.concatenate([rate, rate[:, -1:]], axis=1)
        backward = np.concatenate([rate[:, :1], rate], axis=1)
        ok_fwd = np.concatenate([fine, np.zeros((k, 1), dtype=bool)], axis=1)
        ok_bwd = np.concatenate([np.zeros((k, 1), dtype=bool), fine], axis=1)
        # Neither: the forecast's velocity along the path's direction there.
        step = np.diff(agents.xy, axis=1) / dt[None, :, None]  # (K, T-1, 2)
        vel = np.concatenate([step, step[:, -1:]], axis=1)
        heading = seg_heading[seg]
        tangential = vel[..., 0] * np.cos(heading) + vel[..., 1] * np.sin(heading)
        speed = np.where(ok_fwd, forward, np.where(ok_bwd, backward, tangential))
    else:
        speed = np.zeros((k, t))
    return PathCoords(
        arc_m=arc,
        lateral_m=dist,
        half_along_m=c * half_l + s * half_w,
        half_across_m=s * half_l + c * half_w,
        along=np.cos(rel) >= math.cos(ALONG_ANGLE_RAD),
        speed_along_mps=speed,
        offset_m=np.where(offset < 0.0, -dist, dist),
        on_path=on_path,
    )


def _side_and_span(
    reference: np.ndarray,
    cum: np.ndarray,
    xy: np.ndarray,
    arc: np.ndarray,
    seg: np.ndarray,
    seg_heading: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(K, T)`` each: the points' offset from their foot on the reference across the
    foot's segment (its sign says left / right) and whether the foot lies inside the
    reference (a point beyond either end projects onto the end point)."""
    foot_x = np.interp(arc, cum, reference[:, 0])
    foot_y = np.interp(arc, cum, reference[:, 1])
    ux, uy = np.cos(seg_heading[seg]), np.sin(seg_heading[seg])
    rx, ry = xy[..., 0] - foot_x, xy[..., 1] - foot_y
    across = ux * ry - uy * rx
    ahead = ux * rx + uy * ry  # along the segment from the foot: non-zero only at an end
    eps = 1e-6
    beyond = ((arc <= cum[0] + eps) & (ahead < -eps)) | ((arc >= cum[-1] - eps) & (ahead > eps))
    return across, ~beyond


class CoordsCache:
    """:func:`path_coords` of the last reference, reused for any subset of its agents.

    A filter's plan, and every "all agents but one" plan of the planner truth, asks about
    a subset of the agents of the all-agents request, along the same reference: their
    coordinates are rows of the ones already computed. A hit needs the same reference
    object, the same times, and every agent's id and forecast equal to the cached ones
    (compared, so that a changed forecast under an old id is never served stale).
    """

    def __init__(self) -> None:
        self._key: tuple[np.ndarray, np.ndarray] | None = None
        self._ids = np.zeros(0, dtype=np.int64)
        self._order = np.zeros(0, dtype=np.int64)
        self._xy = np.zeros((0, 0, 2))
        self._heading = np.zeros((0, 0))
        self._size = np.zeros((0, 2))
        self._coords: PathCoords | None = None

    def get(self, reference: np.ndarray, agents: AgentForecasts) -> PathCoords:
        if (
            self._coords is not None
            and self._key is not None
            and self._key[0] is reference
            and np.array_equal(self._key[1], agents.times_s)
            and agents.n <= self._ids.size
        ):
            sorted_ids = self._ids[self._order]
            pos = np.clip(np.searchsorted(sorted_ids, agents.ids), 0, max(sorted_ids.size - 1, 0))
            rows = self._order[pos]
            same = (
                np.array_equal(self._ids[rows], agents.ids)
                and np.array_equal(self._xy[rows], agents.xy)
                and np.array_equal(self._heading[rows], agents.heading_rad)
                and np.array_equal(self._size[rows], np.stack([agents.length_m, agents.width_m], 1))
            )
            if same:
                return self._coords.rows(rows)
        coords = path_coords(reference, agents)
        self._key = (reference, agents.times_s.copy())
        self._ids = agents.ids.copy()
        self._order = np.argsort(self._ids, kind="stable")
        self._xy = agents.xy.copy()
        self._heading = agents.heading_rad.copy()
        self._size = np.stack([agents.length_m, agents.width_m], 1)
        self._coords = coords
        return coords
