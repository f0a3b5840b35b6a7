"""A four-way intersection: lanes, routes through it, and poses along the routes.

Geometry (right-hand traffic, metres, the intersection centre at the origin). Two roads
cross at right angles: one along x, one along y. Each of the four **arms** (east,
north, west, south) carries ``L`` incoming lanes (towards the centre) and ``L`` outgoing
lanes (away from it), ``lane_width_m`` apart, lane ``0`` next to the road's centre line
(the inner lane) and lane ``L-1`` at the kerb (the outer lane). The **box** (the area
where the roads overlap, plus a corner radius) is the square ``|x|, |y| <= h`` with
``h = L * lane_width_m + corner_radius_m``; arms run ``arm_length_m`` beyond it.

Connectors join an incoming lane's end (on the box edge) to an outgoing lane's start:

- **straight** from every incoming lane ``i`` to outgoing lane ``i`` of the opposite arm;
- **left** from the inner incoming lane to the inner outgoing lane of the arm to the
  left: a quarter circle about the far box corner, radius ``h + w/2``;
- **right** from the outer incoming lane to the outer outgoing lane of the arm to the
  right: a quarter circle about the near box corner, radius ``corner_radius_m + w/2``.

Both turns are exact circular arcs tangent to the lanes they join (continuous heading),
sampled every ``arc_step_deg`` degrees. With one lane per direction that lane does all
three. A **route** is incoming lane + connector + outgoing lane; the lanes and their
successor links form the scene's :class:`~risk.frame.LaneMap`.

Agents are placed on routes by arc length ``s`` (m from the route start); the helpers
here turn ``(route, s)`` for many agents at once into positions, headings, lanes and
forward paths, without Python loops over agents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from converters.errors import ConversionError
from risk.frame import Lane, LaneMap

# Arms by outward unit direction, counter-clockwise from east.
ARM_NAMES = ("east", "north", "west", "south")
_ARM_DIRS = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
TURNS = ("straight", "left", "right")


@dataclass(frozen=True)
class IntersectionSettings:
    """Layout of the four-way intersection (all lengths in metres)."""

    lanes_per_direction: int = 2
    lane_width_m: float = 3.5
    arm_length_m: float = 150.0  # from the box edge to the arm's end
    corner_radius_m: float = 6.0  # kerb corner radius: the box is this much wider than the roads
    arc_step_deg: float = 3.0  # angular sampling of the turning arcs

    def __post_init__(self) -> None:
        if not (isinstance(self.lanes_per_direction, int) and 1 <= self.lanes_per_direction <= 6):
            raise ConversionError(
                f"lanes per direction must be 1..6, got {self.lanes_per_direction}"
            )
        for name in ("lane_width_m", "arm_length_m", "arc_step_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConversionError(f"{name} must be a positive number, got {value}")
        if not (math.isfinite(self.corner_radius_m) and self.corner_radius_m >= 0):
            raise ConversionError(f"corner_radius_m must be >= 0, got {self.corner_radius_m}")
        if self.arc_step_deg > 30:
            raise ConversionError(
                f"arc_step_deg must be <= 30 for smooth arcs, got {self.arc_step_deg}"
            )

    @property
    def box_half_m(self) -> float:
        """Half the side of the intersection box, m."""
        return self.lanes_per_direction * self.lane_width_m + self.corner_radius_m


@dataclass(frozen=True, eq=False)
class Routes:
    """Every route through the intersection as padded arrays (``R`` routes, ``V`` vertices).

    A route is exactly three lanes: incoming, connector, outgoing.
    """

    vertices: np.ndarray  # (R, V, 2) m, padded by repeating the last vertex
    n_vertices: np.ndarray  # (R,) real vertices
    arc: np.ndarray  # (R, V) m, arc length at each vertex (padding repeats the total)
    length_m: np.ndarray  # (R,) total length
    lanes: np.ndarray  # (R, 3) lane indices (into Intersection.lanes)
    lane_start_m: np.ndarray  # (R, 3) arc length where each of the route's lanes starts
    turn: np.ndarray  # (R,) index into TURNS
    lane_offset_m: np.ndarray  # (R, n_lanes) where a lane starts along the route, NaN if not on it


@dataclass(frozen=True, eq=False)
class Intersection:
    """The lane map plus the routes, built by :func:`build_intersection`."""

    settings: IntersectionSettings
    lane_map: LaneMap
    lane_length_m: np.ndarray  # (n_lanes,) m, in lane_map order
    lane_role: tuple[str, ...]  # "incoming", "connector" or "outgoing", per lane
    routes: Routes

    @property
    def n_lanes(self) -> int:
        return len(self.lane_map.lanes)

    def routes_through(self, lane: int) -> np.ndarray:
        """Indices of the routes that use lane index ``lane``."""
        return np.flatnonzero((self.routes.lanes == lane).any(axis=1))


# ---------------------------------------------------------------------- building
def build_intersection(settings: IntersectionSettings | None = None) -> Intersection:
    """Lanes, connectors and routes of the four-way intersection."""
    s = settings or IntersectionSettings()
    n, w, h, far = (
        s.lanes_per_direction,
        s.lane_width_m,
        s.box_half_m,
        s.box_half_m + s.arm_length_m,
    )
    lines: list[np.ndarray] = []
    roles: list[str] = []
    incoming: dict[tuple[int, int], int] = {}
    outgoing: dict[tuple[int, int], int] = {}
    for arm, u in enumerate(_ARM_DIRS):
        right_in = np.array([-u[1], u[0]])  # right of the driving direction -u
        for i in range(n):
            off = (i + 0.5) * w
            incoming[arm, i] = len(lines)
            lines.append(np.array([far * u + off * right_in, h * u + off * right_in]))
            roles.append("incoming")
            outgoing[arm, i] = len(lines)
            lines.append(np.array([h * u - off * right_in, far * u - off * right_in]))
            roles.append("outgoing")
    route_parts: list[tuple[int, int, int, int]] = []  # (incoming, connector, outgoing, turn)
    for arm in range(4):
        opposite, left, right = (arm + 2) % 4, (arm + 3) % 4, (arm + 1) % 4
        links = [(i, opposite, i, 0) for i in range(n)]
        links.append((0, left, 0, 1))
        links.append((n - 1, right, n - 1, 2))
        for lane_in, arm_out, lane_out, turn in links:
            a, b = incoming[arm, lane_in], outgoing[arm_out, lane_out]
            lines.append(_connector(lines[a][-1], lines[b][0], turn, s.arc_step_deg))
            roles.append("connector")
            route_parts.append((a, len(lines) - 1, b, turn))
    successors: dict[int, list[int]] = {k: [] for k in range(len(lines))}
    for a, c, b, _ in route_parts:
        successors[a].append(c)
        successors[c].append(b)
    lane_map = LaneMap(
        tuple(
            Lane(id=k + 1, centerline=line, successors=tuple(x + 1 for x in successors[k]))
            for k, line in enumerate(lines)
        )
    )
    lengths = np.array([_polyline_length(line) for line in lines])
    return Intersection(s, lane_map, lengths, tuple(roles), _routes(lines, lengths, route_parts))


def _connector(start: np.ndarray, end: np.ndarray, turn: int, step_deg: float) -> np.ndarray:
    """Straight segment, or a quarter arc tangent to both lanes (turn 1 left, 2 right)."""
    if turn == 0:
        return np.array([start, end])
    heading_in = np.arctan2(-start[1], -start[0])  # lanes end on the box edge heading inwards
    heading_in = np.round(heading_in / (np.pi / 2)) * (np.pi / 2)
    d = np.array([np.cos(heading_in), np.sin(heading_in)])
    sign = 1.0 if turn == 1 else -1.0  # left: centre on the left of the driving direction
    normal = sign * np.array([-d[1], d[0]])
    # The centre lies on the incoming lane's normal and is equidistant from both ends.
    radius = float(np.dot(end - start, end - start) / (2.0 * np.dot(end - start, normal)))
    centre = start + radius * normal
    n_steps = max(2, math.ceil(90.0 / step_deg))
    angle0 = np.arctan2(*(start - centre)[::-1])
    angles = angle0 + sign * np.linspace(0.0, np.pi / 2, n_steps + 1)
    arc = centre + radius * np.column_stack((np.cos(angles), np.sin(angles)))
    arc[0], arc[-1] = start, end  # exact joins, no rounding gap
    return arc


def _polyline_length(line: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())


def _routes(
    lines: list[np.ndarray], lengths: np.ndarray, parts: list[tuple[int, int, int, int]]
) -> Routes:
    polylines = []
    for a, c, b, _ in parts:
        # Lanes share their joining points: drop the duplicates.
        polylines.append(np.concatenate((lines[a], lines[c][1:], lines[b][1:])))
    n_vertices = np.array([len(p) for p in polylines])
    v_max = int(n_vertices.max())
    vertices = np.stack(
        [np.concatenate((p, np.repeat(p[-1:], v_max - len(p), 0))) for p in polylines]
    )
    seg = np.linalg.norm(np.diff(vertices, axis=1), axis=2)
    arc = np.concatenate((np.zeros((len(parts), 1)), np.cumsum(seg, axis=1)), axis=1)
    lanes = np.array([[a, c, b] for a, c, b, _ in parts])
    starts = np.concatenate(
        (np.zeros((len(parts), 1)), np.cumsum(lengths[lanes][:, :2], axis=1)), axis=1
    )
    offset = np.full((len(parts), len(lines)), np.nan)
    np.put_along_axis(offset, lanes, starts, axis=1)
    return Routes(
        vertices=vertices,
        n_vertices=n_vertices,
        arc=arc,
        length_m=arc[:, -1].copy(),
        lanes=lanes,
        lane_start_m=starts,
        turn=np.array([t for *_, t in parts]),
        lane_offset_m=offset,
    )


# ---------------------------------------------------------------------- poses on routes
def _segment(routes: Routes, route: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Index ``(N,)`` of the segment that holds arc length ``s`` on each agent's route."""
    arc = routes.arc[route]
    last = routes.n_vertices[route] - 2  # index of the last real segment
    k = (arc <= s[:, None]).sum(axis=1) - 1
    return np.clip(k, 0, last)


def pose(routes: Routes, route: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position ``(N, 2)`` m and heading ``(N,)`` rad at arc length ``s (N,)`` on ``route (N,)``.

    The heading is that of the polyline segment under the agent (on the sampled arcs it
    differs from the true tangent by at most half an ``arc_step_deg``).
    """
    k = _segment(routes, route, s)
    a = routes.vertices[route, k]
    b = routes.vertices[route, k + 1]
    seg_len = routes.arc[route, k + 1] - routes.arc[route, k]
    d = (b - a) / seg_len[:, None]
    xy = a + (s - routes.arc[route, k])[:, None] * d
    return xy, np.arctan2(d[:, 1], d[:, 0])


def lane_at(routes: Routes, route: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lane index ``(N,)`` under each agent and its arc length within that lane ``(N,)``."""
    starts = routes.lane_start_m[route]
    k = np.clip((starts <= s[:, None]).sum(axis=1) - 1, 0, 2)
    rows = np.arange(route.size)
    return routes.lanes[route, k], s - starts[rows, k]


def forward_paths(
    routes: Routes, route: np.ndarray, s: np.ndarray, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's path from ``xy`` to its route's end: padded ``(N, P, 2)`` m and points ``(N,)``.

    The path is the agent's position followed by the route vertices strictly ahead of it
    (padding repeats the last vertex, as :class:`risk.Frame` expects).
    """
    arc = routes.arc[route]
    n_real = routes.n_vertices[route]
    first_ahead = (arc <= s[:, None]).sum(axis=1)  # first vertex with arc > s
    first_ahead = np.minimum(first_ahead, n_real - 1)
    points = 1 + n_real - first_ahead
    width = int(points.max())
    j = np.arange(width)[None, :]
    idx = np.minimum(first_ahead[:, None] + j - 1, n_real[:, None] - 1)
    paths = routes.vertices[route[:, None], idx]
    paths[:, 0] = xy
    # Slots past the end repeat the last vertex already (idx is clipped), which is the
    # padding Frame expects; points says how many are real.
    return paths, points
