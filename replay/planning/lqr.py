"""A kinematic bicycle driven by a batch LQR tracker (after PDM-Closed's batch_lqr).

Everything works on a batch of ``B`` vehicles at once (numpy, no Python loop over the
batch; the only loop is over time steps):

- :func:`bicycle_step`: one explicit-Euler step of the kinematic bicycle, reference point
  the **rear axle** (as nuPlan and PDM), with first-order lags on acceleration (0.2 s)
  and steering (0.05 s), steering and acceleration clipped to :class:`TrackerSettings`'
  limits, speed never below 0 (our plans never reverse);
- :func:`lqr_commands`: acceleration and steering-rate commands that track a reference
  trajectory, longitudinal and lateral problems decoupled (below);
- :func:`simulate`: both in closed loop over ``n`` steps;
- :class:`LqrTracker`: the :class:`~replay.planning.tracking.Tracker` ``"lqr"`` (B = 1).

**Reference point.** The toolkit's states are box centres. A vehicle's wheelbase is taken
as :data:`WHEELBASE_SHARE` of its box length (a Chrysler Pacifica, nuPlan's ego: 3.089 m
of 5.176 m, 0.597) and the rear axle half a wheelbase behind the centre (the Pacifica's is
1.461 m behind, half its wheelbase is 1.544 m: symmetric overhangs are 0.08 m off). The
conversion happens once, on the way in (:func:`rear_axle_xy`) and on the way out
(:func:`centre_xy`); every array that holds rear-axle positions says so in its name.
The bicycle's speed is the rear axle's, which is the speed along the heading: the same
as :class:`~replay.planning.tracking.VehicleState`'s ``speed_mps``.

**The controller** (one-step LQR over a ``horizon_steps`` look-ahead, inputs held
constant over it, as nuPlan's and PDM's trackers):

- longitudinal: state (position along the reference, speed), input acceleration; ``N``
  steps ahead the speed is ``v + B_v a`` (``B_v = N dt``) and the distance travelled
  ``N dt v + B_s a`` (``B_s = dt^2 N (N - 1) / 2``, Euler); the cost
  ``q_v (v_N - v_ref)^2 + q_s (s_N - s_ref)^2 + r (N / n)^2 a^2`` against the reference
  ``N`` steps ahead gives
  ``a = (q_v B_v (v_ref - v) + q_s B_s d) / (q_v B_v^2 + q_s B_s^2 + r (N / n)^2)``
  with ``d`` the distance still to go. PDM's tracker has ``q_s = 0`` (speed only): it
  then runs 0.4 m/s above a plan braking at 4 m/s^2 and stops 4 m beyond it, and PDM's
  scorer saw every IDM proposal that stops 1 m behind a standing car collide with it.
  ``q_position = 100`` keeps a stop within 0.6 m of its plan (tests/test_tracker.py);
- **the stop horizon** (our departure from PDM-Closed, which always looks ``n`` = 10
  steps, 1 s, ahead): ``N`` is ``n``, or the number of steps until the reference comes
  to rest (its speed at or below ``stop_speed_mps``) when that is sooner. Holding one
  input over 1 s against a reference that stops within it asks for about the speed over
  1 s, whatever the plan's deceleration: re-planned every 0.1 s, PDM's 4.05 m/s^2
  emergency brake took the vehicle from 1 m/s to below 0.05 m/s in 1.5 s over 0.65 m
  (the plan: 0.25 s, 0.12 m), and nuPlan counts an ego that still moves when another car
  drives into it at fault. Past the reference's stop there is nothing to track, so the
  look-ahead ends there: the target is the reference's stop (its speed and position) at
  its time to rest, and the command the deceleration that reaches it (from 1 m/s the
  vehicle is below 0.05 m/s in 0.5 s over 0.31 m; the rest is the 0.2 s actuator lag).
  The input weight is on the speed change the held input makes over the look-ahead
  (``r a^2 (N / n)^2``: PDM's ``r a^2`` when ``N = n``), so a shorter look-ahead pursues
  the same share of the error (``q_v B_v^2 / (q_v B_v^2 + r (N/n)^2)``: 10/11 with speed
  alone) instead of an ever smaller one as the stop nears;
- lateral: state (lateral error, heading error, steering angle) of the rear axle against
  the reference pose at the current time, input steering rate ``u``; linearised
  (small angles) with the speed profile of the chosen acceleration and the reference's
  curvature ``kappa``::

      e'   = v psi
      psi' = v (delta / L - kappa)
      delta' = u

  PDM multiplies the ``N`` Euler step matrices with ``einsum`` in a loop; the products
  of these upper-triangular steps have a closed form in prefix sums, used here
  (:func:`_lateral_response`; the tests check it against the matrix products). The
  lateral look-ahead stays ``n`` steps; its speed profile is limited to come to rest at
  its end at the latest (the acceleration at least ``-v / ((n - 1) dt)``), so a hard
  brake does not predict the vehicle reversing;
- below :attr:`TrackerSettings.stop_speed_mps` (reference ``n`` steps ahead and vehicle)
  a speed controller brings the vehicle to rest with the steering held: it asks for the
  reference's speed within one step, ``(v_ref - v) / dt`` (the actuator's lag spreads
  that over about 0.3 s), and a standing vehicle behind a standing plan is asked for
  nothing and stands. PDM's proportional controller (gain 0.5 /s) let the vehicle creep:
  from 0.19 m/s it was still above 0.05 m/s after 2.5 s, while nuPlan judges an ego
  above 0.05 m/s as moving (at fault when hit from the front or side).

Past a plan's end the reference continues at the plan's last speed along its last
heading (the :class:`~replay.planning.tracking.Tracker` contract).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol, TypeVar, cast

import numpy as np

from replay.planning.types import Plan

#: Wheelbase as a share of the box length (see the module docstring).
WHEELBASE_SHARE = 0.6
#: The least wheelbase (m): keeps the bicycle's yaw rate finite for tiny boxes.
MIN_WHEELBASE_M = 1.0
#: Below this distance travelled in one step (m), curvature is carried over from the step
#: before (a standing reference has no defined curvature).
MIN_CURVATURE_STEP_M = 1e-3


class StateIndex(IntEnum):
    """Columns of a bicycle state array ``(..., N_STATE)``: rear-axle position (m),
    heading (rad), speed along the heading (m/s), acceleration (m/s^2), front-wheel
    steering angle (rad)."""

    REAR_X = 0
    REAR_Y = 1
    HEADING = 2
    SPEED = 3
    ACCEL = 4
    STEER = 5


N_STATE = len(StateIndex)
# Plain ints for the per-step code (indexing with an IntEnum member costs twice as much).
_X, _Y, _HEADING, _SPEED, _ACCEL, _STEER = (int(i) for i in StateIndex)
#: The state rows in the order simulate unpacks them.
_STATE_ROWS = [_X, _Y, _HEADING, _SPEED, _ACCEL, _STEER]


@dataclass(frozen=True, kw_only=True)
class TrackerSettings:
    """The bicycle's limits and lags and the LQR weights.

    Weights, horizon, lags and the stop speed are PDM-Closed's (tuplan_garage
    ``batch_lqr.py``, ``batch_kinematic_bicycle.py``) except ``q_position`` (PDM: 0);
    the longitudinal look-ahead ending where the reference comes to rest and the stop
    controller's gain ``1 / dt_s`` (PDM: 0.5 /s) are ours (see the module docstring).
    ``max_steer_rad``
    is PDM's pi / 3; ``max_accel_mps2`` / ``max_decel_mps2`` are physical limits of a car
    (PDM leaves acceleration unclipped): 8 m/s^2 is IdmSettings' braking limit.
    """

    dt_s: float = 0.1
    horizon_steps: int = 10
    q_speed: float = 10.0
    q_position: float = 100.0
    r_accel: float = 1.0
    q_lateral_error: float = 1.0
    q_heading_error: float = 10.0
    q_steer: float = 0.0
    r_steer_rate: float = 1.0
    stop_speed_mps: float = 0.2
    accel_lag_s: float = 0.2
    steer_lag_s: float = 0.05
    max_steer_rad: float = math.pi / 3.0
    max_accel_mps2: float = 4.0
    max_decel_mps2: float = 8.0


def wheelbase_m(length_m: np.ndarray | float) -> np.ndarray:
    """Wheelbase (m) from the box length (m), broadcasting."""
    return np.maximum(WHEELBASE_SHARE * np.asarray(length_m, dtype=np.float64), MIN_WHEELBASE_M)


def rear_axle_xy(
    centre_xy: np.ndarray, heading_rad: np.ndarray | float, wheelbase: np.ndarray | float
) -> np.ndarray:
    """Rear-axle positions ``(..., 2)`` of boxes centred at ``centre_xy`` ``(..., 2)``:
    half a wheelbase behind the centre along the heading."""
    h = np.asarray(heading_rad)
    back = 0.5 * np.asarray(wheelbase)
    return centre_xy - np.stack([back * np.cos(h), back * np.sin(h)], axis=-1)


def centre_xy(
    rear_xy: np.ndarray, heading_rad: np.ndarray | float, wheelbase: np.ndarray | float
) -> np.ndarray:
    """Box centres ``(..., 2)`` of rear-axle positions ``rear_xy`` (inverse of
    :func:`rear_axle_xy`)."""
    h = np.asarray(heading_rad)
    ahead = 0.5 * np.asarray(wheelbase)
    return rear_xy + np.stack([ahead * np.cos(h), ahead * np.sin(h)], axis=-1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to ``[-pi, pi)``."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


# ---------------------------------------------------------------------- the bicycle
def bicycle_step(
    states: np.ndarray,
    accel_cmd: np.ndarray,
    steer_rate_cmd: np.ndarray,
    dt_s: float,
    wheelbase: np.ndarray | float,
    settings: TrackerSettings,
) -> np.ndarray:
    """One step of ``dt_s`` of the kinematic bicycle: states ``(B, N_STATE)`` (rear axle)
    under commands ``(B,)``; returns the new states ``(B, N_STATE)``.

    The commands pass first-order lags (``accel_lag_s``, ``steer_lag_s``) and the limits;
    position and heading advance with the speed and steering at the start of the step
    (explicit Euler), speed with the lagged acceleration, never below 0. Headings are
    not wrapped (they stay continuous along a simulation).
    """
    s = settings
    heading = states[:, _HEADING]
    speed = states[:, _SPEED]
    steer = states[:, _STEER]
    accel = states[:, _ACCEL]
    out = np.empty_like(states)
    new_accel = out[:, _ACCEL]
    # (np.minimum / np.maximum: np.clip's wrapper costs more than the work here)
    np.multiply(accel_cmd - accel, dt_s / (dt_s + s.accel_lag_s), out=new_accel)
    new_accel += accel
    np.minimum(
        np.maximum(new_accel, -s.max_decel_mps2, out=new_accel), s.max_accel_mps2, out=new_accel
    )
    new_steer = out[:, _STEER]
    np.multiply(steer_rate_cmd, dt_s * dt_s / (dt_s + s.steer_lag_s), out=new_steer)
    new_steer += steer
    np.minimum(
        np.maximum(new_steer, -s.max_steer_rad, out=new_steer), s.max_steer_rad, out=new_steer
    )

    travel = dt_s * speed
    out[:, _X] = states[:, _X] + travel * np.cos(heading)
    out[:, _Y] = states[:, _Y] + travel * np.sin(heading)
    out[:, _HEADING] = heading + travel * np.tan(steer) / wheelbase
    new_speed = out[:, _SPEED]
    np.multiply(new_accel, dt_s, out=new_speed)
    new_speed += speed
    stops = new_speed < 0.0  # comes to rest within the step: no reversing
    if stops.any():
        new_accel[stops] = -speed[stops] / dt_s
        new_speed[stops] = 0.0
    return out


# ---------------------------------------------------------------------- the reference
@dataclass(frozen=True, eq=False, kw_only=True)
class Reference:  # not slotted: arc_m is cached on the instance
    """Reference trajectories ``(B, R)`` on the tracker's time grid ``0, dt, ...``:
    rear-axle positions ``rear_xy`` ``(B, R, 2)``, heading, speed and curvature
    (1/m, of the rear axle's path)."""

    rear_xy: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    curvature_per_m: np.ndarray

    @functools.cached_property
    def arc_m(self) -> np.ndarray:
        """``(B, R)``: distance travelled along the rear-axle reference (m)."""
        step = np.hypot(*np.moveaxis(np.diff(self.rear_xy, axis=1), -1, 0))
        return np.concatenate([np.zeros((step.shape[0], 1)), np.cumsum(step, axis=1)], axis=1)


def reference_from_centres(
    centre_xy_: np.ndarray,
    heading_rad: np.ndarray,
    speed_mps: np.ndarray,
    wheelbase: np.ndarray,
    curvature_per_m: np.ndarray | None = None,
) -> Reference:
    """A :class:`Reference` from box-centre trajectories ``(B, R, 2)``, ``(B, R)``; the
    curvature, when not given, is the heading's change per metre of rear-axle travel
    between samples (carried over where the reference stands)."""
    rear = rear_axle_xy(centre_xy_, heading_rad, np.asarray(wheelbase)[:, None])
    if curvature_per_m is None:
        curvature_per_m = path_curvature(rear, heading_rad)
    return Reference(
        rear_xy=rear,
        heading_rad=np.asarray(heading_rad, dtype=np.float64),
        speed_mps=np.asarray(speed_mps, dtype=np.float64),
        curvature_per_m=curvature_per_m,
    )


def path_curvature(xy: np.ndarray, heading_rad: np.ndarray) -> np.ndarray:
    """Curvature ``(B, R)`` (1/m) of sampled poses ``(B, R, 2)``, ``(B, R)``: heading change
    over distance to the next sample; the last sample repeats the one before, and steps
    shorter than MIN_CURVATURE_STEP_M take the curvature of the last longer step (0 when
    there is none)."""
    b, r = heading_rad.shape
    if r < 2:
        return np.zeros((b, r))
    ds = np.hypot(*np.moveaxis(np.diff(xy, axis=1), -1, 0))
    dh = wrap_angle(np.diff(heading_rad, axis=1))
    moved = ds >= MIN_CURVATURE_STEP_M
    kappa = np.where(moved, dh / np.where(moved, ds, 1.0), 0.0)
    # carry the last moving step's curvature over standing steps
    last = np.maximum.accumulate(np.where(moved, np.arange(r - 1)[None, :], -1), axis=1)
    rows = np.arange(b)[:, None]
    kappa = np.where(last >= 0, kappa[rows, np.maximum(last, 0)], 0.0)
    return np.concatenate([kappa, kappa[:, -1:]], axis=1)


# ---------------------------------------------------------------------- the controller
@functools.lru_cache(maxsize=8)
def _moment_weights(n: int) -> np.ndarray:
    """Weights ``(n, 5)`` over the look-ahead steps ``j = 0 .. n-1`` whose dot products with
    a curvature window give the moments :func:`_lateral_response` needs: ``1``, ``j``,
    ``c2_j = n-1-j``, ``c1_j = j (n-1-j) + T_j``, ``c0_j = j T_j`` with
    ``T_j = sum_{i=j+1}^{n-1} i``."""
    j = np.arange(n, dtype=np.float64)
    tail = (n - 1) * n / 2.0 - j * (j + 1) / 2.0
    c2 = n - 1 - j
    w = np.stack([np.ones(n), j, c2, j * c2 + tail, j * tail], axis=1)
    w.flags.writeable = False
    return w


@functools.lru_cache(maxsize=8)
def _moment_sums(n: int) -> tuple[float, ...]:
    """``sum j, sum j^2, sum c2, sum c1, sum c0, sum j c2, sum j c1, sum j c0``."""
    w = _moment_weights(n)
    j = w[:, 1]
    return (
        float(j.sum()), float((j * j).sum()),
        float(w[:, 2].sum()), float(w[:, 3].sum()), float(w[:, 4].sum()),
        float(j @ w[:, 2]), float(j @ w[:, 3]), float(j @ w[:, 4]),
    )  # fmt: skip


def curvature_moments(curvature_per_m: np.ndarray, horizon_steps: int) -> np.ndarray:
    """For every start index ``k`` of the reference, the moments ``(B, R, 5)`` of the
    curvature window ``kappa[k : k + n]`` (indices past the end clamped to the last)."""
    r = curvature_per_m.shape[1]
    idx = np.minimum(np.arange(r)[:, None] + np.arange(horizon_steps)[None, :], r - 1)
    return np.asarray(curvature_per_m[:, idx] @ _moment_weights(horizon_steps))


@functools.lru_cache(maxsize=8)
def _response_coefficients(n: int, dt_s: float) -> np.ndarray:
    """``(5, 5)``: rows for the basis ``(v^2, v alpha, alpha^2, v, alpha)``, columns
    ``A01, A02 L, A12 L, B0 L, B1 L`` of :func:`_lateral_response` (``L`` the wheelbase,
    divided out per row afterwards)."""
    sj, sjj, c2, c1, c0, jc2, jc1, jc0 = _moment_sums(n)
    dt2 = dt_s * dt_s
    coef = np.zeros((5, 5))
    coef[3, 0], coef[4, 0] = dt_s * n, dt_s * sj  # sum_i b_i
    coef[0:3, 1] = dt2 * np.array([c2, c1, c0])  # sum_i b_i S^a_i
    coef[3, 2], coef[4, 2] = dt_s * n, dt_s * sj  # S^a_n
    coef[0:3, 3] = dt2 * dt_s * np.array([jc2, jc1, jc0])  # B0
    coef[3, 4], coef[4, 4] = dt2 * sj, dt2 * sjj  # B1
    coef.flags.writeable = False
    return coef


def _lateral_response(
    speed_mps: np.ndarray,
    accel_mps2: np.ndarray,
    moments: np.ndarray,
    dt_s: float,
    wheelbase: np.ndarray | float,
    n: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The lateral error system after ``n`` Euler steps at the speeds
    ``v_i = v_0 + alpha i`` (``alpha = accel dt``) for a constant steering rate ``u``:
    ``x_n = A x_0 + B u + g`` with ``x = (e, psi, delta)``. Returns ``(B, 5)`` the free
    entries ``A01, A02, A12, B0, B1`` (``A`` is otherwise the identity, ``B2 = n dt``)
    and ``(B, 2)`` ``g0, g1`` (``g2 = 0``); ``moments`` ``(B, 5)`` from
    :func:`curvature_moments`.

    With ``a_i = v_i dt / L``, ``b_i = v_i dt``, ``c_i = v_i kappa_i dt`` and exclusive
    prefix sums ``S^a_i = sum_{j<i} a_j`` (likewise ``S^j`` of ``j a_j``, ``S^c`` of
    ``c_j``)::

        delta_i = delta_0 + i dt u
        psi_i   = psi_0 + S^a_i delta_0 + dt S^j_i u - S^c_i
        e_n     = e_0 + sum_i b_i psi_i

    Every sum is a polynomial in ``v_0`` and ``alpha`` whose coefficients are sums over
    ``j`` (:func:`_moment_sums`, :func:`_moment_weights`), so no array over the look-ahead
    is built per step: one matrix product per step. PDM multiplies the ``n`` step
    matrices with ``einsum`` instead; the tests check this form against those products.
    """
    basis = np.empty((speed_mps.shape[0], 5))  # v^2, v alpha, alpha^2, v, alpha
    alpha = basis[:, 4]
    np.multiply(accel_mps2, dt_s, out=alpha)
    basis[:, 3] = speed_mps
    np.multiply(speed_mps, speed_mps, out=basis[:, 0])
    np.multiply(speed_mps, alpha, out=basis[:, 1])
    np.multiply(alpha, alpha, out=basis[:, 2])
    free = basis @ _response_coefficients(n, dt_s)
    free[:, 1:] /= np.reshape(wheelbase, (-1, 1))
    # g0 = -dt^2 (v^2 m2 + v alpha m3 + alpha^2 m4), g1 = -dt (v m0 + alpha m1)
    basis *= moments[:, _MOMENT_ORDER]
    g = basis @ _affine_sum(dt_s)
    return free, g


_QUAD_LEFT = np.array([0, 0, 1])
_QUAD_RIGHT = np.array([0, 1, 1])
#: The moments in the basis' order: v^2 <-> m2, v alpha <-> m3, alpha^2 <-> m4, v <-> m0,
#: alpha <-> m1.
_MOMENT_ORDER = np.array([2, 3, 4, 0, 1])


@functools.lru_cache(maxsize=8)
def _affine_sum(dt_s: float) -> np.ndarray:
    """``(5, 2)``: sums the basis-times-moment products into ``g0, g1``."""
    out = np.zeros((5, 2))
    out[0:3, 0] = -dt_s * dt_s
    out[3:5, 1] = -dt_s
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class TrackingProblem:
    """A reference prepared for the controller: everything that depends on the time
    index only, computed once for all steps, time-major ``(R, B, ...)`` (row ``k`` is
    what step ``k`` reads). Built by :meth:`of`."""

    settings: TrackerSettings
    wheelbase: np.ndarray  # (B,) m
    rear: np.ndarray  # (R, B) complex: reference rear-axle positions x + iy
    unrotate: np.ndarray  # (R, B) complex: exp(-i heading), into the reference's frame
    heading: np.ndarray  # (R, B) rad
    base_accel: np.ndarray  # (R, B): the longitudinal command's reference part
    speed_gain: np.ndarray  # (R, B): how much the command drops per m/s of speed
    position_gain: np.ndarray  # (R, B): ... per m the vehicle is ahead of the reference
    moments: np.ndarray  # (R, B, 5): curvature moments of the look-ahead window
    stopping_ref: np.ndarray  # (R, B) bool: the reference speed ahead is a stop
    v_ref_ahead: np.ndarray  # (R, B) m/s: the reference speed n steps ahead

    @classmethod
    def of(
        cls, reference: Reference, wheelbase: np.ndarray | float, settings: TrackerSettings
    ) -> TrackingProblem:
        s = settings
        n = s.horizon_steps
        b, r = reference.speed_mps.shape
        rows = np.arange(r)
        ahead = np.minimum(rows + n, r - 1)
        v_ahead = reference.speed_mps[:, ahead]  # (B, R)
        # Longitudinal look-ahead m (B, R): n steps, or fewer when the reference comes to
        # rest (speed <= stop_speed_mps) sooner: m = steps to the first such index after k
        # (past the reference's end its last speed holds, hence the repeated last column).
        at_rest = reference.speed_mps <= s.stop_speed_mps
        at_rest = np.concatenate([at_rest, at_rest[:, -1:]], axis=1)
        rest_index = np.where(at_rest, np.arange(r + 1)[None, :], r + n)
        next_rest = np.minimum.accumulate(rest_index[:, ::-1], axis=1)[:, ::-1][:, 1:]
        m = np.clip(next_rest - rows[None, :], 1, n).astype(np.float64)
        target = rows[None, :] + m.astype(np.int64)
        target_row = np.minimum(target, r - 1)
        v_target = np.take_along_axis(reference.speed_mps, target_row, axis=1)
        # a = c_v (v_ref - v) + c_s (to_go), to_go = the reference's travel to m steps
        # ahead (past its end at its last speed, the Tracker contract) minus how far the
        # vehicle is ahead of the reference now minus m dt v; the input weight r is on
        # the speed change the held input makes over the look-ahead (r (m / n)^2: PDM's
        # r a^2 when m = n).
        gain_v = m * s.dt_s
        gain_s = s.dt_s * s.dt_s * m * (m - 1.0) / 2.0
        r_eff = s.r_accel * (m / n) ** 2
        den = s.q_speed * gain_v * gain_v + s.q_position * gain_s * gain_s + r_eff
        c_v, c_s = s.q_speed * gain_v / den, s.q_position * gain_s / den
        arc = reference.arc_m
        beyond = (target - target_row) * s.dt_s * reference.speed_mps[:, -1:]
        travel = np.take_along_axis(arc, target_row, axis=1) + beyond - arc
        base = c_v * v_target + c_s * travel
        heading = reference.heading_rad
        return cls(
            settings=s,
            wheelbase=np.broadcast_to(np.asarray(wheelbase, dtype=np.float64), (b,)),
            rear=np.ascontiguousarray(
                (reference.rear_xy[..., 0] + 1j * reference.rear_xy[..., 1]).T
            ),
            unrotate=np.ascontiguousarray(np.exp(-1j * heading).T),
            heading=np.ascontiguousarray(heading.T),
            base_accel=np.ascontiguousarray(base.T),
            speed_gain=np.ascontiguousarray((c_v + c_s * gain_v).T),
            position_gain=np.ascontiguousarray(c_s.T),
            moments=np.ascontiguousarray(
                np.moveaxis(curvature_moments(reference.curvature_per_m, n), 1, 0)
            ),
            stopping_ref=np.ascontiguousarray((v_ahead <= s.stop_speed_mps).T),
            v_ref_ahead=np.ascontiguousarray(v_ahead.T),
        )

    @property
    def rest_within(self) -> float:
        """``-1 / ((n - 1) dt)``: with ``a >= rest_within * v`` the lateral prediction's
        speeds ``v + a dt i`` stay >= 0 over the look-ahead (its acceleration is limited so)."""
        s = self.settings
        return -1.0 / (max(s.horizon_steps - 1, 1) * s.dt_s)


def lqr_commands(
    states: np.ndarray, problem: TrackingProblem, step: int
) -> tuple[np.ndarray, np.ndarray]:
    """Acceleration (m/s^2) and steering-rate (rad/s) commands ``(B,)`` for the states
    ``(B, N_STATE)`` at time index ``step`` of the reference (see the module docstring;
    past the reference's last index, its last row)."""
    p = problem
    s = p.settings
    n = s.horizon_steps
    k = min(step, p.heading.shape[0] - 1)
    speed = states[:, _SPEED]
    # The rear axle in the reference pose's frame: along (ahead of it) and lateral error.
    rear = states[:, _X] + 1j * states[:, _Y]
    local = (rear - p.rear[k]) * p.unrotate[k]
    # Longitudinal: one-step LQR on speed and position n steps ahead, or at the
    # reference's rest when sooner (TrackingProblem.of).
    accel = p.base_accel[k] - p.speed_gain[k] * speed - p.position_gain[k] * local.real

    # Lateral: error state (e, psi, delta) now, and n steps ahead with u = 0.
    e0 = local.imag
    psi0 = wrap_angle(states[:, _HEADING] - p.heading[k])
    delta0 = states[:, _STEER]
    free, g = _lateral_response(
        speed, np.maximum(accel, speed * p.rest_within), p.moments[k], s.dt_s, p.wheelbase, n
    )
    e_n = e0 + free[:, 0] * psi0 + free[:, 1] * delta0 + g[:, 0]
    psi_n = psi0 + free[:, 2] * delta0 + g[:, 1]  # small: PDM's wrap would not change it
    b0, b1 = free[:, 3], free[:, 4]
    num = s.q_lateral_error * b0 * e_n + s.q_heading_error * b1 * psi_n
    den = s.q_lateral_error * b0 * b0 + s.q_heading_error * b1 * b1 + s.r_steer_rate
    if s.q_steer:
        b2 = n * s.dt_s
        num = num + s.q_steer * b2 * delta0
        den = den + s.q_steer * b2 * b2
    steer_rate = -num / den

    # Near standstill: the reference's speed within one step (the lag smooths it),
    # steering held.
    stopping = p.stopping_ref[k] & (speed <= s.stop_speed_mps)
    if stopping.any():
        accel = np.where(stopping, (p.v_ref_ahead[k] - speed) / s.dt_s, accel)
        steer_rate = np.where(stopping, 0.0, steer_rate)
    return accel, steer_rate


def simulate(
    initial: np.ndarray,
    reference: Reference,
    n_steps: int,
    wheelbase: np.ndarray | float,
    settings: TrackerSettings,
) -> np.ndarray:
    """The bicycle under the LQR tracker from ``initial`` ``(B, N_STATE)`` for ``n_steps``
    steps of ``settings.dt_s`` along ``reference`` (time index 0 = ``initial``'s time):
    states ``(B, n_steps + 1, N_STATE)``."""
    problem = TrackingProblem.of(reference, wheelbase, settings)
    # The per-step work of lqr_commands then bicycle_step, fused: the same operations in
    # the same order (bit for bit the same states, tests/test_lqr_fused.py keeps the
    # two-call loop as the oracle), on state rows (time, state, batch) that need no
    # column slicing, with the moments' reordering done once for all steps: the batch
    # is small (17 proposals), so the step costs its number of numpy calls.
    p, s = problem, settings
    n, dt = s.horizon_steps, s.dt_s
    out = np.empty((n_steps + 1, N_STATE, initial.shape[0]))
    out[0] = initial.T
    coef = _response_coefficients(n, dt)
    affine = _affine_sum(dt)
    wheelbase_b = p.wheelbase
    wheelbase_col = np.reshape(wheelbase_b, (-1, 1))
    moments = p.moments[:, :, _MOMENT_ORDER]
    rest_within = p.rest_within
    accel_share = dt / (dt + s.accel_lag_s)
    steer_share = dt * dt / (dt + s.steer_lag_s)
    last = p.heading.shape[0] - 1
    basis = np.empty((initial.shape[0], 5))  # v^2, v alpha, alpha^2, v, alpha
    for k in range(n_steps):  # time steps only; the batch is vectorised
        r = min(k, last)
        x, y, heading, speed, accel, steer = out[k, _STATE_ROWS]
        # -- lqr_commands
        local = (x + 1j * y - p.rear[r]) * p.unrotate[r]
        accel_cmd = p.base_accel[r] - p.speed_gain[r] * speed - p.position_gain[r] * local.real
        psi0 = wrap_angle(heading - p.heading[r])
        alpha = basis[:, 4]
        np.maximum(accel_cmd, speed * rest_within, out=alpha)
        alpha *= dt
        basis[:, 3] = speed
        np.multiply(speed, speed, out=basis[:, 0])
        np.multiply(speed, alpha, out=basis[:, 1])
        np.multiply(alpha, alpha, out=basis[:, 2])
        free = basis @ coef
        free[:, 1:] /= wheelbase_col
        basis *= moments[r]
        g = basis @ affine
        e_n = local.imag + free[:, 0] * psi0 + free[:, 1] * steer + g[:, 0]
        psi_n = psi0 + free[:, 2] * steer + g[:, 1]
        b0, b1 = free[:, 3], free[:, 4]
        num = s.q_lateral_error * b0 * e_n + s.q_heading_error * b1 * psi_n
        den = s.q_lateral_error * b0 * b0 + s.q_heading_error * b1 * b1 + s.r_steer_rate
        if s.q_steer:
            b2 = n * dt
            num = num + s.q_steer * b2 * steer
            den = den + s.q_steer * b2 * b2
        steer_rate = -num / den
        stopping = p.stopping_ref[r] & (speed <= s.stop_speed_mps)
        if stopping.any():
            accel_cmd = np.where(stopping, (p.v_ref_ahead[r] - speed) / dt, accel_cmd)
            steer_rate = np.where(stopping, 0.0, steer_rate)
        # -- bicycle_step
        new = out[k + 1]
        new_accel = new[_ACCEL]
        np.multiply(accel_cmd - accel, accel_share, out=new_accel)
        new_accel += accel
        np.minimum(
            np.maximum(new_accel, -s.max_decel_mps2, out=new_accel),
            s.max_accel_mps2,
            out=new_accel,
        )
        new_steer = new[_STEER]
        np.multiply(steer_rate, steer_share, out=new_steer)
        new_steer += steer
        np.minimum(
            np.maximum(new_steer, -s.max_steer_rad, out=new_steer), s.max_steer_rad, out=new_steer
        )
        travel = dt * speed
        np.add(x, travel * np.cos(heading), out=new[_X])
        np.add(y, travel * np.sin(heading), out=new[_Y])
        np.add(heading, travel * np.tan(steer) / wheelbase_b, out=new[_HEADING])
        new_speed = new[_SPEED]
        np.multiply(new_accel, dt, out=new_speed)
        new_speed += speed
        stops = new_speed < 0.0  # comes to rest within the step: no reversing
        if stops.any():
            new_accel[stops] = -speed[stops] / dt
            new_speed[stops] = 0.0
    return np.ascontiguousarray(np.transpose(out, (2, 0, 1)))


# ---------------------------------------------------------------------- the Tracker
def _plan_on_grid(plan: Plan, times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plan's centres ``(R, 2)``, headings and speeds ``(R,)`` at ``times_s``: linear
    between its samples; past its end at its last speed along its last heading."""
    t = plan.times_s
    end = float(t[-1])
    at = np.minimum(times_s, end)
    heading = np.unwrap(plan.heading_rad)
    x = np.interp(at, t, plan.xy[:, 0])
    y = np.interp(at, t, plan.xy[:, 1])
    h = np.interp(at, t, heading)
    v = np.interp(at, t, plan.speed_mps)
    beyond = np.maximum(times_s - end, 0.0) * float(plan.speed_mps[-1])
    x = x + beyond * math.cos(float(heading[-1]))
    y = y + beyond * math.sin(float(heading[-1]))
    return np.stack([x, y], axis=1), h, v


class _BoxState(Protocol):
    """What :meth:`LqrTracker.follow` reads of a state: the fields of
    :class:`~replay.planning.tracking.VehicleState`. (tracking.py loads this module to make
    the tracker; importing it back would close an import cycle, so the state is described
    here and copied with ``dataclasses.replace``.)"""

    @property
    def xy(self) -> np.ndarray: ...
    @property
    def heading_rad(self) -> float: ...
    @property
    def speed_mps(self) -> float: ...
    @property
    def accel_mps2(self) -> float: ...
    @property
    def steer_rad(self) -> float: ...
    @property
    def length_m(self) -> float: ...


_State = TypeVar("_State", bound=_BoxState)


class LqrTracker:
    """The tracker ``"lqr"``: the kinematic bicycle under the batch LQR tracker (B = 1),
    simulated at ``settings.dt_s`` (a last, shorter step ends exactly at ``duration_s``)."""

    name = "lqr"

    def __init__(self, settings: TrackerSettings | None = None) -> None:
        self.settings = TrackerSettings() if settings is None else settings

    def follow(self, state: _State, plan: Plan, duration_s: float) -> _State:
        """The state (a :class:`~replay.planning.tracking.VehicleState`) after tracking
        ``plan`` for ``duration_s`` (the :class:`~replay.planning.tracking.Tracker`
        contract); box size kept."""
        s = self.settings
        n_full = math.floor(duration_s / s.dt_s + 1e-9)
        rest = duration_s - n_full * s.dt_s
        grid = np.arange(n_full + s.horizon_steps + 2) * s.dt_s
        xy, heading, speed = _plan_on_grid(plan, grid)
        wheelbase = wheelbase_m(np.array([state.length_m]))
        reference = reference_from_centres(xy[None], heading[None], speed[None], wheelbase)
        initial = np.empty((1, N_STATE))
        initial[0, [StateIndex.REAR_X, StateIndex.REAR_Y]] = rear_axle_xy(
            state.xy, state.heading_rad, wheelbase[0]
        )
        initial[0, StateIndex.HEADING] = state.heading_rad
        initial[0, StateIndex.SPEED] = max(state.speed_mps, 0.0)
        initial[0, StateIndex.ACCEL] = state.accel_mps2
        initial[0, StateIndex.STEER] = state.steer_rad
        states = simulate(initial, reference, n_full, wheelbase, s)[:, -1]
        if rest > 1e-9:  # the last, shorter step, with the commands of the next time index
            accel, steer_rate = lqr_commands(
                states, TrackingProblem.of(reference, wheelbase, s), n_full
            )
            states = bicycle_step(states, accel, steer_rate, rest, wheelbase, s)
        final = states[0]
        moved = dataclasses.replace(
            cast(Any, state),
            xy=centre_xy(
                final[[StateIndex.REAR_X, StateIndex.REAR_Y]],
                final[StateIndex.HEADING],
                wheelbase[0],
            ),
            heading_rad=float(wrap_angle(final[StateIndex.HEADING])),
            speed_mps=float(final[StateIndex.SPEED]),
            accel_mps2=float(final[StateIndex.ACCEL]),
            steer_rad=float(final[StateIndex.STEER]),
        )
        return cast(_State, moved)
