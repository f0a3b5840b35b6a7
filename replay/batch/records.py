"""The plain data of a batch run: tasks, their outcomes and failures (picklable, so that
any engine can ship them to its workers)."""

from __future__ import annotations

from dataclasses import dataclass

from replay.core.engine import EVERY_FRAME, Stride
from replay.jobs.failures import Failure
from risk.cascade import CascadeConfig

STAGES: tuple[str, ...] = ("setup", "convert", "read", "replay", "record", "write", "worker")
"""Where a scene can fail: loading riskreplay in the worker (a cluster node without the
package), converting, reading the MCAP, replaying (models, cascade, missing ego), writing
the recording, writing the tables or marker, and the worker process itself dying."""

__all__ = [
    "STAGES",
    "ConvertOutcome",
    "ConvertTask",
    "Failure",
    "ReplayOutcome",
    "ReplayTask",
    "SceneDone",
]


@dataclass(frozen=True)
class ReplayTask:
    """Replay one MCAP scene into its table (and recording). Paths are strings so that
    the task reads the same on every node of a cluster (a shared file system)."""

    input: str
    scene: str  # the MCAP file
    name: str
    table: str  # agents table (replay.core.tables columns + scene)
    frames_table: str  # frames table of replay.analysis.stats (cascade counts and times per frame)
    recording: str | None
    marker: str
    digest: str
    cascade: CascadeConfig
    ego: int | str | None = None  # None: the recording's ego; "all": every moving agent
    every: Stride = EVERY_FRAME


@dataclass(frozen=True)
class SceneDone:
    """A replayed (or, on resume, previously replayed) scene: a row of ``scenes.csv``."""

    name: str
    input: str
    table: str
    frames_table: str
    recording: str | None
    frames: int
    skipped_frames: int  # frames without the ego
    agents: int
    seconds: float  # wall-clock time of the replay task
    status: str = "replayed"  # or "skipped" (complete from an earlier run)


@dataclass(frozen=True)
class ReplayOutcome:
    task: ReplayTask
    done: SceneDone | None
    failure: Failure | None


@dataclass(frozen=True)
class ConvertTask:
    """Convert one raw input (a file, a log folder, or several track files of one
    recording: ``input`` and ``extra``) of source ``kind`` (a key of
    converters.sources.SOURCES) into MCAP scenes under ``scenes_dir``."""

    input: str
    name: str
    kind: str
    paths: str
    map_osm: str | None
    scenes_dir: str
    marker: str
    digest: str
    extra: tuple[str, ...] = ()  # more track files of the same scene (INTERACTION)
    time_step: str | float = "auto"  # converters.clock: auto, file or seconds


@dataclass(frozen=True)
class ConvertOutcome:
    task: ConvertTask
    scenes: tuple[tuple[str, str], ...]  # (scene name, MCAP path) of every scene written
    failures: tuple[Failure, ...]
    seconds: float
