"""The kernel's corridor stage (:class:`risk.cascade_config.CorridorSettings`): the agents
a planner following the ego's route reacts to, found geometrically in one compiled pass
over the agents.

Measured first (issue 37): of 189 frames where the cascade changed an IDM plan, 186 had
dropped an in-lane leader ahead (median 105 m, 10th-90th percentile 77-170 m) that the
Gaussian stage judged harmless. A planner that follows a leader reacts to it well before
any collision risk appears, so the stage looks where the planner looks: along the ego's
path, out to the distance at which the planner starts to react.
"""

from __future__ import annotations

import math

import numpy as np

from risk.kernel_jit import _inner, _jit
from risk.kernel_prediction import _others, _row_starts
from risk.kernel_shared import BEHIND, CROSSING, LEADER

#: The corridor's numbers in the kernel's float vector, in this order
#: (:data:`risk.cascade.CORRIDOR_FIELDS` packs them).
C_LEADERS, C_HEADWAY, C_BRAKE, C_ACCEL, C_MARGIN, C_LAT, C_CROSS, C_SLACK, C_HORIZON = range(9)
#: Time step (s) of the crossing check along an agent's path.
CROSS_STEP_S = 0.2


@_inner
def _corridor_line(paths, path_points, row, x0, y0, heading):
    """The polyline of path row ``row`` (``x, y, cumulative arc``); an agent with a path of
    fewer than two points runs straight along its heading from ``(x0, y0)``."""
    n = path_points[row] if row >= 0 else 0
    if n < 2:
        xs = np.empty(2)
        ys = np.empty(2)
        xs[0], ys[0] = x0, y0
        xs[1], ys[1] = x0 + math.cos(heading), y0 + math.sin(heading)
        n = 2
    else:
        xs = np.empty(n)
        ys = np.empty(n)
        for k in range(n):
            xs[k] = paths[row, k, 0]
            ys[k] = paths[row, k, 1]
    cum = np.zeros(n)
    for k in range(1, n):
        cum[k] = cum[k - 1] + math.hypot(xs[k] - xs[k - 1], ys[k] - ys[k - 1])
    return xs, ys, cum


@_inner
def _corridor_project(xs, ys, cum, qx, qy):
    """Arc length along the polyline, signed lateral offset (the distance to the nearest
    point, left positive) and the direction (unit x, y) of the segment of the nearest
    point to ``(qx, qy)``; the first segment runs on backwards and the last forwards (a
    path extended straight)."""
    n = xs.shape[0]
    best = math.inf
    arc, lat, ux, uy = 0.0, math.inf, 1.0, 0.0
    for k in range(n - 1):
        dx, dy = xs[k + 1] - xs[k], ys[k + 1] - ys[k]
        seg2 = dx * dx + dy * dy
        if seg2 <= 0.0:
            continue
        t = ((qx - xs[k]) * dx + (qy - ys[k]) * dy) / seg2
        if k > 0 and t < 0.0:
            t = 0.0
        if k < n - 2 and t > 1.0:
            t = 1.0
        px, py = xs[k] + t * dx, ys[k] + t * dy
        d2 = (qx - px) ** 2 + (qy - py) ** 2
        if d2 < best:
            best = d2
            seg = math.sqrt(seg2)
            arc = cum[k] + t * seg
            side = dx * (qy - ys[k]) - dy * (qx - xs[k])
            lat = math.sqrt(d2) if side >= 0 else -math.sqrt(d2)
            ux, uy = dx / seg, dy / seg
    return arc, lat, ux, uy


@_inner
def _line_bounds(xs, ys):
    """What :func:`_line_gap` needs of a polyline, once per frame: the bounding box of its
    points, and its two end rays (start point, unit direction, 1 if it exists: the first
    segment runs on backwards and the last forwards, when not of zero length)."""
    n = xs.shape[0]
    out = np.zeros(14)
    out[0], out[1], out[2], out[3] = xs.min(), ys.min(), xs.max(), ys.max()
    for r, (k, sign) in enumerate(((0, -1.0), (n - 2, 1.0))):
        dx, dy = xs[k + 1] - xs[k], ys[k + 1] - ys[k]
        seg = math.hypot(dx, dy)
        if seg > 0.0:
            base = 4 + 5 * r
            out[base] = xs[k] if sign < 0 else xs[k + 1]
            out[base + 1] = ys[k] if sign < 0 else ys[k + 1]
            out[base + 2], out[base + 3] = sign * dx / seg, sign * dy / seg
            out[base + 4] = 1.0
    return out


@_inner
def _line_gap(bounds, qx, qy):
    """A lower bound of ``|lat|`` of :func:`_corridor_project` (the distance from
    ``(qx, qy)`` to the polyline with its end rays) in O(1): the least of the distances to
    the points' bounding box, which holds every segment, and to the two rays. Like the
    distance itself it is 1-Lipschitz in the point."""
    gx = max(bounds[0] - qx, 0.0, qx - bounds[2])
    gy = max(bounds[1] - qy, 0.0, qy - bounds[3])
    gap = math.hypot(gx, gy)
    for base in (4, 9):
        if bounds[base + 4] > 0.5:
            rx, ry = qx - bounds[base], qy - bounds[base + 1]
            along = rx * bounds[base + 2] + ry * bounds[base + 3]
            if along <= 0.0:
                d = math.hypot(rx, ry)
            else:
                d = abs(rx * bounds[base + 3] - ry * bounds[base + 2])
            gap = min(gap, d)
    return gap


@_inner
def _at_arc(xs, ys, cum, arc):
    """The point at arc length ``arc`` along the polyline, straight on beyond either end."""
    n = xs.shape[0]
    k = 0
    while k < n - 2 and cum[k + 1] < arc:
        k += 1
    span = cum[k + 1] - cum[k]
    f = (arc - cum[k]) / span if span > 0 else 0.0
    return xs[k] + f * (xs[k + 1] - xs[k]), ys[k] + f * (ys[k + 1] - ys[k])


@_inner
def _line_box(xs, ys, cum, a0, a1, pad):
    """Bounding box ``(x0, y0, x1, y1)`` of the polyline between arc lengths ``a0`` and
    ``a1`` (straight on beyond its ends), grown by ``pad``."""
    x, y = _at_arc(xs, ys, cum, a0)
    x0, y0, x1, y1 = x, y, x, y
    x, y = _at_arc(xs, ys, cum, a1)
    x0, y0, x1, y1 = min(x0, x), min(y0, y), max(x1, x), max(y1, y)
    for k in range(xs.shape[0]):
        if a0 < cum[k] < a1:
            x0, y0 = min(x0, xs[k]), min(y0, ys[k])
            x1, y1 = max(x1, xs[k]), max(y1, ys[k])
    return np.array([x0 - pad, y0 - pad, x1 + pad, y1 + pad])


@_inner
def _corridor_range(params, v, closing):
    """The interaction range (m) at ego speed ``v`` closing at ``closing`` (m/s)."""
    brake = v * v / (2.0 * params[C_BRAKE])
    gap = v * max(closing, 0.0) / (2.0 * math.sqrt(params[C_ACCEL] * params[C_BRAKE]))
    return params[C_MARGIN] + v * params[C_HEADWAY] + max(brake, gap)


@_jit
def corridor_keep(
    xy, heading, speed, length, width, valid, paths, path_points, path_agent, ego, params
):
    """The corridor stage: ``(N,)`` int8, :data:`LEADER` or :data:`CROSSING` for the agents
    it keeps, :data:`BEHIND` for those it drops, :data:`NOT_KEPT` for the others (and for
    the ego and invalid agents).

    The corridor is the ego's first path candidate, extended straight at both ends; an
    agent is *in* it when its centre's lateral offset is at most ``(w_ego + w_i) / 2 +
    lateral_margin``. **Leaders**: agents in the corridor ahead of the ego whose bumper
    gap is within the range (:func:`_corridor_range`, with the speed at which the ego
    closes on the agent along the corridor); the ``leaders`` nearest are kept.
    **Behind**: an agent in the corridor behind the ego whose bumper gap exceeds what it
    can close within the horizon at its speed along the corridor, plus ``margin``: no
    planner that follows a path reacts to it within the horizon; it is dropped.
    **Crossing** (when ``params[C_CROSS]`` is 1): an agent outside the corridor, moving
    at constant speed along its first path candidate (straight on along its heading or
    its last segment), whose first point inside the corridor lies ahead of the ego and
    within the range for a standing obstacle, reached at ``t <= horizon`` no later than
    ``crossing_slack`` after the ego has passed it (the ego at its present speed).
    One pass over the agents; each costs O(path points) for a leader and O(steps x path
    points) for a crossing check, which a bounding-box test skips (exactly: no decision
    changes) for agents whose motion within the horizon never comes near the part of the
    corridor a crossing may count. A point's projection onto the corridor is skipped
    where an O(1) lower bound of its distance (:func:`_line_gap`) already puts it
    outside, and a crossing check skips the steps that bound shows cannot reach the
    corridor (exact too: the oracle test compares every decision)."""
    n = xy.shape[0]
    out = np.zeros(n, np.int8)
    if n == 0 or ego < 0 or not valid[ego]:
        return out
    starts = _row_starts(path_agent, n)
    ego_row = starts[ego] if starts[ego] < starts[ego + 1] else -1
    ex, ey, ecum = _corridor_line(paths, path_points, ego_row, xy[ego, 0], xy[ego, 1], heading[ego])
    s_ego, _, _, _ = _corridor_project(ex, ey, ecum, xy[ego, 0], xy[ego, 1])
    v = max(speed[ego], 0.0)
    range_stop = _corridor_range(params, v, v)  # for a standing obstacle
    horizon = params[C_HORIZON]
    agents = _others(valid, ego)
    m = agents.shape[0]
    # A box around every point a crossing may count: ahead of the ego within the range
    # (plus the largest bumper reach) and within the largest half width of the line.
    reach_max, half_max = 0.0, 0.0
    for a in range(m):
        reach_max = max(reach_max, 0.5 * (length[ego] + length[agents[a]]))
        half_max = max(half_max, 0.5 * (width[ego] + width[agents[a]]) + params[C_LAT])
    box = _line_box(ex, ey, ecum, s_ego, s_ego + range_stop + reach_max, half_max)
    bounds = _line_bounds(ex, ey)
    lead_arc = np.full(m, math.inf)
    for a in range(m):
        i = agents[a]
        half = 0.5 * (width[ego] + width[i]) + params[C_LAT]
        reach = 0.5 * (length[ego] + length[i])
        # (the 1e-6 m keeps rounding from deciding: a gap above it is certainly outside)
        inside = _line_gap(bounds, xy[i, 0], xy[i, 1]) <= half + 1e-6
        if inside:
            s, lat, ux, uy = _corridor_project(ex, ey, ecum, xy[i, 0], xy[i, 1])
            inside = abs(lat) <= half
        if inside:
            along = speed[i] * (math.cos(heading[i]) * ux + math.sin(heading[i]) * uy)
            if s > s_ego:
                if s - s_ego - reach <= _corridor_range(params, v, v - along):
                    lead_arc[a] = s
            elif s_ego - s - reach > max(along - v, 0.0) * horizon + params[C_MARGIN]:
                out[i] = BEHIND  # a follower that cannot close the gap within the horizon
            continue
        if params[C_CROSS] < 0.5 or speed[i] <= 0.0:
            continue
        row = starts[i] if starts[i] < starts[i + 1] else -1
        ax, ay, acum = _corridor_line(paths, path_points, row, xy[i, 0], xy[i, 1], heading[i])
        na = ax.shape[0]
        # exact pruning: the agent's motion within the horizon never enters that box
        motion = _line_box(ax, ay, acum, 0.0, speed[i] * horizon, 0.0)
        if motion[0] > box[2] or box[0] > motion[2] or motion[1] > box[3] or box[1] > motion[3]:
            continue
        seg = 0
        steps = int(horizon / CROSS_STEP_S + 1e-9)
        outside_until = -math.inf  # points at an arc below this are outside the corridor
        for k in range(1, steps + 1):
            t = k * CROSS_STEP_S
            arc = speed[i] * t
            if arc < outside_until:
                continue
            while seg < na - 2 and acum[seg + 1] < arc:
                seg += 1
            span = acum[seg + 1] - acum[seg]
            f = (arc - acum[seg]) / span if span > 0 else 0.0
            qx = ax[seg] + f * (ax[seg + 1] - ax[seg])
            qy = ay[seg] + f * (ay[seg + 1] - ay[seg])
            gap = _line_gap(bounds, qx, qy)
            if gap <= half + 1e-6:
                s, lat, _, _ = _corridor_project(ex, ey, ecum, qx, qy)
                gap = abs(lat)
            if gap > half:
                # The gap (the distance to the extended line, or its lower bound) falls by
                # at most the arc the agent travels: no point before this arc can be
                # inside (1e-6 m for rounding). Exact; far agents skip steps.
                outside_until = arc + (gap - half) - 1e-6
                continue
            # the first point in the corridor decides
            ahead = s - s_ego
            if ahead > 0 and ahead - reach <= range_stop:
                passed = (ahead + reach) / v if v > 0 else math.inf
                if t <= passed + params[C_SLACK]:
                    out[i] = CROSSING
            break
    # the nearest ``leaders`` leaders
    n_lead = int(params[C_LEADERS])
    for _ in range(n_lead):
        best = -1
        for a in range(m):
            if lead_arc[a] < math.inf and (best < 0 or lead_arc[a] < lead_arc[best]):
                best = a
        if best < 0:
            break
        out[agents[best]] = LEADER
        lead_arc[best] = math.inf
    return out
