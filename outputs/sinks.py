"""The types a replay hands to its outputs: :class:`Sink`, :class:`SceneInfo`,
:class:`FrameResult`.

The engine (:mod:`replay.core.engine`) builds them; every output (the table writer, the
statistics collector, the Rerun recorder in :mod:`recordings`, ...) consumes them. They
live here, below both, so that an output package needs nothing from ``replay`` (see
:mod:`outputs`). ``replay.core.engine`` re-exports them under their old names.
"""

from __future__ import annotations

import pathlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from risk.cascade import CascadeConfig, CascadeResult
from risk.frame import Frame, LaneMap
from risk.hindsight import Tracks


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
    # The scene's recorded agent states (risk.hindsight.Tracks), read on first call and
    # cached: for sinks that need the recorded future (hindsight truth). None: unknown.
    tracks: Callable[[], Tracks] | None = None


@dataclass(frozen=True, eq=False)
class FrameResult:
    """One frame's results. ``N = frame.n_agents``."""

    index: int  # frame index in the scene
    frame: Frame
    risks: dict[str, np.ndarray]  # model name -> (N,) risk on ALL agents (NaN: ego/invalid)
    cascade: CascadeResult
    #: What annotators added (a planner's plans and labels, see
    #: :mod:`replay.planning.annotator`); empty without one.
    extras: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class Annotator(Protocol):
    """Computes more per frame for the sinks (e.g. a planner's plans): ``begin`` once per
    scene (and ego), then ``annotate`` per frame; what it returns goes into
    :attr:`FrameResult.extras` before any sink sees the frame. ``name`` labels its time."""

    @property
    def name(self) -> str: ...

    def begin(self, info: SceneInfo) -> None: ...

    def annotate(self, result: FrameResult) -> dict[str, Any]: ...


@runtime_checkable
class Sink(Protocol):
    """A consumer of per-frame results (recording, table, statistics)."""

    def begin(self, info: SceneInfo) -> None: ...

    def add(self, result: FrameResult) -> None: ...

    def close(self) -> None: ...  # finalise atomically

    def abort(self) -> None: ...  # discard partial output

    # Optional: ``start_close()``, called on every sink before any close(), for a sink
    # that writes in another process (the recorder with the output process), so that its
    # writing overlaps the other sinks' close().
