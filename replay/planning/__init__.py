"""Planners in the loop: the interface (:mod:`replay.planning.types`), the inputs built
from a frame (:mod:`replay.planning.inputs`), plan comparison
(:mod:`replay.planning.compare`) and the planners (IDM, fiss-planner's Frenet planners)."""

from replay.planning.errors import NoReferencePath, PlannerUnavailable, PlanningError, UnknownPlanner
from replay.planning.types import AgentForecasts, EgoState, Plan, Planner, PlanRequest

__all__ = [
    "AgentForecasts",
    "EgoState",
    "NoReferencePath",
    "Plan",
    "PlanRequest",
    "Planner",
    "PlannerUnavailable",
    "PlanningError",
    "UnknownPlanner",
]
