"""Batch runs over whole datasets: convert, replay and tabulate every scene, in parallel.

One **task** is one unit of work a worker runs from start to finish:

- a *convert task* turns one raw dataset file (``--convert waymo|av2|commonroad|
  interaction``) into MCAP scenes under ``OUT/scenes/`` (a Waymo TFRecord may hold many
  scenarios: one scene each);
- a *replay task* replays one MCAP scene through every model and the cascade
  (:func:`replay.core.engine.run_scene`) into its per-scene table (and, with ``rrd``, its
  Rerun recording).

The driver (:func:`run_batch`) plans the tasks, hands them to an :class:`Engine`, starts
the replay of a converted file's scenes as soon as its conversion is back, merges the
per-scene tables and runs the dataset statistics of ``replay stats`` on them.

Modules: :mod:`~replay.batch.records` (tasks, outcomes, failures: plain data),
:mod:`~replay.batch.tasks` (the functions workers run), :mod:`~replay.batch.markers`
(done-markers, atomic files), :mod:`~replay.batch.engines` (local processes, Ray),
:mod:`~replay.batch.driver` (discovery, planning, the run, its tables and statistics).

Engines (one small interface, :class:`Engine`): ``local`` is a
:class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn`` start method (no
forked copies of polars' or rerun's threads); ``ray`` runs the same task functions as Ray
tasks on a local Ray instance or an existing cluster. Task functions are module-level and
their arguments plain frozen dataclasses, so both engines can pickle them.

Fault isolation: a task never raises; it returns an outcome holding either its result or
a :class:`Failure` (input, scene, stage, error type, one-line reason). A worker process
that dies (a crash in native code, the out-of-memory killer) is handled by the engine:
the local engine re-runs every task the dead pool took down, each one alone, so only the
culprit is reported; Ray retries the task once itself.

Layout of ``OUT`` (``NAME`` is a scene's name, see :func:`discover`)::

    scenes/NAME.mcap          converted scenes (only with --convert); NAME keeps the
                              input's sub-folders, e.g. sind/NAME
    tables/NAME.parquet       per-scene agents tables (replay.core.tables' columns + scene)
    frames/NAME.parquet       per-scene frames tables (replay.analysis.stats: cascade per frame)
    recordings/NAME.rrd       Rerun recordings (only with --rrd)
    .done/NAME.json           replay done-markers
    .done/convert/NAME.json   conversion done-markers (only with --convert)
    stats/                    dataset statistics over the merged tables (replay stats)
    scenes.csv                every scene of the run: replayed, skipped or failed
    failures.csv              every failure: input, scene, stage, error type, reason

Resuming. Every output is written atomically (temporary file in the same folder, then
``os.replace``), and a scene's done-marker is written last, after all its outputs. A
scene is **complete**, and skipped by a rerun, when its marker

1. parses and has this module's marker format,
2. names the same scene file with the same size and modification time (ns),
3. has the same settings digest (:meth:`BatchSettings.replay_digest`: cascade, models,
   package version), and
4. lists outputs that all still exist with their recorded sizes, including a recording
   when ``rrd`` is asked for.

A converted file is complete likewise (same file size and time, same conversion settings,
every scene it produced still present with its recorded size and time). Its conversion
failures (a corrupt record in a TFRecord) are deterministic, so they are kept in the
marker and reported again instead of converting the file again; a failure that may be
transient (``OSError``, ``MemoryError``) leaves no marker, so the file is converted again.
"""

from replay.batch.driver import (
    SCENE_COLUMNS,
    BatchReport,
    BatchSettings,
    InputFile,
    Layout,
    dataset_stats,
    discover,
    run_batch,
    write_scenes,
)
from replay.batch.markers import MARKER_FORMAT, completed_conversion, completed_scene
from replay.batch.records import (
    STAGES,
    ConvertOutcome,
    ConvertTask,
    Failure,
    ReplayOutcome,
    ReplayTask,
    SceneDone,
)
from replay.batch.tasks import CONVERT_KINDS, convert_one, replay_one
from replay.core.pool import LocalEngine, WorkerDied, default_workers
from replay.jobs.engines import ENGINES, RAY_MISSING, Engine, RayEngine, make_engine
from replay.jobs.failures import FAILURE_COLUMNS, read_failures, write_failures

__all__ = [
    "CONVERT_KINDS",
    "ENGINES",
    "FAILURE_COLUMNS",
    "MARKER_FORMAT",
    "RAY_MISSING",
    "SCENE_COLUMNS",
    "STAGES",
    "BatchReport",
    "BatchSettings",
    "ConvertOutcome",
    "ConvertTask",
    "Engine",
    "Failure",
    "InputFile",
    "Layout",
    "LocalEngine",
    "RayEngine",
    "ReplayOutcome",
    "ReplayTask",
    "SceneDone",
    "WorkerDied",
    "completed_conversion",
    "completed_scene",
    "convert_one",
    "dataset_stats",
    "default_workers",
    "discover",
    "make_engine",
    "read_failures",
    "replay_one",
    "run_batch",
    "write_failures",
    "write_scenes",
]
