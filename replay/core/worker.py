"""The one per-scene worker: a scene replayed into its statistics tables (and recording).

``replay stats``, ``replay batch`` and ``replay experiment`` all replay scenes through
:func:`replay_scene`: the engine with a :class:`~replay.core.stats_sink.StatsSink` (and a
:class:`recordings.SceneRecorder` when a recording is asked for), without a progress bar,
with frames that lack the ego counted in the tables instead of warned about by every
worker over the driver's progress bar. Other warnings pass through.
"""

from __future__ import annotations

import os
import pathlib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import polars as pl

from outputs.sinks import Sink
from replay.core.egos import ALL_EGOS, pooled, run_every_ego
from replay.core.engine import (
    EVERY_FRAME,
    ReplayWarning,
    RunSummary,
    SceneSource,
    Stride,
    run_scene,
)
from replay.core.stats_sink import StatsSink
from risk.cascade import CascadeConfig
from risk.frame import Scene
from risk.hindsight import HindsightSettings
from risk.prediction import PredictionSettings


@dataclass(frozen=True, eq=False)
class SceneTables:
    """One replayed scene: its agents and frames tables and the engine's summary."""

    agents: pl.DataFrame
    frames: pl.DataFrame
    summary: RunSummary


def replay_scene(
    source: str | os.PathLike[str] | SceneSource | Scene,
    *,
    name: str,
    cascade: CascadeConfig,
    models: tuple[str, ...] | None = None,
    recording: str | os.PathLike[str] | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    ego: int | str | None = None,
    every: int | Stride = 1,
) -> SceneTables:
    """Replay ``source`` (a scene file, an open reader or an in-memory scene) into its
    tables, named ``name`` in their ``scene`` column; also write its ``.rrd`` to
    ``recording`` (its folder is created). Every output is aborted on an error.

    ``params`` (model name -> parameters) and ``prediction`` go to every model
    evaluation; ``hindsight``: the settings of the table's truth columns. ``ego``: an
    agent id, None for the recording's ego, or ``"all"`` for every moving agent in turn
    (:mod:`replay.core.egos`; a scene file only, and no recording). ``every``: the frame
    stride."""
    if ego == ALL_EGOS:
        if recording is not None:
            raise ValueError("a recording shows one ego's view; it cannot go with ego='all'")
        if not isinstance(source, (str, os.PathLike)):
            raise TypeError("ego='all' replays a scene file")
        collect = StatsSink(name, hindsight=hindsight)
        egos = run_every_ego(
            source, sinks=[collect], cascade=cascade, models=models, every=every,
            params=params, prediction=prediction, progress=False,
        )  # fmt: skip
        return SceneTables(collect.agents(), collect.frames(), pooled(egos))
    collect = StatsSink(name, hindsight=hindsight)
    sinks: list[Sink] = [collect]
    if recording is not None:
        # Imported here: rerun adds about a second to every worker's start, and most
        # workers (statistics, the experiment) write no recording.
        from recordings import SceneRecorder

        pathlib.Path(recording).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(SceneRecorder(recording))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ReplayWarning)  # skipped frames: absent from tables
        summary = run_scene(
            source, sinks=sinks, cascade=cascade, models=models, params=params,
            prediction=prediction, progress=False, ego=None if ego is None else int(ego),
            every=every,
        )  # fmt: skip
    return SceneTables(collect.agents(), collect.frames(), summary)


@dataclass(frozen=True)
class SceneJob:
    """A scene file for :func:`replay_job` in a worker process (picklable)."""

    path: pathlib.Path
    name: str
    cascade: CascadeConfig
    models: tuple[str, ...] | None = None
    ego: int | str | None = None
    every: Stride = EVERY_FRAME
    params: Mapping[str, Any] | None = None  # model name -> parameters, for every evaluation
    prediction: PredictionSettings | None = None
    hindsight: HindsightSettings | None = None  # settings of the truth columns


def replay_job(job: SceneJob) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The agents and frames tables of one scene file (runs in a worker process)."""
    tables = replay_scene(
        job.path, name=job.name, cascade=job.cascade, models=job.models, ego=job.ego,
        every=job.every, params=job.params, prediction=job.prediction, hindsight=job.hindsight,
    )  # fmt: skip
    return tables.agents, tables.frames


__all__ = ["SceneJob", "SceneTables", "replay_job", "replay_scene"]
