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

from replay.planning.types import AgentForecasts, EgoState, Plan
from risk.hindsight import boxes_overlap

DEFAULT_TOLERANCE_M = 0.5
#: The part of a plan that is executed before the next plan replaces it, and then some:
#: ``changed_1s`` compares the plans over their first second only.
EXECUTED_S = 1.0
#: A plan is *unsafe* when it comes within this time-to-collision of an agent the filter
#: dropped (docs/planners.md: nuPlan's bound is 0.95 s; 1 s is the round value above it).
UNSAFE_TTC_S = 1.0
#: Steps of the time-to-collision look-ahead within UNSAFE_TTC_S.
TTC_STEPS = 10


@dataclass(frozen=True)
class PlanChange:
    """``changed``: True / False, or None when both plans failed (not comparable: never
    counted as unchanged). ``max_shift_m``: largest displacement at equal times over the
    common horizon (NaN unless both plans succeeded). ``why``: the first reason found
    ("" when unchanged)."""

    changed: bool | None
    max_shift_m: float
    why: str


def max_shift_m(reference: Plan, other: Plan, *, until_s: float | None = None) -> float:
    """Largest distance (m) between the two trajectories at equal times over their common
    horizon (up to ``until_s`` from the start when given); ``other`` is interpolated
    linearly onto ``reference``'s times there."""
    t_ref, t_oth = reference.times_s, other.times_s
    if t_ref.size == 0 or t_oth.size == 0:
        return float("nan")
    end = min(float(t_ref[-1]), float(t_oth[-1]))
    if until_s is not None:
        end = min(end, float(t_ref[0]) + until_s)
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


def changed_within(
    reference: Plan,
    other: Plan,
    *,
    until_s: float = EXECUTED_S,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
) -> bool | None:
    """Whether the two plans differ by more than ``tolerance_m`` within their first
    ``until_s`` (the executed part); True when exactly one of them failed, None when both
    did."""  # fmt: skip
    if not reference.ok and not other.ok:
        return None
    if reference.ok != other.ok:
        return True
    return bool(max_shift_m(reference, other, until_s=until_s) > tolerance_m)


def conflicts(
    plan: Plan,
    agents: AgentForecasts,
    ego: EgoState,
    *,
    ttc_s: float = UNSAFE_TTC_S,
) -> np.ndarray:
    """``(K,)`` float: for each agent, the first plan time (s) at which the planned ego box
    overlaps the agent's forecast box, or comes within a time-to-collision of ``ttc_s``
    of it; ``inf`` where it never does (and for every agent of a failed plan).

    Time-to-collision at a plan time: both boxes carried on at their velocities then
    (the plan's, and the forecast's finite differences), checked at ``TTC_STEPS`` steps
    up to ``ttc_s``. Vectorised over agents, plan times and look-ahead steps."""
    k = agents.n
    first = np.full(k, np.inf)
    if not plan.ok or k == 0 or plan.times_s.size == 0:
        return first
    times = plan.times_s
    moved = agents.on_times(times)  # (K, T) on the plan's own times
    dt = np.diff(times) if times.size > 1 else np.ones(1)
    ego_v = np.diff(plan.xy, axis=0) / dt[:, None] if times.size > 1 else np.zeros((1, 2))
    ego_v = np.vstack([ego_v, ego_v[-1:]])  # (T, 2)
    ag_v = np.diff(moved.xy, axis=1) / dt[None, :, None] if times.size > 1 else np.zeros((k, 1, 2))
    ag_v = np.concatenate([ag_v, ag_v[:, -1:]], axis=1)  # (K, T, 2)
    ahead = np.linspace(0.0, ttc_s, TTC_STEPS + 1)  # (Q,) look-ahead, 0 = now
    ex = plan.xy[None, :, None, 0] + ego_v[None, :, None, 0] * ahead  # (1, T, Q)
    ey = plan.xy[None, :, None, 1] + ego_v[None, :, None, 1] * ahead
    ax = moved.xy[:, :, None, 0] + ag_v[:, :, None, 0] * ahead  # (K, T, Q)
    ay = moved.xy[:, :, None, 1] + ag_v[:, :, None, 1] * ahead
    overlap = boxes_overlap(
        ex, ey, plan.heading_rad[None, :, None], np.asarray(ego.length_m),
        np.asarray(ego.width_m), ax, ay, moved.heading_rad[:, :, None],
        agents.length_m[:, None, None], agents.width_m[:, None, None],
    )  # fmt: skip
    touch = np.asarray(np.asarray(overlap).any(axis=2), dtype=bool)  # (K, T)
    hit = touch.any(axis=1)
    first[hit] = times[np.argmax(touch[hit], axis=1)]
    return first


@dataclass(frozen=True)
class SafetyVerdict:
    """``unsafe``: the filtered plan collides with, or comes within ``UNSAFE_TTC_S`` of,
    an agent the filter dropped, where the all-agents plan does not (None when the
    filtered plan failed: there is nothing to execute). ``agent_id``: that agent (the
    earliest such conflict), -1 when none."""

    unsafe: bool | None
    agent_id: int


def safety_verdict(
    filtered: Plan,
    agents: AgentForecasts,
    kept: np.ndarray,
    ego: EgoState,
    *,
    reference_conflicts: np.ndarray,
    ttc_s: float = UNSAFE_TTC_S,
) -> SafetyVerdict:
    """The filtered plan checked against *all* ``agents`` (the dropped ones included,
    with the same forecasts). ``kept`` (K,) bool: the agents the filter kept.
    ``reference_conflicts``: :func:`conflicts` of the all-agents plan (computed once per
    frame for every filter)."""
    if not filtered.ok:
        return SafetyVerdict(None, -1)
    mine = conflicts(filtered, agents, ego, ttc_s=ttc_s)
    new = np.isfinite(mine) & ~np.asarray(kept, dtype=bool) & ~np.isfinite(reference_conflicts)
    if not new.any():
        return SafetyVerdict(False, -1)
    worst = np.flatnonzero(new)[np.argmin(mine[new])]
    return SafetyVerdict(True, int(agents.ids[worst]))
