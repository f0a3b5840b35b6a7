"""Recordings: results streamed into Rerun .rrd files (the only package that imports rerun).

``SceneRecorder`` is the replay sink that writes one ``.rrd`` per scene; ``layout`` holds
its entity paths, colours and blueprint, ``columns`` the Arrow batching, ``summary`` the
summary text (see ``docs/recording.md``).
"""

from recordings.errors import RecordingError
from recordings.recorder import LABEL_MODES, SceneRecorder

__all__ = ["LABEL_MODES", "RecordingError", "SceneRecorder"]
