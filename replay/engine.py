"""The replay engine: a scene's frames through every model and the cascade, out to sinks.

Per frame the engine evaluates every registered model on all agents (for the per-agent
timelines), runs the filter cascade (:mod:`risk.cascade`) and hands a :class:`FrameResult`
to every sink (the Rerun recorder, the table writer, ...). Sinks are finalised with
``close()`` when the scene is done, or discarded with ``abort()`` on any error, so that no
half-written output is ever left behind.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from risk.cascade import CascadeConfig, CascadeResult
from risk.frame import Frame, LaneMap


@dataclass(frozen=True, eq=False)
class SceneInfo:
    """What a sink needs to know about a scene before its first frame."""

    map: LaneMap
    metadata: dict[str, str]
    labels: dict[str, tuple[int, ...]]
    frame_period_s: float
    ego_id: int
    cascade: CascadeConfig
    model_names: tuple[str, ...]  # the keys of FrameResult.risks, in registry order
    source: pathlib.Path | None  # the scene file, None for an in-memory scene
    n_frames: int  # frames in the scene (some may be skipped: ego missing)


@dataclass(frozen=True, eq=False)
class FrameResult:
    """One frame's results. ``N = frame.n_agents``."""

    index: int  # frame index in the scene
    frame: Frame
    risks: dict[str, np.ndarray]  # model name -> (N,) risk on ALL agents (NaN: ego/invalid)
    cascade: CascadeResult


@runtime_checkable
class Sink(Protocol):
    """A consumer of per-frame results (recording, table, statistics)."""

    def begin(self, info: SceneInfo) -> None: ...

    def add(self, result: FrameResult) -> None: ...

    def close(self) -> None: ...  # finalise atomically

    def abort(self) -> None: ...  # discard partial output


@dataclass(frozen=True)
class RunSummary:
    """What one replay did: counts, means, false negatives and times."""

    source: pathlib.Path | None
    ego_id: int
    frames: int  # frames processed
    skipped_frames: int  # frames without the ego
    agents: int  # distinct agent ids seen (ego included)
    mean_others: float  # mean number of valid non-ego agents per processed frame
    stage_names: tuple[str, ...]
    mean_kept: tuple[float, ...]  # (S,) mean agents kept after each stage
    tier_names: tuple[str, ...]
    mean_tier: tuple[float, ...]  # mean agents per tier (nested counts)
    baseline_agents: int  # baseline-important agent-frames
    false_negatives: tuple[int, ...]  # (S,) cumulative baseline agent-frames dropped
    stage_time_s: tuple[float, ...]  # (S,) total compute time of each stage
    sort_time_s: float  # total survival-on-survivors + sorting time
    survival_all_time_s: float  # total survival-on-all-agents time
    models_time_s: float  # total time of the all-model evaluation (timelines)
    read_time_s: float  # total time spent reading frames
    sink_time_s: dict[str, float] = field(default_factory=dict)  # per sink class
    outputs: tuple[pathlib.Path, ...] = ()
