"""Agent paths from a lane graph: match agents to lanes, follow successor lanes forward.

Every converter with a map uses this module (``--paths map``). The rules (also in
docs/recorded-data.md):

- **Which agents.** Vehicles match vehicle and bus lanes; cyclists also bike lanes.
  Pedestrians and ``other`` agents are never matched: they get a straight path along
  their heading (pedestrians do not follow lane centre lines, and ``other`` is mostly
  static clutter).
- **Matching.** An agent matches a lane when its distance to the lane's centre line is at
  most ``max_lateral_m`` and its heading differs from the centre line's direction at the
  nearest point by at most ``max_heading_rad``. An agent may match several lanes
  (overlapping lanes at an intersection, a lane change in progress); a matched lane that is
  a successor of another matched lane of the same agent is dropped (the agent straddles
  the joint, and the predecessor's expansion already covers it). Agents that match no lane
  get a straight path.
- **Forward paths.** From each matched lane, routes follow successor links until they are
  ``max(v * horizon_s + margin_m, map_path_m)`` long beyond the projection point (the
  whole known path, capped at 300 m by default); at a fork every branch is
  a candidate, ordered straightest first (total heading change of the branch lane), and
  candidates are interleaved round-robin over the matched lanes and the forks so that the
  first ``max_candidates`` keep the nearest alternatives. A route that ends (a dead end or
  the edge of the map) is extended straight along its last segment.
- **Shape.** A path starts at the agent's own position, joins the centre line
  ``join_m`` ahead of the projection point (a straight blend, instead of a sideways jump
  to the centre line) and follows it to the route's end, at most ``max(v * horizon_s +
  margin_m, map_path_m)`` and at least ``v * horizon_s + margin_m``. Centre lines are simplified
  once (Ramer-Douglas-Peucker, ``simplify_m``) so that paths have few segments, which is
  what makes the O(p^2) path models cheap (paper Sec. IV-C).

Failure cases: an agent more than ``max_lateral_m`` from every centre line (parked at the
kerb, in a car park, on a lane the map lacks) or turning across lanes by more than
``max_heading_rad`` gets a straight path; an agent driving against a lane's direction is
not matched to it (a wrong-way driver gets a straight path); at a lane change the
target lane is a candidate only once the agent is within ``max_lateral_m`` of it; only the
first ``max_candidates`` routes are kept, so a far fork may be missing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from risk import geometry
from risk.frame import Kind, LaneMap

VEHICLE_LANE_KINDS = frozenset({"vehicle", "bus"})
"""Lane kinds a vehicle can be matched to."""
CYCLIST_LANE_KINDS = frozenset({"vehicle", "bus", "bike"})
"""Lane kinds a cyclist can be matched to."""

_EPS_M = 1e-9
_CUT_CHUNK = 4096  # path rows cut at once


@dataclass(frozen=True)
class PathSettings:
    """How agent paths are built (both ``map`` and ``hindsight`` modes).

    A path is at least ``v * horizon_s + margin_m`` long (``v`` the agent's speed, m/s):
    the distance the constant-speed prediction of the model spec (docs/models.md) covers, plus a
    margin so that a slow or stopped agent still has a path ahead of it.

    A **map** path goes on along the lane graph to the graph's end or ``map_path_m``
    beyond the agent, whichever comes first (never shorter than the above): the paper's
    path distance uses the agents' whole map paths, which a cut at ``v * T + margin``
    makes the same as trajectory distance. ``map_path_m = 0`` gives the short paths.
    """

    horizon_s: float = 12.0  # the paper's prediction horizon T
    margin_m: float = 10.0
    map_path_m: float = 300.0  # map paths: how far the lane graph is followed (see below)
    max_lateral_m: float = 2.0  # about half a lane width (lanes are 3-4 m wide)
    max_heading_rad: float = math.pi / 4  # 45 deg: a lane change, not a crossing lane
    max_candidates: int = 3
    join_m: float = 2.0
    simplify_m: float = 0.05

    def __post_init__(self) -> None:
        checks = (
            ("horizon_s", self.horizon_s >= 0),
            ("margin_m", self.margin_m >= 0),
            ("map_path_m", self.map_path_m >= 0),
            ("max_lateral_m", self.max_lateral_m > 0),
            ("max_heading_rad", 0 < self.max_heading_rad <= math.pi),
            ("max_candidates", self.max_candidates >= 1),
            ("join_m", self.join_m >= 0),
            ("simplify_m", self.simplify_m >= 0),
        )
        for name, ok in checks:
            value = getattr(self, name)
            if not (ok and math.isfinite(value)):
                raise ValueError(f"PathSettings.{name} is out of range: {value!r}")

    def required_length_m(self, speed_mps: np.ndarray) -> np.ndarray:
        """Path length needed at speed ``speed_mps`` (any shape), metres."""
        return np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0) * self.horizon_s + (
            self.margin_m
        )


# ---------------------------------------------------------------------- polylines
def dedupe(points: np.ndarray, tol_m: float = 1e-6) -> np.ndarray:
    """Drop consecutive points closer than ``tol_m``: ``(P, 2) -> (P', 2)``, P' >= 1."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return pts
    step = np.hypot(*np.diff(pts, axis=0).T)
    return pts[np.concatenate(([True], step > tol_m))]


def simplify(points: np.ndarray, tol_m: float) -> np.ndarray:
    """Indices of the points that Ramer-Douglas-Peucker keeps at tolerance ``tol_m``.

    ``points`` is ``(P, 2)``; the result is sorted and always holds both end points.
    Iterative (an explicit stack) and vectorised within each split.
    """
    n = len(points)
    if n <= 2 or tol_m <= 0:
        return np.arange(n)
    keep = np.zeros(n, dtype=bool)
    keep[[0, n - 1]] = True
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        inner = points[i + 1 : j]
        (ax, ay), (bx, by) = points[i], points[j]
        dist = geometry.point_segment_distance(inner[:, 0], inner[:, 1], ax, ay, bx, by)
        k = int(np.argmax(dist))
        if dist[k] > tol_m:
            k += i + 1
            keep[k] = True
            stack.append((i, k))
            stack.append((k, j))
    return np.flatnonzero(keep)


def arc_length(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length ``(P,)`` of a ``(P, 2)`` polyline, starting at 0
    (:func:`risk.geometry.cumulative_lengths` of one path)."""
    return geometry.cumulative_lengths(np.asarray(points, dtype=np.float64)[None])[0]


def lanelet_centerline(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Centre line ``(P, 2)`` of a lane from its bounds: the mean of the two (CommonRoad
    lanelets, Lanelet2 ways). Bounds with different point counts are first resampled at
    the same fractions of their arc length."""
    if len(left) != len(right):
        n = max(len(left), len(right))
        left, right = _resample(left, n), _resample(right, n)
    return 0.5 * (left + right)


def _resample(line: np.ndarray, n: int) -> np.ndarray:
    """``n`` points at equal arc-length fractions along ``line`` ``(P, 2)``."""
    cum = arc_length(line)
    if cum[-1] == 0:
        return np.repeat(line[:1], n, axis=0)
    target = np.linspace(0.0, cum[-1], n)
    return np.stack([np.interp(target, cum, line[:, 0]), np.interp(target, cum, line[:, 1])], 1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------------- path rows
@dataclass(frozen=True)
class PathRows:
    """Path candidates of many (frame, agent) pairs in flat padded form.

    ``R`` rows: ``frame (R,)`` and ``agent (R,)`` indices, ``points (R, P, 2)`` metres
    padded by repeating the last real point, ``count (R,)`` real points (>= 1).
    """

    frame: np.ndarray
    agent: np.ndarray
    points: np.ndarray
    count: np.ndarray

    @staticmethod
    def empty() -> PathRows:
        return PathRows(
            np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 1, 2)), np.zeros(0, np.int64)
        )

    @staticmethod
    def concat(parts: Sequence[PathRows]) -> PathRows:
        """All rows of ``parts`` (points padded to the widest part)."""
        parts = [p for p in parts if len(p.frame)]
        if not parts:
            return PathRows.empty()
        width = max(p.points.shape[1] for p in parts)
        padded = [_pad_points(p.points, p.count, width) for p in parts]
        return PathRows(
            np.concatenate([p.frame for p in parts]),
            np.concatenate([p.agent for p in parts]),
            np.concatenate(padded),
            np.concatenate([p.count for p in parts]),
        )

    def without_repeats(self, tol_m: float = 1e-9) -> PathRows:
        """The same rows with every point equal (within ``tol_m``) to its predecessor
        removed, so that no path has a zero-length segment. Vectorised over rows."""
        if len(self.frame) == 0:
            return self
        width = self.points.shape[1]
        real = np.arange(width)[None, :] < self.count[:, None]
        step = np.hypot(*np.diff(self.points, axis=1).transpose(2, 0, 1))
        keep = real & np.concatenate([np.ones((len(real), 1), bool), step > tol_m], axis=1)
        if keep.sum() == real.sum():
            return self
        order = np.argsort(~keep, axis=1, kind="stable")  # kept points first, in order
        points = np.take_along_axis(self.points, order[:, :, None], axis=1)
        count = keep.sum(axis=1)
        last = points[np.arange(len(points)), count - 1]
        pad = np.arange(width)[None, :] >= count[:, None]
        points = np.where(pad[:, :, None], last[:, None, :], points)
        return PathRows(self.frame, self.agent, points, count.astype(np.int64))


def _pad_points(points: np.ndarray, count: np.ndarray, width: int) -> np.ndarray:
    if points.shape[1] == width:
        return points
    last = points[np.arange(len(points)), count - 1]
    out = np.repeat(last[:, None, :], width, axis=1)
    out[:, : points.shape[1]] = points
    return out


def straight_rows(
    frame: np.ndarray,
    agent: np.ndarray,
    xy: np.ndarray,
    heading: np.ndarray,
    length_m: np.ndarray,
) -> PathRows:
    """One straight path per row: from ``xy`` ``(R, 2)`` along ``heading`` ``(R,)`` rad.

    Rows with ``length_m <= 0`` get the one-point path ``[xy]``.
    """
    direction = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    end = xy + np.maximum(length_m, 0.0)[:, None] * direction
    points = np.stack([xy, end], axis=1)
    count = np.where(length_m > 0, 2, 1).astype(np.int64)
    return PathRows(frame.astype(np.int64), agent.astype(np.int64), points, count)


# ---------------------------------------------------------------------- lane graph
@dataclass(frozen=True)
class Matches:
    """Agent-lane matches: for each of ``K`` matches the query index, the lane index (into
    the graph's lanes), the arc length of the projection point along the lane (m) and a
    cost (lower is a better fit: lateral distance and heading difference, each divided by
    its threshold)."""

    query: np.ndarray  # (K,) int64, sorted
    lane: np.ndarray  # (K,) int64
    s_m: np.ndarray  # (K,) float64
    cost: np.ndarray  # (K,) float64


class LaneGraph:
    """Centre lines and successor links of a :class:`risk.LaneMap`, ready for matching.

    Lanes whose centre line has fewer than two distinct points cannot give a direction and
    are left out (they stay in the scene's map). Successor ids that name no lane of the map
    (a map cropped at its edge) are ignored.
    """

    def __init__(self, lane_map: LaneMap, settings: PathSettings | None = None) -> None:
        self.settings = settings or PathSettings()
        pts: list[np.ndarray] = []
        ids: list[int] = []
        kinds: list[str] = []
        raw_succ: list[tuple[int, ...]] = []
        for lane in lane_map.lanes:
            line = dedupe(lane.centerline)
            if len(line) < 2:
                continue
            pts.append(line[simplify(line, self.settings.simplify_m)])
            ids.append(int(lane.id))
            kinds.append(lane.kind)
            raw_succ.append(tuple(int(s) for s in lane.successors))
        self.lane_ids = np.array(ids, dtype=np.int64)
        self.lane_kinds = tuple(kinds)
        index = {lane_id: i for i, lane_id in enumerate(ids)}
        self._points = pts
        self._cum = [arc_length(p) for p in pts]
        self.lane_length_m = np.array([c[-1] for c in self._cum])
        self._successors = [tuple(index[s] for s in succ if s in index) for succ in raw_succ]
        self._turn = np.array([_total_turn(p) for p in pts])
        self._build_segments()
        self._routes: list[tuple[int, ...]] = []
        self._route_index: dict[tuple[int, ...], int] = {}
        self._route_cache: dict[tuple[int, int], tuple[int, ...]] = {}
        self._candidate_cache: dict[tuple, tuple[tuple[int, int], ...]] = {}
        self._route_len: dict[int, float] = {}
        self._route_lines: dict[int, np.ndarray] = {}

    @property
    def n_lanes(self) -> int:
        return len(self._points)

    def _build_segments(self) -> None:
        """Flat segment arrays of all lanes (``S`` segments), for vectorised matching."""
        n_seg = np.array([len(p) - 1 for p in self._points], dtype=np.int64)
        self._seg_start = np.concatenate(([0], np.cumsum(n_seg)))
        if self.n_lanes == 0:
            self._seg_a = np.zeros((0, 2))
            self._seg_d = np.zeros((0, 2))
            self._seg_s0 = self._seg_len = self._seg_heading = np.zeros(0)
            self._bbox = np.zeros((0, 4))
            return
        self._seg_a = np.concatenate([p[:-1] for p in self._points])
        self._seg_d = np.concatenate([np.diff(p, axis=0) for p in self._points])
        self._seg_s0 = np.concatenate([c[:-1] for c in self._cum])
        self._seg_len = np.hypot(*self._seg_d.T)
        self._seg_heading = np.arctan2(self._seg_d[:, 1], self._seg_d[:, 0])
        self._bbox = np.array(
            [(*p.min(axis=0), *p.max(axis=0)) for p in self._points]
        )  # (L, 4): xmin, ymin, xmax, ymax

    # ------------------------------------------------------------------ matching
    def match(self, xy: np.ndarray, heading: np.ndarray, kinds: np.ndarray) -> Matches:
        """Lanes consistent with each query's position and heading.

        ``xy`` ``(Q, 2)`` m, ``heading`` ``(Q,)`` rad, ``kinds`` ``(Q,)`` Kind codes.
        Vectorised over queries: lane bounding boxes pick candidate (query, lane) pairs,
        then the exact point-to-segment distance runs over those pairs' segments.
        """
        xy = np.asarray(xy, np.float64)
        heading = np.asarray(heading, np.float64)
        kinds = np.asarray(kinds)
        # Chunks keep the (queries x lanes) bounding-box test small on large maps.
        chunk = max(1, 4_000_000 // max(self.n_lanes, 1))
        if len(xy) > chunk:
            parts = [
                self.match(xy[i : i + chunk], heading[i : i + chunk], kinds[i : i + chunk])
                for i in range(0, len(xy), chunk)
            ]
            offsets = range(0, len(xy), chunk)
            return Matches(
                np.concatenate([p.query + o for p, o in zip(parts, offsets, strict=True)]),
                np.concatenate([p.lane for p in parts]),
                np.concatenate([p.s_m for p in parts]),
                np.concatenate([p.cost for p in parts]),
            )
        s = self.settings
        q_idx, lane_idx = self._bbox_pairs(xy, kinds)
        if q_idx.size == 0:
            return Matches(*(np.zeros(0, np.int64),) * 2, np.zeros(0), np.zeros(0))
        # Expand each (query, lane) pair to the lane's segments.
        n_seg = self._seg_start[lane_idx + 1] - self._seg_start[lane_idx]
        pair_of_seg = np.repeat(np.arange(q_idx.size), n_seg)
        first = np.repeat(self._seg_start[lane_idx] - np.cumsum(n_seg) + n_seg, n_seg)
        seg = first + np.arange(pair_of_seg.size)
        p = xy[q_idx[pair_of_seg]]
        rel = p - self._seg_a[seg]
        t = np.clip(
            np.einsum("ij,ij->i", rel, self._seg_d[seg]) / self._seg_len[seg] ** 2, 0.0, 1.0
        )
        dist = np.hypot(*(rel - t[:, None] * self._seg_d[seg]).T)
        # Nearest segment of each pair: min per group, then the first segment reaching it.
        group_start = np.concatenate(([0], np.cumsum(n_seg)[:-1]))
        best = np.minimum.reduceat(dist, group_start)
        at_min = dist <= best[pair_of_seg]
        rank = np.where(at_min, pair_of_seg.size - np.arange(pair_of_seg.size), 0)
        arg = pair_of_seg.size - np.maximum.reduceat(rank, group_start)
        dheading = np.abs(wrap_angle(heading[q_idx] - self._seg_heading[seg[arg]]))
        ok = (best <= s.max_lateral_m) & (dheading <= s.max_heading_rad)
        s_m = self._seg_s0[seg[arg]] + t[arg] * self._seg_len[seg[arg]]
        cost = best / s.max_lateral_m + dheading / s.max_heading_rad
        return Matches(q_idx[ok], lane_idx[ok], s_m[ok], cost[ok])

    def _bbox_pairs(self, xy: np.ndarray, kinds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(query, lane) pairs whose lane bounding box (grown by the lateral threshold)
        holds the query and whose lane kind suits the query's kind."""
        if self.n_lanes == 0 or len(xy) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        r = self.settings.max_lateral_m
        b = self._bbox
        inside = (
            (xy[:, :1] >= b[None, :, 0] - r)
            & (xy[:, :1] <= b[None, :, 2] + r)
            & (xy[:, 1:] >= b[None, :, 1] - r)
            & (xy[:, 1:] <= b[None, :, 3] + r)
        )
        inside &= self._kind_allowed(kinds)
        q_idx, lane_idx = np.nonzero(inside)
        return q_idx.astype(np.int64), lane_idx.astype(np.int64)

    def _kind_allowed(self, kinds: np.ndarray) -> np.ndarray:
        """``(Q, L)`` whether each query's kind may use each lane."""
        vehicle_ok = np.array([k in VEHICLE_LANE_KINDS for k in self.lane_kinds], dtype=bool)
        cyclist_ok = np.array([k in CYCLIST_LANE_KINDS for k in self.lane_kinds], dtype=bool)
        kinds = np.asarray(kinds)
        return np.where(
            (kinds == Kind.VEHICLE)[:, None],
            vehicle_ok[None, :],
            (kinds == Kind.CYCLIST)[:, None] & cyclist_ok[None, :],
        )

    # ------------------------------------------------------------------ routes
    def routes_from(self, lane: int, need_m: float) -> tuple[int, ...]:
        """Route ids starting at lane index ``lane``, each at least ``need_m`` long from the
        lane's start unless it reaches a dead end; at most ``max_candidates``, nearest forks
        first. Cached per lane and 50 m bucket of ``need_m``."""
        bucket = max(1, math.ceil(need_m / 50.0))
        key = (lane, bucket)
        hit = self._route_cache.get(key)
        if hit is None:
            hit = tuple(self._route_id(r) for r in self._expand(lane, bucket * 50.0))
            self._route_cache[key] = hit
        return hit

    def _expand(self, lane: int, need_m: float) -> list[tuple[int, ...]]:
        """Breadth-first expansion of successor links, round-robin over forks."""
        cap = self.settings.max_candidates
        routes: list[tuple[tuple[int, ...], float]] = [((lane,), float(self.lane_length_m[lane]))]
        for _ in range(10_000):  # guard against degenerate zero-length loops
            if all(length >= need_m or not self._successors[r[-1]] for r, length in routes):
                break
            options: list[list[tuple[tuple[int, ...], float]]] = []
            for r, length in routes:
                succ = self._successors[r[-1]]
                if length >= need_m or not succ:
                    options.append([(r, length)])
                    continue
                ordered = sorted(succ, key=lambda j: (self._turn[j], self.lane_ids[j]))
                options.append([((*r, j), length + float(self.lane_length_m[j])) for j in ordered])
            routes = _round_robin(options)[:cap]
        return [r for r, _ in routes]

    def _route_id(self, lanes: tuple[int, ...]) -> int:
        rid = self._route_index.get(lanes)
        if rid is None:
            rid = len(self._routes)
            self._routes.append(lanes)
            self._route_index[lanes] = rid
        return rid

    def route_lanes(self, route_id: int) -> tuple[int, ...]:
        return self._routes[route_id]

    def _route_length(self, routes: np.ndarray) -> np.ndarray:
        """Arc length (m) of each route's polyline, ``(R,)``; cached per route."""
        cache = self._route_len
        for r in np.unique(routes).tolist():
            if r not in cache:
                cache[r] = float(arc_length(self.route_polyline(r))[-1])
        return np.array([cache[r] for r in routes.tolist()], dtype=np.float64)

    def route_polyline(self, route_id: int) -> np.ndarray:
        """The centre line ``(K, 2)`` of a route: its lanes' simplified centre lines joined.
        Cached per route (read-only)."""
        line = self._route_lines.get(route_id)
        if line is None:
            lanes = self._routes[route_id]
            line = dedupe(np.concatenate([self._points[i] for i in lanes]))
            line.flags.writeable = False
            self._route_lines[route_id] = line
        return line

    # ------------------------------------------------------------------ candidates
    def candidates(self, lanes: Sequence[int], at_end: Sequence[bool], need_m: float):
        """The chosen ``(match position, route id)`` pairs for one agent's matched lanes.

        ``lanes`` are the matched lane indices in order of preference, ``at_end`` whether
        the projection point is at the lane's end, ``need_m`` the largest required length
        from the start of the matched lanes. Cached: an agent keeps its lanes for many
        frames.
        """
        bucket = max(1, math.ceil(need_m / 50.0))
        key = (tuple(lanes), tuple(at_end), bucket)
        hit = self._candidate_cache.get(key)
        if hit is not None:
            return hit
        matched = set(lanes)
        keep = [
            i
            for i, lane in enumerate(lanes)
            if not any(lane in self._successors[o] for o in matched if o != lane)
        ] or [0]  # lanes that succeed each other in a loop: keep the best match
        per_lane: list[list[tuple[int, int]]] = []
        for i in keep:
            per_lane.append([(i, r) for r in self.routes_from(lanes[i], bucket * 50.0)])
        seen: set[tuple[int, ...]] = set()
        chosen: list[tuple[int, int]] = []
        for i, rid in _round_robin(per_lane):
            route = self._routes[rid]
            # A projection at the very end of a lane starts on its successors: routes from
            # two lanes merging into the same successor are then the same path.
            effective = route[1:] if at_end[i] and len(route) > 1 else route
            if effective in seen:
                continue
            seen.add(effective)
            chosen.append((i, rid))
            if len(chosen) == self.settings.max_candidates:
                break
        result = tuple(chosen)
        self._candidate_cache[key] = result
        return result

    def map_rows(
        self,
        frame: np.ndarray,
        agent: np.ndarray,
        xy: np.ndarray,
        heading: np.ndarray,
        speed: np.ndarray,
        kinds: np.ndarray,
    ) -> tuple[PathRows, np.ndarray]:
        """Lane-following path candidates for the given (frame, agent) states.

        All inputs have one entry per query (``Q``): ``frame``, ``agent`` indices, ``xy``
        ``(Q, 2)`` m, ``heading`` rad, ``speed`` m/s, ``kinds`` Kind codes. Returns the rows
        of the matched queries and a ``(Q,)`` mask of the queries that matched no lane (the
        caller gives those a straight path).
        """
        q = len(frame)
        need = self.settings.required_length_m(speed)
        reach = np.maximum(need, self.settings.map_path_m)  # follow the graph this far
        m = self.match(xy, heading, kinds)
        matched = np.zeros(q, dtype=bool)
        matched[m.query] = True
        if m.query.size == 0:
            return PathRows.empty(), ~matched
        # Per query: its matches in order of cost (the Python part, cached per lane set).
        order = np.lexsort((m.cost, m.query))
        mq, ml, ms = m.query[order], m.lane[order], m.s_m[order]
        at_end = ms >= self.lane_length_m[ml] - 1e-6
        bounds = np.flatnonzero(np.diff(mq)) + 1
        first = np.concatenate(([0], bounds))
        # Per query, vectorised: the largest required length from the start of its lanes.
        need_from_start = (np.maximum.reduceat(ms, first) + reach[mq[first]]).tolist()
        row_q: list[int] = []
        row_route: list[int] = []
        row_s: list[float] = []
        mq_l, ml_l, ms_l, end_l = mq.tolist(), ml.tolist(), ms.tolist(), at_end.tolist()
        for k, (lo, hi) in enumerate(zip(first.tolist(), [*bounds.tolist(), mq.size], strict=True)):
            qi = mq_l[lo]
            for i, rid in self.candidates(ml_l[lo:hi], end_l[lo:hi], need_from_start[k]):
                row_q.append(qi)
                row_route.append(rid)
                row_s.append(ms_l[lo + i])
        rq = np.array(row_q, dtype=np.int64)
        routes, starts = np.array(row_route, dtype=np.int64), np.array(row_s)
        # To the route's end (the graph's end, or where the expansion stopped beyond
        # ``reach``), at most ``reach``, at least ``need`` (straight on past a dead end).
        remaining = self._route_length(routes) - starts
        length = np.maximum(need[rq], np.minimum(reach[rq], remaining))
        parts = []
        for lo in range(0, rq.size, _CUT_CHUNK):  # bounds the (rows x route points) arrays
            sl = slice(lo, lo + _CUT_CHUNK)
            points, count = self._cut(routes[sl], starts[sl], length[sl], xy[rq[sl]])
            parts.append(PathRows(frame[rq[sl]], agent[rq[sl]], points, count))
        rows = PathRows.concat(parts)
        rows = PathRows(
            rows.frame.astype(np.int64), rows.agent.astype(np.int64), rows.points, rows.count
        )
        return rows.without_repeats(), ~matched

    def _cut(
        self, route: np.ndarray, s0: np.ndarray, length: np.ndarray, xy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Cut each route from its projection point ``s0`` for ``length`` metres, vectorised.

        A row's points: the agent position, the centre line point ``join_m`` ahead of the
        projection, the centre line vertices up to ``s0 + length``, and the point there
        (beyond a route's end the centre line continues straight along its last segment).
        """
        used = np.unique(route)
        lines = {int(r): self.route_polyline(int(r)) for r in used}
        width = max(len(v) for v in lines.values())
        pts = np.zeros((len(used), width, 2))
        cum = np.full((len(used), width), np.inf)
        n_pts = np.zeros(len(used), dtype=np.int64)
        for i, r in enumerate(used):
            line = lines[int(r)]
            pts[i, : len(line)] = line
            pts[i, len(line) :] = line[-1]
            cum[i, : len(line)] = arc_length(line)
            n_pts[i] = len(line)
        local = np.searchsorted(used, route)
        P, C, K = pts[local], cum[local], n_pts[local]
        s_end = s0 + length
        s_join = np.minimum(s0 + self.settings.join_m, s_end)
        p_join = _interp(P, C, K, s_join)
        p_end = _interp(P, C, K, s_end)
        first = (s_join[:, None] >= C).sum(axis=1)
        inner = np.maximum((s_end[:, None] > C).sum(axis=1) - first, 0)
        has_join = s_join < s_end - _EPS_M
        has_any = length > 0
        width_out = 3 + int(inner.max(initial=0))
        rows = np.arange(len(route))
        out = np.empty((len(route), width_out, 2))
        out[:, 0] = xy
        count = np.ones(len(route), dtype=np.int64)
        out[rows, count] = p_join
        count += has_join & has_any
        j = np.arange(width_out - 3)
        src = np.minimum(first[:, None] + j[None, :], K[:, None] - 1)
        take = j[None, :] < inner[:, None]
        slots = count[:, None] + j[None, :]
        rr, jj = np.nonzero(take)
        out[rr, slots[rr, jj]] = P[rr, src[rr, jj]]
        count += inner * has_any
        out[rows, count] = p_end
        count += has_any
        last = out[rows, count - 1]
        pad = np.arange(width_out)[None, :] >= count[:, None]
        out = np.where(pad[:, :, None], last[:, None, :], out)
        return out, count


def _interp(P: np.ndarray, C: np.ndarray, K: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Point at arc length ``s`` on each padded polyline (rows of ``P`` with ``C``, ``K``
    real points); beyond the end the last segment continues straight."""
    rows = np.arange(len(s))
    k = np.clip((s[:, None] >= C).sum(axis=1) - 1, 0, K - 2)
    a, b = P[rows, k], P[rows, k + 1]
    seg = C[rows, k + 1] - C[rows, k]
    t = (s - C[rows, k]) / seg
    return a + t[:, None] * (b - a)


def _round_robin(groups: Sequence[Sequence]) -> list:
    """First items of every group, then second items, ...: ``[[a1, a2], [b1]] -> [a1, b1, a2]``."""
    out: list = []
    depth = max((len(g) for g in groups), default=0)
    for d in range(depth):
        out.extend(g[d] for g in groups if d < len(g))
    return out


def _total_turn(points: np.ndarray) -> float:
    """Absolute heading change between a polyline's first and last segment, rad."""
    d0 = points[1] - points[0]
    d1 = points[-1] - points[-2]
    turn = np.array(math.atan2(d1[1], d1[0]) - math.atan2(d0[1], d0[0]))
    return abs(float(wrap_angle(turn)))
