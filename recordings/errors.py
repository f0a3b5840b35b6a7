"""Exceptions raised while writing recordings."""

from __future__ import annotations


class RecordingError(RuntimeError):
    """A recording could not be written."""
