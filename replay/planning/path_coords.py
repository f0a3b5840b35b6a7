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
    ``arc_m``; a finite difference of the forecast)."""

    arc_m: np.ndarray
    lateral_m: np.ndarray
    half_along_m: np.ndarray
    half_across_m: np.ndarray
    along: np.ndarray
    speed_along_mps: np.ndarray

    def rows(self, which: np.ndarray) -> PathCoords:
        """The agents selected by a mask or index array ``(K,)``."""
        return PathCoords(
            arc_m=self.arc_m[which],
            lateral_m=self.lateral_m[which],
            half_along_m=self.half_along_m[which],
            half_across_m=self.half_across_m[which],
            along=self.along[which],
            speed_along_mps=self.speed_along_mps[which],
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
    if t >= 2:
        dt = np.diff(agents.times_s)
        rate = np.diff(arc, axis=1) / dt[None, :]
        speed = np.concatenate([rate, rate[:, -1:]], axis=1)
    else:
        speed = np.zeros((k, t))
    return PathCoords(
        arc_m=arc,
        lateral_m=dist,
        half_along_m=c * half_l + s * half_w,
        half_across_m=s * half_l + c * half_w,
        along=np.cos(rel) >= math.cos(ALONG_ANGLE_RAD),
        speed_along_mps=speed,
    )
