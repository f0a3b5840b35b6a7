"""Recordings: results streamed into Rerun .rrd files (the only package that imports rerun).

``SceneRecorder`` is the replay sink that writes one ``.rrd`` per scene; ``layout`` holds
its entity paths, colours and blueprint, ``columns`` the Arrow batching, ``summary`` the
summary text (see ``docs/recording.md``).
"""

from __future__ import annotations

from typing import Any

from recordings.errors import RecordingError

__all__ = ["LABEL_MODES", "RecordingError", "SceneRecorder"]


def __getattr__(name: str) -> Any:
    """``SceneRecorder`` and ``LABEL_MODES`` load ``recordings.recorder`` (and rerun, about
    0.7 s) on first use, so that importing ``recordings.errors`` (the CLI's error types,
    looked up whenever a command ends with an exception, ``--help`` included) does not."""
    if name in ("SceneRecorder", "LABEL_MODES"):
        import recordings.recorder

        return getattr(recordings.recorder, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
