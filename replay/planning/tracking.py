"""Trackers: how the simulated ego follows a plan between two re-plans in closed loop.

The interface every tracker implements (:class:`Tracker`), the state it moves
(:class:`VehicleState`), and the trackers by name (:func:`make_tracker`):

- ``perfect``: the ego is put on the plan's own state ``duration_s`` after its start (no
  vehicle dynamics beyond what the planner itself respects);
- ``lqr``: a kinematic bicycle driven by an LQR controller that tracks the plan
  (:mod:`replay.planning.lqr`).

``VehicleState.xy`` is the box centre, as everywhere else in the toolkit (``EgoState.xy``);
a tracker that models the rear axle converts once, inside, and names the converted value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from replay.planning.errors import PlanningError
from replay.planning.types import Plan

#: Every tracker name, the default first.
TRACKERS: tuple[str, ...] = ("perfect", "lqr")


@dataclass(frozen=True, eq=False, kw_only=True)
class VehicleState:
    """The simulated ego: box centre ``xy`` (2,) m, heading (rad, counter-clockwise from
    +x), speed and acceleration along the heading, front-wheel steering angle, box size.
    ``steer_rad`` and ``accel_mps2`` carry a tracker's actuator state from one call to
    the next (a perfect tracker leaves steering at 0)."""

    xy: np.ndarray  # (2,) float64, m
    heading_rad: float
    speed_mps: float
    accel_mps2: float = 0.0
    steer_rad: float = 0.0
    length_m: float = 4.5
    width_m: float = 1.8

    def __post_init__(self) -> None:
        xy = np.asarray(self.xy, dtype=np.float64)
        if xy.shape != (2,):
            raise ValueError(f"VehicleState.xy: expected shape (2,), got {xy.shape}")
        object.__setattr__(self, "xy", xy)


@runtime_checkable
class Tracker(Protocol):
    """Follows a plan: ``follow(state, plan, duration_s)`` is the state after tracking
    ``plan`` (whose time 0 is ``state``'s time) for ``duration_s`` seconds. ``plan.ok`` is
    True and it has at least two samples; past the plan's end a tracker holds the plan's
    last speed along its last heading."""

    name: str

    def follow(self, state: VehicleState, plan: Plan, duration_s: float) -> VehicleState: ...


class PerfectTracker:
    """The plan's own state ``duration_s`` after its start, linear between its samples."""

    name = "perfect"

    def follow(self, state: VehicleState, plan: Plan, duration_s: float) -> VehicleState:
        t = plan.times_s
        end = float(t[-1])
        at = min(duration_s, end)
        heading = np.unwrap(plan.heading_rad)
        x = float(np.interp(at, t, plan.xy[:, 0]))
        y = float(np.interp(at, t, plan.xy[:, 1]))
        h = float(np.interp(at, t, heading))
        v = float(np.interp(at, t, plan.speed_mps))
        if duration_s > end:  # beyond the plan: hold its last speed and heading
            extra = (duration_s - end) * v
            x += extra * math.cos(h)
            y += extra * math.sin(h)
        accel = float(np.interp(at, t, np.gradient(plan.speed_mps, t)))
        return VehicleState(
            xy=np.array([x, y]),
            heading_rad=h,
            speed_mps=v,
            accel_mps2=accel,
            steer_rad=0.0,
            length_m=state.length_m,
            width_m=state.width_m,
        )


def make_tracker(name: str) -> Tracker:
    """A tracker by name (one of :data:`TRACKERS`)."""
    if name == "perfect":
        return PerfectTracker()
    if name == "lqr":
        from replay.planning.lqr import LqrTracker  # loaded only when asked for

        return LqrTracker()
    raise PlanningError(f"unknown tracker {name!r}; expected one of {', '.join(TRACKERS)}")
