"""Exceptions raised by the replay package (running, statistics)."""

from __future__ import annotations

from risk.errors import RiskReplayError


class ReplayError(RiskReplayError, RuntimeError):
    """Base class of replay errors; the message says what is wrong and what to do."""


class StatsError(ReplayError):
    """Statistics that cannot be computed from the given input (the message says why)."""
