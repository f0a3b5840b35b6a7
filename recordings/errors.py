"""Exceptions raised while writing recordings."""

from __future__ import annotations

from risk.errors import RiskReplayError


class RecordingError(RiskReplayError, RuntimeError):
    """A recording could not be written."""
