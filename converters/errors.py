"""Exceptions raised by converters."""

from __future__ import annotations

from risk.errors import RiskReplayError


class ConversionError(RiskReplayError, RuntimeError):
    """A source could not be converted; the message names the file (and record) at fault."""
