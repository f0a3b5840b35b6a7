"""The Intelligent Driver Model's acceleration, written once for every user.

Treiber, Hennecke, Helbing (Phys. Rev. E 62, 2000)::

    a = a0 * (1 - (v / v0)^delta) - a0 * (s* / s)^2
    s* = s0 + max(0, v T + v (v - v_l) / (2 sqrt(a0 b)))

with ``v`` the follower's speed, ``v0`` its desired speed, ``s`` the bumper-to-bumper gap
to its leader, ``v_l`` the leader's speed (along the follower's path), ``a0`` the
maximum acceleration, ``b`` the comfortable deceleration, ``T`` the time headway, ``s0``
the jam distance and ``delta`` the acceleration exponent.

Vectorised: every argument broadcasts (scalars, ``(K,)`` agents, ``(P, L)`` proposals x
leaders). An infinite gap is the free road (its interaction term is exactly 0). No
clipping and no gap floor: callers differ there (the reactive agents floor the gap and
clip to ``[-b, a0]``, the IDM planner brakes fully on an overlap and clips to its
physical limit), and each says so where it calls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True)
class IdmLaw:
    """IDM parameters; units in the names. ``accel_mps2`` is ``a0``, ``decel_mps2`` is
    ``b`` (comfortable), ``headway_s`` is ``T``, ``min_gap_m`` is ``s0``, ``exponent`` is
    ``delta``."""

    accel_mps2: float
    decel_mps2: float
    headway_s: float
    min_gap_m: float
    exponent: float

    @property
    def braking_scale_mps2(self) -> float:
        """``2 sqrt(a0 b)``, the divisor of the approach term of ``s*``."""
        return 2.0 * math.sqrt(self.accel_mps2 * self.decel_mps2)


Values = np.ndarray | float


def free_road_acceleration(speed_mps: Values, desired_mps: Values, law: IdmLaw) -> Values:
    """``a0 (1 - (v / v0)^delta)``: the acceleration with no leader (m/s²). No conversion:
    a scalar stays a scalar (the planners' per-step arithmetic on one ego)."""
    return law.accel_mps2 * (1.0 - (speed_mps / desired_mps) ** law.exponent)


def desired_gap_m(speed_mps: Values, lead_speed_mps: Values, law: IdmLaw) -> Values:
    """``s* = s0 + max(0, v T + v (v - v_l) / (2 sqrt(a0 b)))`` (m)."""
    v = speed_mps
    approach = v * law.headway_s + v * (v - lead_speed_mps) / law.braking_scale_mps2
    return law.min_gap_m + np.maximum(0.0, approach)


def idm_acceleration(
    speed_mps: Values,
    desired_mps: Values,
    gap_m: Values,
    lead_speed_mps: Values,
    law: IdmLaw,
) -> np.ndarray:
    """The IDM acceleration (m/s²), unclipped, broadcast over the arguments.

    ``gap_m``: bumper-to-bumper gap to the leader (inf: none, which gives the free-road
    acceleration exactly; 0 gives -inf; NaN stays NaN); ``desired_mps`` must be positive.
    """
    free = free_road_acceleration(speed_mps, desired_mps, law)
    s_star = desired_gap_m(speed_mps, lead_speed_mps, law)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(free - law.accel_mps2 * (s_star / gap_m) ** 2)
