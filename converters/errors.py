"""Exceptions raised by converters."""

from __future__ import annotations


class ConversionError(RuntimeError):
    """A source could not be converted; the message names the file (and record) at fault."""
