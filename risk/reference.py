"""A slow, plain-Python reference of the nine models: the oracle for the fast ones.

Written straight from the model spec (docs/models.md) with loops over agents, candidates, steps and
segments, ``math`` instead of numpy in the inner loops, no pruning, no caching, and no
code shared with the vectorised modules (only the frame, the parameter dataclasses and
the settings). Tests compare :func:`reference_evaluate` with :func:`risk.evaluate` on
random frames. It is far too slow for real use: keep frames small.

The conventions it shares with the fast code are the choices documented in
docs/models.md (extension direction, circle placement, on-path tolerance, first crossing
along the agent's path, ties to the earliest step).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from risk.frame import Frame
from risk.prediction import PredictionSettings
from risk.registry import resolve_models, resolve_params

Point = tuple[float, float]


# ---------------------------------------------------------------------- plain geometry
def _seg_len(a: Point, b: Point) -> float:
    return math.hypot(b[0] - a[0], b[1] - a[1])


def _arc_lengths(path: list[Point]) -> list[float]:
    out = [0.0]
    for i in range(1, len(path)):
        out.append(out[-1] + _seg_len(path[i - 1], path[i]))
    return out


def _direction(path: list[Point], j: int, heading: float) -> Point:
    """Unit direction of segment j, or of the last non-degenerate one before it."""
    while j >= 0:
        a, b = path[j], path[j + 1]
        length = _seg_len(a, b)
        if length > 0:
            return ((b[0] - a[0]) / length, (b[1] - a[1]) / length)
        j -= 1
    return (math.cos(heading), math.sin(heading))


def _extend(path: list[Point], heading: float, min_length: float) -> list[Point]:
    """Extend straight along the last real segment (or the heading) to ``min_length``."""
    total = _arc_lengths(path)[-1]
    if total >= min_length:
        return list(path)
    if len(path) >= 2:
        ux, uy = _direction(path, len(path) - 2, heading)
    else:
        ux, uy = math.cos(heading), math.sin(heading)
    extra = min_length - total
    end = path[-1]
    return [*path, (end[0] + ux * extra, end[1] + uy * extra)]


def _point_at(path: list[Point], arcs: list[float], s: float, heading: float):
    """Position and unit path direction at arc length s (clipped to the path)."""
    if len(path) == 1:
        return path[0], (math.cos(heading), math.sin(heading))
    s = min(max(s, 0.0), arcs[-1])
    j = 0
    for i in range(len(arcs)):
        if arcs[i] <= s:
            j = i
    j = min(j, len(path) - 2)
    seg = arcs[j + 1] - arcs[j]
    f = (s - arcs[j]) / seg if seg > 0 else 0.0
    f = min(max(f, 0.0), 1.0)
    a, b = path[j], path[j + 1]
    return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])), _direction(path, j, heading)


def _cut(path: list[Point], length: float, heading: float) -> list[Point]:
    arcs = _arc_lengths(path)
    kept = [p for p, s in zip(path, arcs, strict=True) if s <= length]
    end, _ = _point_at(path, arcs, length, heading)
    return [*kept, end]


def _segments(path: list[Point]) -> list[tuple[Point, Point]]:
    if len(path) == 1:
        return [(path[0], path[0])]
    return [(path[i], path[i + 1]) for i in range(len(path) - 1)]


def _point_seg(p: Point, a: Point, b: Point) -> float:
    abx, aby = b[0] - a[0], b[1] - a[1]
    len2 = abx * abx + aby * aby
    t = 0.0
    if len2 > 0:
        t = ((p[0] - a[0]) * abx + (p[1] - a[1]) * aby) / len2
        t = min(max(t, 0.0), 1.0)
    return math.hypot(p[0] - a[0] - t * abx, p[1] - a[1] - t * aby)


def _orientation(a: Point, b: Point, c: Point) -> int:
    v = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    return 0 if v == 0 else (1 if v > 0 else -1)


def _on_box(a: Point, b: Point, c: Point) -> bool:
    """c within the bounding box of a-b (used for collinear points)."""
    return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])


def _intersect(p1: Point, q1: Point, p2: Point, q2: Point) -> bool:
    """Textbook segment intersection test (general and collinear cases)."""
    o1, o2 = _orientation(p1, q1, p2), _orientation(p1, q1, q2)
    o3, o4 = _orientation(p2, q2, p1), _orientation(p2, q2, q1)
    if o1 != o2 and o3 != o4:
        return True
    return (
        (o1 == 0 and _on_box(p1, q1, p2))
        or (o2 == 0 and _on_box(p1, q1, q2))
        or (o3 == 0 and _on_box(p2, q2, p1))
        or (o4 == 0 and _on_box(p2, q2, q1))
    )


def _segments_meet(p1: Point, q1: Point, p2: Point, q2: Point) -> bool:
    """Whether two segments cross or touch (the 2D headway's crossing test).

    Decided by orientation signs. Where an end point lies on the other segment to the
    last bit, the signs, and so the verdict, depend on rounding, and the kernel, whose
    expressions are ordered differently, may decide the other way. The oracle tests accept
    either verdict there and nowhere else (``tests/oracle_ties.py``)."""
    return _intersect(p1, q1, p2, q2)


def _seg_seg(p1: Point, q1: Point, p2: Point, q2: Point) -> float:
    if _intersect(p1, q1, p2, q2):
        return 0.0
    return min(
        _point_seg(p1, p2, q2),
        _point_seg(q1, p2, q2),
        _point_seg(p2, p1, q1),
        _point_seg(q2, p1, q1),
    )


def _polyline_distance(a: list[Point], b: list[Point]) -> float:
    best = math.inf
    for p1, q1 in _segments(a):
        for p2, q2 in _segments(b):
            best = min(best, _seg_seg(p1, q1, p2, q2))
    return best


def _project(p: Point, path: list[Point]) -> tuple[float, float]:
    """Distance to the path and arc length of the nearest point (first one on ties)."""
    arcs = _arc_lengths(path)
    best, best_arc = math.inf, 0.0
    for j, (a, b) in enumerate(_segments(path)):
        abx, aby = b[0] - a[0], b[1] - a[1]
        len2 = abx * abx + aby * aby
        t = 0.0
        if len2 > 0:
            t = min(max(((p[0] - a[0]) * abx + (p[1] - a[1]) * aby) / len2, 0.0), 1.0)
        d = math.hypot(p[0] - a[0] - t * abx, p[1] - a[1] - t * aby)
        if d < best:
            seg = arcs[j + 1] - arcs[j] if len(path) > 1 else 0.0
            best, best_arc = d, arcs[j] + t * seg
    return best, best_arc


def _first_crossing(agent: list[Point], ego: list[Point]) -> tuple[float, float] | None:
    """(agent arc, ego arc) of the first point along ``agent`` that lies on ``ego``."""
    a_arcs, e_arcs = _arc_lengths(agent), _arc_lengths(ego)
    best: tuple[float, float] | None = None
    for j, (p, q) in enumerate(_segments(agent)):
        for i, (e0, e1) in enumerate(_segments(ego)):
            if not _segments_meet(p, q, e0, e1):
                continue
            dx, dy = q[0] - p[0], q[1] - p[1]
            ex, ey = e1[0] - e0[0], e1[1] - e0[1]
            den = dx * ey - dy * ex
            wx, wy = e0[0] - p[0], e0[1] - p[1]
            if den != 0:
                t = (wx * ey - wy * ex) / den
            else:  # parallel and touching: first shared point along the agent segment
                l2 = dx * dx + dy * dy
                if l2 > 0:
                    t0 = (wx * dx + wy * dy) / l2
                    t1 = ((e1[0] - p[0]) * dx + (e1[1] - p[1]) * dy) / l2
                    t = min(t0, t1)
                else:
                    t = 0.0
            t = min(max(t, 0.0), 1.0)
            x = (p[0] + t * dx, p[1] + t * dy)
            el2 = ex * ex + ey * ey
            u = 0.0
            if el2 > 0:
                u = min(max(((x[0] - e0[0]) * ex + (x[1] - e0[1]) * ey) / el2, 0.0), 1.0)
            a_seg = a_arcs[j + 1] - a_arcs[j] if len(agent) > 1 else 0.0
            e_seg = e_arcs[i + 1] - e_arcs[i] if len(ego) > 1 else 0.0
            cand = (a_arcs[j] + t * a_seg, e_arcs[i] + u * e_seg)
            if best is None or cand < best:
                best = cand
    return best


# ---------------------------------------------------------------------- per agent
def _step_time(k: int, settings: PredictionSettings) -> float:
    """s_k: 0, dt, ..., T, the last one exactly the horizon."""
    n = settings.n_steps
    return settings.horizon_s if k == n - 1 else k * (settings.horizon_s / (n - 1))


class _Agent:
    """One candidate of one agent: extended path, cut path and predicted states."""

    def __init__(self, frame: Frame, i: int, path: list[Point], settings: PredictionSettings):
        self.i = i
        self.v = float(frame.speed[i])
        self.heading = float(frame.heading[i])
        self.length = float(frame.length[i])
        self.width = float(frame.width[i])
        self.xy = (float(frame.xy[i, 0]), float(frame.xy[i, 1]))
        horizon = settings.horizon_s
        self.path = _extend(path, self.heading, self.v * horizon)
        self.cut = _cut(self.path, self.v * horizon, self.heading)
        u = settings.uncertainty.for_kind(int(frame.kinds[i]))
        arcs = _arc_lengths(self.path)
        n = settings.n_steps
        self.pos, self.cov, self.sig_lon, self.dirs = [], [], [], []
        for k in range(n):
            s = _step_time(k, settings)
            p, (c, sn) = _point_at(self.path, arcs, self.v * s, self.heading)
            lon = min(
                u.sigma0_lon_m + u.growth_lon * self.v * s + u.time_growth_lon_mps * s,
                u.sigma_max_lon_m,
            )
            lat = min(
                u.sigma0_lat_m + u.growth_lat * self.v * s + u.time_growth_lat_mps * s,
                u.sigma_max_lat_m,
            )
            self.pos.append(p)
            self.dirs.append((c, sn))
            self.sig_lon.append(lon)
            self.cov.append(
                (
                    lon * lon * c * c + lat * lat * sn * sn,
                    (lon * lon - lat * lat) * c * sn,
                    lon * lon * sn * sn + lat * lat * c * c,
                )
            )


def _overlaps(a: _Agent, b: _Agent) -> list[float]:
    out = []
    for k in range(len(a.pos)):
        sxx = a.cov[k][0] + b.cov[k][0]
        sxy = a.cov[k][1] + b.cov[k][1]
        syy = a.cov[k][2] + b.cov[k][2]
        det = sxx * syy - sxy * sxy
        dx = b.pos[k][0] - a.pos[k][0]
        dy = b.pos[k][1] - a.pos[k][1]
        q = (syy * dx * dx - 2 * sxy * dx * dy + sxx * dy * dy) / det
        out.append(math.exp(-0.5 * q) / (2 * math.pi * math.sqrt(det)))
    return out


def _encounter(ego: _Agent, other: _Agent) -> tuple[float, int]:
    """Closest distance, and the first step within 1e-9 m of it."""
    dists = [
        math.hypot(other.pos[k][0] - ego.pos[k][0], other.pos[k][1] - ego.pos[k][1])
        for k in range(len(ego.pos))
    ]
    best = min(dists)
    first = next(k for k, d in enumerate(dists) if d <= best + 1e-9)
    return best, first


def _pair_risks(ego: _Agent, other: _Agent, params: dict[str, Any], st: PredictionSettings):
    """Every model's risk for one (ego candidate, agent candidate) pair."""
    n = st.n_steps
    steps = [_step_time(k, st) for k in range(n)]
    out: dict[str, float] = {}

    def r_dist(d: float, eps: float) -> float:
        return eps / (eps + d)

    out["current_distance"] = r_dist(
        math.hypot(other.xy[0] - ego.xy[0], other.xy[1] - ego.xy[1]),
        params["current_distance"].epsilon_m,
    )
    out["path_distance"] = r_dist(
        _polyline_distance(ego.path, other.path), params["path_distance"].epsilon_m
    )
    out["trajectory_distance"] = r_dist(
        _polyline_distance(ego.cut, other.cut), params["trajectory_distance"].epsilon_m
    )
    d_e, k_e = _encounter(ego, other)

    def r_enc(p: Any) -> float:
        limit = st.horizon_s if p.encounter_time_max_s is None else p.encounter_time_max_s
        return r_dist(d_e, p.epsilon_m) if steps[k_e] < limit else 0.0

    out["closest_encounter"] = r_enc(params["closest_encounter"])

    _, l1 = _project(ego.xy, ego.path)

    def headway_time(l2: float) -> float:
        if ego.v <= 0 or l2 < l1:
            return math.inf
        return (l2 - l1) / ego.v

    lateral, l2 = _project(other.xy, ego.path)
    for name in ("headway", "headway_2d"):
        p = params[name]
        on_path = lateral <= p.on_path_tolerance_m
        th = headway_time(l2) if on_path else math.inf
        if name == "headway_2d" and not on_path:
            crossing = _first_crossing(other.path, ego.path)
            if crossing is not None:
                th = headway_time(crossing[1] - crossing[0])
        out[name] = max(r_enc(p), p.tau_s / (p.tau_s + th))

    pc = params["circles"]
    best = math.inf
    for k in range(n):
        ego_body = ego.length if pc.radius_rule == "spec" else ego.width
        r1 = 0.5 * ego_body + pc.sigma_scale * ego.sig_lon[k]
        r2 = 0.5 * other.width + pc.sigma_scale * other.sig_lon[k]
        for j in range(pc.n_circles):
            off = ((j + 0.5) / pc.n_circles - 0.5) * other.length
            cx = other.pos[k][0] + other.dirs[k][0] * off
            cy = other.pos[k][1] + other.dirs[k][1] * off
            gap = math.hypot(cx - ego.pos[k][0], cy - ego.pos[k][1]) - r1 - r2
            best = min(best, gap)
    out["circles"] = r_dist(max(best, 0.0), pc.epsilon_m)

    po = _overlaps(ego, other)
    out["gaussian"] = max(po)
    tau = params["survival"].escape_time_s
    survive, risk = 1.0, 0.0
    for p_k in po:
        risk += p_k * survive
        survive *= math.exp(-(p_k + st.dt_s / tau))
    out["survival"] = risk
    return out


def reference_evaluate(
    frame: Frame,
    models: Iterable[str] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    prediction: PredictionSettings | None = None,
) -> dict[str, np.ndarray]:
    """Same contract as :func:`risk.evaluate`, computed slowly with plain loops."""
    names = resolve_models(models)
    chosen = resolve_params(params)
    st = PredictionSettings() if prediction is None else prediction
    n = frame.n_agents
    out = {name: np.full(n, np.nan) for name in names}
    candidates: dict[int, list[_Agent]] = {}
    for i in range(n):
        if not frame.valid[i]:
            continue
        candidates[i] = [
            _Agent(frame, i, [(float(x), float(y)) for x, y in path], st)
            for path in frame.agent_paths(i)
        ]
    for i in range(n):
        if i == frame.ego or not frame.valid[i]:
            continue
        for ego in candidates[frame.ego]:
            for other in candidates[i]:
                risks = _pair_risks(ego, other, chosen, st)
                for name in names:
                    prev = out[name][i]
                    out[name][i] = risks[name] if math.isnan(prev) else max(prev, risks[name])
    return out
