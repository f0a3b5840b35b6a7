"""Planners in the loop: the interface (:mod:`replay.planning.types`), the inputs built
from a frame (:mod:`replay.planning.inputs`), plan comparison
(:mod:`replay.planning.compare`) and the planners (IDM, fiss-planner's Frenet planners)."""

from replay.planning.compare import PlanChange, compare_plans
from replay.planning.errors import (
    NoReferencePath,
    PlannerUnavailable,
    PlanningError,
    UnknownPlanner,
)
from replay.planning.idm import IdmPlanner, IdmSettings
from replay.planning.inputs import forecasts_for, plan_request
from replay.planning.registry import PLANNERS, available_planners, make_planner
from replay.planning.types import AgentForecasts, EgoState, Plan, Planner, PlanRequest

__all__ = [
    "PLANNERS",
    "AgentForecasts",
    "EgoState",
    "IdmPlanner",
    "IdmSettings",
    "NoReferencePath",
    "Plan",
    "PlanChange",
    "PlanRequest",
    "Planner",
    "PlannerUnavailable",
    "PlanningError",
    "UnknownPlanner",
    "available_planners",
    "compare_plans",
    "forecasts_for",
    "make_planner",
    "plan_request",
]
