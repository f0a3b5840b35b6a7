"""Did a plan change? One rule for ``replay plan``'s ``changed`` column and for the
planner truth of issue 28 ("the agent whose removal changes the plan").

Tolerance: 0.5 m of displacement at equal times. It is below half the gap between a car's
side and its lane's edge (a 1.8 m car in a 3.5 m lane has 0.85 m each side), so a plan
that moves by more than the tolerance has moved the car noticeably within its lane or
across it; and it is above what the planners' own discretisation produces between two
plans of the same situation (fiss-planner samples target speeds 1-2 m/s apart and end
times 0.5 s apart, so a genuinely different choice shifts the end of a 5 s plan by metres,
not centimetres). Decisions count whatever the distance: stop versus go, the end lane,
and success versus failure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from replay.planning.types import Plan

DEFAULT_TOLERANCE_M = 0.5


@dataclass(frozen=True)
class PlanChange:
    """``changed``: True / False, or None when both plans failed (not comparable: never
    counted as unchanged). ``max_shift_m``: largest displacement at equal times over the
    common horizon (NaN unless both plans succeeded). ``why``: the first reason found
    ("" when unchanged)."""

    changed: bool | None
    max_shift_m: float
    why: str


def max_shift_m(reference: Plan, other: Plan) -> float:
    """Largest distance (m) between the two trajectories at equal times over their common
    horizon; ``other`` is interpolated linearly onto ``reference``'s times there."""
    t_ref, t_oth = reference.times_s, other.times_s
    if t_ref.size == 0 or t_oth.size == 0:
        return float("nan")
    end = min(float(t_ref[-1]), float(t_oth[-1]))
    start = max(float(t_ref[0]), float(t_oth[0]))
    keep = (t_ref >= start - 1e-9) & (t_ref <= end + 1e-9)
    if not keep.any():
        return float("nan")
    t = t_ref[keep]
    same_grid = t_oth.shape == t_ref.shape and np.allclose(t_oth, t_ref)
    if same_grid:
        ox, oy = other.xy[keep, 0], other.xy[keep, 1]
    else:
        ox, oy = np.interp(t, t_oth, other.xy[:, 0]), np.interp(t, t_oth, other.xy[:, 1])
    dx, dy = reference.xy[keep, 0] - ox, reference.xy[keep, 1] - oy
    return float(np.sqrt(dx * dx + dy * dy).max())


def compare_plans(
    reference: Plan, other: Plan, *, tolerance_m: float = DEFAULT_TOLERANCE_M
) -> PlanChange:
    """Whether ``other`` differs from ``reference`` (see the module's rule)."""
    if not reference.ok and not other.ok:
        return PlanChange(None, float("nan"), "both plans failed")
    if reference.ok != other.ok:
        what = "the reference plan failed" if not reference.ok else "the other plan failed"
        return PlanChange(True, float("nan"), f"success: {what}")
    shift = max_shift_m(reference, other)
    if reference.stops != other.stops:
        return PlanChange(True, shift, "stop/go")
    if reference.lane != other.lane:
        return PlanChange(True, shift, f"lane {reference.lane} -> {other.lane}")
    if shift > tolerance_m:
        return PlanChange(True, shift, f"shift {shift:.2f} m > {tolerance_m:g} m")
    return PlanChange(False, shift, "")
