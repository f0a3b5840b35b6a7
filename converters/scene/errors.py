"""Exceptions raised by the scene package (reading and writing scene files)."""

from __future__ import annotations

from risk.errors import RiskReplayError


class SceneFormatError(RiskReplayError, RuntimeError):
    """A file is not a readable scene: not MCAP, truncated, or missing our channels."""


class ProtoSyntaxError(RiskReplayError, ValueError):
    """A ``.proto`` file uses something outside the subset the schema parser reads (for
    ``scene.proto``, a packaging bug)."""
