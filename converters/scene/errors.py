"""Exceptions raised by the scene package (reading and writing scene files)."""

from __future__ import annotations


class SceneFormatError(RuntimeError):
    """A file is not a readable scene: not MCAP, truncated, or missing our channels."""
