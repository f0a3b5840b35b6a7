"""Exceptions raised by the replay package (reading scenes, running, statistics)."""

from __future__ import annotations


class ReplayError(RuntimeError):
    """Base class of replay errors; the message says what is wrong and what to do."""


class SceneFormatError(ReplayError):
    """A file is not a readable scene: not MCAP, truncated, or missing our channels."""


class StatsError(ReplayError):
    """Statistics that cannot be computed from the given input (the message says why)."""
