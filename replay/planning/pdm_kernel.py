"""``pdm``'s per-time-step loops compiled with numba: the IDM proposals
(:func:`idm_rollout`) and the LQR tracker driving the kinematic bicycle
(:func:`simulate`, the twin of :func:`replay.planning.lqr.simulate`).

Why: both loops run over 50 time steps on arrays of 15-17 proposals and a handful of
leaders, so numpy's per-call overhead, not the arithmetic, set their cost (about 5 ms of a
10 ms plan). Each kernel does the numpy form's operations in the same order, element by
element; the numpy forms stay as the oracles (``PdmPlanner(compiled=False)``,
:func:`replay.planning.lqr.simulate`) and the tests compare them (tests/test_pdm_kernel.py).
The results agree to rounding: numpy's SIMD ``sin``/``cos``/``tan``/``pow`` and its BLAS
matrix products may round the last bit another way than the C library and the loops here.

Compiled as the risk kernel is (:mod:`risk.kernel_jit`: ``@njit(cache=True)``, numpy's
error model, the same per-user cache folder), so a fresh process, a pool worker or a Ray
worker loads the compiled code from the cache instead of compiling it (about 5 s cold).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from replay.planning import lqr
from risk.kernel_jit import _jit


class IdmConstants(Protocol):
    """What :func:`idm_rollout` reads of :class:`replay.planning.pdm.PdmSettings`
    (described here: importing pdm back would close an import cycle)."""

    @property
    def idm_accel_mps2(self) -> float: ...
    @property
    def idm_decel_mps2(self) -> float: ...
    @property
    def idm_exponent(self) -> float: ...
    @property
    def idm_min_gap_m(self) -> float: ...
    @property
    def idm_headway_s(self) -> float: ...
    @property
    def leader_update_steps(self) -> int: ...


# ---------------------------------------------------------------------- IDM proposals
@_jit
def _idm_loop(
    n_t: int,
    s0: float,
    v0: float,
    inv_target: np.ndarray,
    corridor: np.ndarray,
    arc_t: np.ndarray,
    back_t: np.ndarray,
    speed_t: np.ndarray,
    any_t: np.ndarray,
    has_leaders: bool,
    every: int,
    dt: float,
    a_max: float,
    b_max: float,
    exponent: float,
    min_gap: float,
    headway: float,
    sqrt_ab: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n_p = inv_target.shape[0]
    n_l = arc_t.shape[1]
    s = np.empty((n_t, n_p))
    v = np.empty((n_t, n_p))
    a_free_t = np.zeros((n_t, n_p))
    a_lead_t = np.zeros((n_t, n_p))
    lead_t = np.zeros((n_t, n_p), dtype=np.int64)
    s[0, :] = s0
    v[0, :] = v0
    held_back = np.full(n_p, np.inf)
    held_speed = np.zeros(n_p)
    held_row = np.zeros(n_p, dtype=np.int64)
    a_free = np.empty(n_p)
    accel = np.empty(n_p)
    for k in range(n_t - 1):
        for p in range(n_p):
            a_free[p] = a_max - a_max * (v[k, p] * inv_target[p]) ** exponent
            accel[p] = a_free[p]
        if has_leaders:
            i = k // every
            if k % every == 0:
                if any_t[i]:
                    for p in range(n_p):  # the nearest rear ahead in the corridor (first)
                        best = np.inf
                        row = 0
                        for m in range(n_l):
                            value = np.inf
                            if corridor[i, p, m] and arc_t[i, m] > s[k, p]:
                                value = back_t[i, m]
                            if value < best:
                                best = value
                                row = m
                        held_row[p] = row
                        held_back[p] = best
                        held_speed[p] = speed_t[i, row]
                else:
                    held_back[:] = np.inf
            finite = False
            for p in range(n_p):
                if np.isfinite(held_back[p]):
                    finite = True
            if finite:
                for p in range(n_p):
                    vk = v[k, p]
                    gap = held_back[p] - s[k, p]
                    s_star = min_gap + vk * (headway + (vk - held_speed[p]) / sqrt_ab)
                    ratio = s_star / max(gap, min_gap)
                    accel[p] = a_free[p] - a_max * (ratio * ratio)
                    a_free_t[k, p] = a_free[p]
                    a_lead_t[k, p] = accel[p]
                    lead_t[k, p] = held_row[p]
        for p in range(n_p):
            a = min(max(accel[p], -b_max), a_max)
            vk = v[k, p]
            sk = s[k, p]
            v_next = vk + a * dt
            if v_next < 0.0:  # stops within the step: no reversing
                s[k + 1, p] = sk + vk * vk / (2.0 * -a)
                v[k + 1, p] = 0.0
            else:
                s[k + 1, p] = sk + (vk + 0.5 * dt * a) * dt
                v[k + 1, p] = v_next
    return s, v, a_free_t, a_lead_t, lead_t


def idm_rollout(
    n_t: int,
    s0: float,
    v0: float,
    target_mps: np.ndarray,
    leaders: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
    settings: IdmConstants,
    dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """IDM along every proposal ``(P,)`` from arc ``s0`` at speed ``v0`` over ``n_t``
    times: arc and speed ``(n_t, P)``, and per step the free-road and with-leader
    accelerations ``(n_t, P)`` and the held leader's row ``(n_t, P)`` (zeros at steps
    without any held leader), as the numpy loop of ``PdmPlanner._proposals``.
    ``leaders``: ``corridor`` ``(S, P, L)`` bool, the leaders' arcs, rears (less the ego's
    half length) and speeds along the path ``(S, L)`` at the search steps; None: none."""
    p = settings
    n_p = target_mps.shape[0]
    if leaders is None:
        corridor = np.zeros((1, n_p, 0), dtype=np.bool_)
        arc_t = back_t = speed_t = np.zeros((1, 0))
    else:
        corridor, arc_t, back_t, speed_t = leaders
    any_t = np.ascontiguousarray(corridor.any(axis=(1, 2)))
    return _idm_loop(
        int(n_t), float(s0), float(v0), 1.0 / target_mps,
        np.ascontiguousarray(corridor), np.ascontiguousarray(arc_t),
        np.ascontiguousarray(back_t), np.ascontiguousarray(speed_t), any_t,
        leaders is not None, int(p.leader_update_steps), float(dt),
        float(p.idm_accel_mps2), float(p.idm_decel_mps2), float(p.idm_exponent),
        float(p.idm_min_gap_m), float(p.idm_headway_s),
        2.0 * math.sqrt(p.idm_accel_mps2 * p.idm_decel_mps2),
    )  # fmt: skip


# ---------------------------------------------------------------------- LQR + bicycle
@_jit
def _wrap(a: float) -> float:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@_jit
def _tracking_loop(
    out: np.ndarray,
    rear: np.ndarray,
    unrotate: np.ndarray,
    heading_ref: np.ndarray,
    base_accel: np.ndarray,
    speed_gain: np.ndarray,
    position_gain: np.ndarray,
    moments: np.ndarray,
    stopping_ref: np.ndarray,
    v_ref_ahead: np.ndarray,
    wheelbase: np.ndarray,
    coef: np.ndarray,
    affine: np.ndarray,
    gains: np.ndarray,
) -> None:
    """``out`` ``(n + 1, N_STATE, B)``, row 0 the initial states, filled in place; the
    problem's rows time-major ``(R, B, ...)``; ``gains``: the scalars in the order
    :func:`simulate` packs them."""
    rest_within, dt = gains[0], gains[2]
    q_lat, q_head, r_steer, q_steer, b2 = gains[3], gains[4], gains[5], gains[6], gains[7]
    stop_speed = gains[8]
    accel_share, steer_share = gains[10], gains[11]
    max_decel, max_accel, max_steer = gains[12], gains[13], gains[14]
    n_steps = out.shape[0] - 1
    n_b = out.shape[2]
    last = heading_ref.shape[0] - 1
    basis = np.empty(5)
    free = np.empty(5)
    for k in range(n_steps):
        r = min(k, last)
        for b in range(n_b):
            x, y = out[k, 0, b], out[k, 1, b]
            heading, speed = out[k, 2, b], out[k, 3, b]
            accel, steer = out[k, 4, b], out[k, 5, b]
            # -- the commands (lqr_commands)
            local = (complex(x, y) - rear[r, b]) * unrotate[r, b]
            accel_cmd = (
                base_accel[r, b] - speed_gain[r, b] * speed - position_gain[r, b] * local.real
            )
            psi0 = _wrap(heading - heading_ref[r, b])
            alpha = max(accel_cmd, speed * rest_within) * dt
            basis[0] = speed * speed
            basis[1] = speed * alpha
            basis[2] = alpha * alpha
            basis[3] = speed
            basis[4] = alpha
            for j in range(5):
                total = 0.0
                for i in range(5):
                    total += basis[i] * coef[i, j]
                free[j] = total
            for j in range(1, 5):
                free[j] /= wheelbase[b]
            g0 = 0.0
            g1 = 0.0
            for i in range(5):
                basis[i] *= moments[r, b, i]
                g0 += basis[i] * affine[i, 0]
                g1 += basis[i] * affine[i, 1]
            e_n = local.imag + free[0] * psi0 + free[1] * steer + g0
            psi_n = psi0 + free[2] * steer + g1
            num = q_lat * free[3] * e_n + q_head * free[4] * psi_n
            den = q_lat * free[3] * free[3] + q_head * free[4] * free[4] + r_steer
            if q_steer != 0.0:
                num = num + q_steer * b2 * steer
                den = den + q_steer * b2 * b2
            steer_rate = -num / den
            if stopping_ref[r, b] and speed <= stop_speed:
                accel_cmd = (v_ref_ahead[r, b] - speed) / dt
                steer_rate = 0.0
            # -- the bicycle (bicycle_step)
            new_accel = (accel_cmd - accel) * accel_share
            new_accel += accel
            new_accel = min(max(new_accel, -max_decel), max_accel)
            new_steer = steer_rate * steer_share
            new_steer += steer
            new_steer = min(max(new_steer, -max_steer), max_steer)
            travel = dt * speed
            out[k + 1, 0, b] = x + travel * math.cos(heading)
            out[k + 1, 1, b] = y + travel * math.sin(heading)
            out[k + 1, 2, b] = heading + travel * math.tan(steer) / wheelbase[b]
            new_speed = new_accel * dt
            new_speed += speed
            if new_speed < 0.0:  # comes to rest within the step: no reversing
                new_accel = -speed / dt
                new_speed = 0.0
            out[k + 1, 3, b] = new_speed
            out[k + 1, 4, b] = new_accel
            out[k + 1, 5, b] = new_steer


def simulate(
    initial: np.ndarray,
    reference: lqr.Reference,
    n_steps: int,
    wheelbase: np.ndarray | float,
    settings: lqr.TrackerSettings,
) -> np.ndarray:
    """:func:`replay.planning.lqr.simulate` compiled: the bicycle under the LQR tracker
    from ``initial`` ``(B, N_STATE)`` for ``n_steps`` steps along ``reference``; states
    ``(B, n_steps + 1, N_STATE)``."""
    p = lqr.TrackingProblem.of(reference, wheelbase, settings)
    s = settings
    n, dt = s.horizon_steps, s.dt_s
    out = np.empty((n_steps + 1, lqr.N_STATE, initial.shape[0]))
    out[0] = initial.T
    gains = np.array(
        [
            p.rest_within, 0.0, dt,
            s.q_lateral_error, s.q_heading_error, s.r_steer_rate, s.q_steer, n * dt,
            s.stop_speed_mps, 0.0,
            dt / (dt + s.accel_lag_s), dt * dt / (dt + s.steer_lag_s),
            s.max_decel_mps2, s.max_accel_mps2, s.max_steer_rad,
        ],
        dtype=np.float64,
    )  # fmt: skip
    _tracking_loop(
        out,
        p.rear,
        p.unrotate,
        p.heading,
        p.base_accel,
        p.speed_gain,
        p.position_gain,
        np.ascontiguousarray(p.moments[:, :, lqr._MOMENT_ORDER]),
        p.stopping_ref,
        p.v_ref_ahead,
        np.array(p.wheelbase, dtype=np.float64),  # (a writable copy: one compiled type)
        lqr._response_coefficients(n, dt),
        lqr._affine_sum(dt),
        gains,
    )
    return np.ascontiguousarray(np.transpose(out, (2, 0, 1)))


# ---------------------------------------------------------------------- the centreline
@_jit
def _project(
    points: np.ndarray, xy: np.ndarray, arc_m: np.ndarray, segment_heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = points.shape[0]
    n_seg = xy.shape[0] - 1
    abx = np.empty(n_seg)
    aby = np.empty(n_seg)
    inv2 = np.empty(n_seg)
    seg_len = np.empty(n_seg)
    for j in range(n_seg):
        abx[j] = xy[j + 1, 0] - xy[j, 0]
        aby[j] = xy[j + 1, 1] - xy[j, 1]
        len2 = abx[j] * abx[j] + aby[j] * aby[j]
        inv2[j] = 1.0 / len2 if len2 > 0 else 0.0
        seg_len[j] = np.sqrt(len2)
    arc = np.empty(n)
    lateral = np.empty(n)
    heading = np.empty(n)
    ax = np.ascontiguousarray(xy[:-1, 0])
    ay = np.ascontiguousarray(xy[:-1, 1])
    d2 = np.empty(n_seg)
    along = np.empty(n_seg)
    for i in range(n):
        px, py = points[i, 0], points[i, 1]
        for j in range(n_seg):  # every segment (a loop without branches: vectorised)
            rx = px - ax[j]
            ry = py - ay[j]
            t = min(max((rx * abx[j] + ry * aby[j]) * inv2[j], 0.0), 1.0)
            rx -= t * abx[j]
            ry -= t * aby[j]
            d2[j] = rx * rx + ry * ry
            along[j] = t
        best = 0  # the nearest segment, the first of equals
        best_d2 = d2[0]
        for j in range(1, n_seg):
            if d2[j] < best_d2:
                best_d2 = d2[j]
                best = j
        best_t = along[best]
        a = arc_m[best] + best_t * seg_len[best]
        # the segment the arc length falls in (searchsorted right, less one, clipped)
        seg = min(max(np.searchsorted(arc_m, a, side="right") - 1, 0), n_seg - 1)
        h = segment_heading[seg]
        cross = math.cos(h) * (py - xy[seg, 1]) - math.sin(h) * (px - xy[seg, 0])
        arc[i] = a
        lateral[i] = np.sqrt(best_d2) if cross >= 0.0 else -np.sqrt(best_d2)
        heading[i] = h
    return arc, lateral, heading


def project(
    points: np.ndarray, xy: np.ndarray, arc_m: np.ndarray, segment_heading: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arc length, signed lateral offset (+ left) and the path's heading ``(N,)`` of
    points ``(N, 2)`` on the polyline ``xy`` ``(V, 2)`` (arc lengths ``arc_m``, segment
    headings ``(V - 1,)``): the compiled ``_Centreline.project`` of
    :mod:`replay.planning.pdm` (the nearest point of :func:`risk.geometry.project_points`,
    the first of equally near ones)."""
    return _project(np.ascontiguousarray(points, dtype=np.float64), xy, arc_m, segment_heading)


# ---------------------------------------------------------------------- the scorer's boxes
@_jit
def _candidate_pairs(
    sim_x: np.ndarray,
    sim_y: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    look_s: np.ndarray,
    look: np.ndarray,
    agent_xy: np.ndarray,
    reach: np.ndarray,
    last: np.ndarray,
) -> np.ndarray:
    n_p, n_t = heading.shape
    n_d = look.shape[0]
    n_k = agent_xy.shape[0]
    out = np.zeros((n_p, n_t, n_d, n_k), dtype=np.bool_)
    for p in range(n_p):
        for t in range(n_t):
            c, s = math.cos(heading[p, t]), math.sin(heading[p, t])
            for d in range(n_d):
                shift = speed[p, t] * look_s[d]
                cx = sim_x[p, t] + shift * c
                cy = sim_y[p, t] + shift * s
                ta = t + look[d]
                for k in range(n_k):
                    if ta > last[k]:
                        continue
                    dx = cx - agent_xy[k, ta, 0]
                    dy = cy - agent_xy[k, ta, 1]
                    out[p, t, d, k] = dx * dx + dy * dy <= reach[k] * reach[k]
    return out


def candidates(
    sim_xy: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    look: np.ndarray,
    dt: float,
    agent_xy: np.ndarray,
    reach: np.ndarray,
    last: np.ndarray,
) -> np.ndarray:
    """``(P, T, D, K)``: the compiled ``_candidates`` of :mod:`replay.planning.pdm` (its
    bounding-circle test, without the coarse pre-test, which only saves numpy work):
    the ego's box centre ``sim_xy`` ``(P, T, 2)`` moved ahead by ``speed`` times look-ahead
    ``look * dt`` along ``heading`` ``(P, T)``, against agent ``k``'s centre ``agent_xy``
    ``(K, T, 2)`` at ``t + look`` up to its ``last`` ``(K,)`` index, within ``reach``
    ``(K,)`` (the sum of the two half diagonals)."""
    return _candidate_pairs(
        np.ascontiguousarray(sim_xy[..., 0]), np.ascontiguousarray(sim_xy[..., 1]),
        np.ascontiguousarray(heading), np.ascontiguousarray(speed), look * dt,
        np.ascontiguousarray(look, dtype=np.int64), np.ascontiguousarray(agent_xy),
        np.ascontiguousarray(reach, dtype=np.float64),
        np.ascontiguousarray(last, dtype=np.int64),
    )  # fmt: skip


@_jit
def _box_contacts(
    cand: np.ndarray,
    sim_x: np.ndarray,
    sim_y: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    look_s: np.ndarray,
    look: np.ndarray,
    ego_length: float,
    ego_width: float,
    agent_xy: np.ndarray,
    agent_heading: np.ndarray,
    agent_length: np.ndarray,
    agent_width: np.ndarray,
    touch: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n_p, n_t, n_d, n_k = cand.shape
    n = 0
    for p in range(n_p):
        for t in range(n_t):
            for d in range(n_d):
                for k in range(n_k):
                    if cand[p, t, d, k]:
                        n += 1
    ip = np.empty(n, np.int64)
    it = np.empty(n, np.int64)
    idd = np.empty(n, np.int64)
    ik = np.empty(n, np.int64)
    ta_out = np.empty(n, np.int64)
    x_out = np.empty(n)
    y_out = np.empty(n)
    hla, hwa = ego_length / 2.0, ego_width / 2.0
    m = 0
    for p in range(n_p):
        for t in range(n_t):
            h = heading[p, t]
            ca, sa = math.cos(h), math.sin(h)
            for d in range(n_d):
                shift = look_s[d] * speed[p, t]
                cx = sim_x[p, t] + shift * ca
                cy = sim_y[p, t] + shift * sa
                ta = t + look[d]
                for k in range(n_k):
                    if not cand[p, t, d, k]:
                        continue
                    # the separating-axis test of risk.boxes.boxes_overlap, term by term
                    dx = agent_xy[k, ta, 0] - cx
                    dy = agent_xy[k, ta, 1] - cy
                    hb = agent_heading[k, ta]
                    cb, sb = math.cos(hb), math.sin(hb)
                    hlb, hwb = agent_length[k] / 2.0, agent_width[k] / 2.0
                    uu = abs(ca * cb + sa * sb)
                    uv = abs(-ca * sb + sa * cb)
                    if (
                        abs(dx * ca + dy * sa) <= hla + hlb * uu + hwb * uv + touch
                        and abs(-dx * sa + dy * ca) <= hwa + hlb * uv + hwb * uu + touch
                        and abs(dx * cb + dy * sb) <= hlb + hla * uu + hwa * uv + touch
                        and abs(-dx * sb + dy * cb) <= hwb + hla * uv + hwa * uu + touch
                    ):
                        ip[m], it[m], idd[m], ik[m], ta_out[m] = p, t, d, k, ta
                        x_out[m], y_out[m] = cx, cy
                        m += 1
    return ip[:m], it[:m], idd[:m], ik[:m], ta_out[:m], x_out[:m], y_out[:m]


def box_contacts(
    cand: np.ndarray,
    sim_xy: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    look: np.ndarray,
    dt: float,
    ego_length_m: float,
    ego_width_m: float,
    agent_xy: np.ndarray,
    agent_heading: np.ndarray,
    agent_length_m: np.ndarray,
    agent_width_m: np.ndarray,
    touch_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled box tests of ``contacts`` (:mod:`replay.planning.pdm`): of the
    candidate pairs ``cand`` ``(P, T, D, K)``, in their C order, those whose boxes overlap:
    proposal, step, look-ahead and agent indices, the agent's step, and the moved ego
    box's centre."""
    return _box_contacts(
        np.ascontiguousarray(cand), np.ascontiguousarray(sim_xy[..., 0]),
        np.ascontiguousarray(sim_xy[..., 1]), np.ascontiguousarray(heading),
        np.ascontiguousarray(speed), look * dt, np.ascontiguousarray(look, dtype=np.int64),
        float(ego_length_m), float(ego_width_m), np.ascontiguousarray(agent_xy),
        np.ascontiguousarray(agent_heading), np.ascontiguousarray(agent_length_m, np.float64),
        np.ascontiguousarray(agent_width_m, np.float64), float(touch_m),
    )  # fmt: skip
