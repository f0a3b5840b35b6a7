"""Which agents really mattered to a planner: plan with all agents, then with all but one.

An agent is *planner-important* when removing it alone changes the plan beyond the
tolerance of :func:`replay.planning.compare.compare_plans` (Waymo's CausalAgents idea:
an agent whose removal changes the ego's behaviour). The counterfactual plan is skipped
only for the agents the planner itself says provably cannot change its plan
(``Planner.may_matter`` False; each planner documents why): they are labelled
unimportant, and counted as skipped.

Also the ego's *target speed* for replayed scenes, shared by every planner caller.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from replay.planning.compare import DEFAULT_TOLERANCE_M, compare_plans
from replay.planning.types import Plan, Planner, PlanRequest
from risk.hindsight import Tracks

#: planner_label values: important, not important, unknown (the all-agents plan failed,
#: so nothing can be compared with it).
LABEL_TRUE, LABEL_FALSE, LABEL_UNKNOWN = 1.0, 0.0, float("nan")


@dataclass(frozen=True)
class PlannerTruth:
    """Per agent of ``request.agents`` (K,): ``label`` 1.0 important, 0.0 not, NaN unknown
    (the all-agents plan failed); ``shift_m`` the plan's change without it (0 when
    skipped, NaN when a plan failed); ``skipped`` True where no counterfactual plan was
    made (``may_matter`` False)."""

    ids: np.ndarray  # (K,) int64
    label: np.ndarray  # (K,) float64
    shift_m: np.ndarray  # (K,) float64, m
    skipped: np.ndarray  # (K,) bool
    plans: int  # counterfactual plans made


def planner_truth(
    planner: Planner,
    request: PlanRequest,
    reference: Plan,
    *,
    tolerance_m: float = DEFAULT_TOLERANCE_M,
) -> PlannerTruth:
    """Label every agent of ``request`` by removing it alone (see the module docstring).
    ``reference``: the plan with all of ``request.agents``."""
    agents = request.agents
    k = agents.n
    label = np.full(k, LABEL_UNKNOWN if not reference.ok else LABEL_FALSE)
    shift = np.zeros(k)
    may = np.asarray(planner.may_matter(request), dtype=bool) if k else np.zeros(0, bool)
    plans = 0
    if reference.ok:
        everyone = np.ones(k, dtype=bool)
        for j in np.flatnonzero(may):  # one plan per agent that may matter
            everyone[j] = False
            plan = planner.plan(request.with_agents(agents.subset(everyone)))
            everyone[j] = True
            plans += 1
            change = compare_plans(reference, plan, tolerance_m=tolerance_m)
            label[j] = LABEL_TRUE if change.changed else LABEL_FALSE
            shift[j] = change.max_shift_m
    else:
        shift[:] = np.nan
    return PlannerTruth(
        ids=agents.ids.copy(), label=label, shift_m=shift, skipped=~may, plans=plans
    )


def target_speed(tracks: Tracks, row: int, column: int, horizon_s: float, now_mps: float) -> float:
    """The speed the driver was willing to drive: the larger of ``now_mps`` and the
    fastest the agent drove over the next ``horizon_s`` of its recorded track (finite
    differences of recorded positions).

    A planner given only the recorded speed would never show what an agent made the
    driver give up; one given a fixed speed limit would speed through every scene.
    """
    steps = max(1, round(horizon_s / tracks.dt_s))
    stop = min(tracks.valid.shape[0], row + steps + 1)
    if not 0 <= row < stop:
        return float(now_mps)
    xy = tracks.xy[row:stop, column]
    ok = tracks.valid[row:stop, column]
    both = ok[1:] & ok[:-1]
    if not both.any():
        return float(now_mps)
    step = np.hypot(*(xy[1:] - xy[:-1]).T)[both] / tracks.dt_s
    return float(max(now_mps, step.max()))
