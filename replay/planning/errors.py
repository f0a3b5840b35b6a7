"""User-facing errors of the planner package (the CLI prints them as ``Error: ...``)."""

from __future__ import annotations

from replay.errors import ReplayError


class PlanningError(ReplayError):
    """Base of the planner package's errors; the message says what is wrong and what to do."""


class NoReferencePath(PlanningError):
    """The ego has no usable path to plan along."""


class PlannerUnavailable(PlanningError):
    """A planner needs an optional dependency that is not installed."""


class UnknownPlanner(PlanningError):
    """A planner name that is not in the registry."""
