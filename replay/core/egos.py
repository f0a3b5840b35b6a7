"""Every moving agent as the ego (``--ego all``): one scene replayed once per ego.

Drone and camera recordings have no ego vehicle; any agent that moves can be one. The
scene is read once into memory; each agent whose travel extent reaches
:data:`risk.motion.MIN_TRAVEL_M` (see :mod:`risk.motion`) becomes the ego in turn, and the
frames where it is valid are replayed through every model and the cascade. The sinks see
one ``begin``/``add`` sequence per ego and are closed once at the end, so a table sink
writes one table holding every ego (its ``ego_id`` column says whose view a row is), and
nothing is written if any ego fails.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import pathlib
import sys
import warnings
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from converters.scene.reader import open_scene
from outputs.sinks import Annotator
from replay.core.engine import (
    FrameResult,
    ReplayWarning,
    RunSummary,
    SceneInfo,
    Sink,
    Stride,
    run_scene,
)
from replay.errors import ReplayError
from risk.cascade import CascadeConfig, Evaluator
from risk.frame import Frame, LaneMap
from risk.hindsight import Tracks, tracks_from_frames
from risk.motion import MIN_TRAVEL_M, moving_agent_ids
from risk.prediction import PredictionSettings

#: What ``--ego`` takes besides an agent id.
ALL_EGOS = "all"


@dataclasses.dataclass(frozen=True, eq=False)
class _LoadedScene:
    """A scene file read once: frames seen from any valid agent, with their indices."""

    map: LaneMap
    metadata: dict[str, str]
    labels: dict[str, tuple[int, ...]]
    frame_period_s: float
    indexed: tuple[tuple[int, Frame], ...]
    path: pathlib.Path | None

    @property
    def n_frames(self) -> int:
        return len(self.indexed)

    @property
    def ego_id(self) -> int | None:
        return None  # every agent in turn; the recording's own is in the metadata

    def entries(self) -> Iterator[_Entry]:
        for index, frame in self.indexed:
            yield _Entry(index, frame.ego_id, frame)

    def frames(self) -> Iterator[Frame]:
        return (frame for _, frame in self.indexed)

    def tracks(self) -> Tracks:
        """Every recorded agent state (the hindsight truth's input), built once."""
        return self._tracks

    @functools.cached_property
    def _tracks(self) -> Tracks:
        return tracks_from_frames([f for _, f in self.indexed], frame_period_s=self.frame_period_s)


@dataclasses.dataclass(frozen=True)
class _Entry:
    index: int
    ego_id: int
    frame: Frame


class _KeepOpen:
    """Forwards one ego's ``begin``/``add`` to a sink; the ego loop closes it once."""

    def __init__(self, sink: Sink) -> None:
        self.sink = sink
        # what replay.core.engine reports its time as
        self.timing_name = getattr(sink, "timing_name", type(sink).__name__)

    def begin(self, info: SceneInfo) -> None:
        self.sink.begin(info)

    def add(self, result: FrameResult) -> None:
        self.sink.add(result)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass  # the ego loop aborts the real sink


@dataclasses.dataclass(frozen=True)
class EgosSummary:
    """What an every-ego replay did: the moving agents and one summary per ego."""

    source: pathlib.Path | None
    egos: tuple[int, ...]
    min_travel_m: float
    every: Stride
    runs: tuple[RunSummary, ...]
    outputs: tuple[pathlib.Path, ...] = ()

    @property
    def ego_frames(self) -> int:
        return sum(r.frames for r in self.runs)


def load_scene(source: str | os.PathLike[str]) -> _LoadedScene:
    """Read a scene file into memory, every frame with at least one valid agent."""
    path = pathlib.Path(source)
    reader = open_scene(path)
    indexed = tuple(
        (int(e.index), e.frame) for e in reader.entries(any_ego=True) if e.frame is not None
    )
    return _LoadedScene(
        map=reader.map,
        metadata=dict(reader.metadata),
        labels=dict(reader.labels),
        frame_period_s=float(reader.frame_period_s),
        indexed=indexed,
        path=path,
    )


def run_every_ego(
    source: str | os.PathLike[str],
    *,
    sinks: Sequence[Sink] = (),
    cascade: CascadeConfig | None = None,
    every: int | Stride = 1,
    min_travel_m: float = MIN_TRAVEL_M,
    models: Sequence[str] | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    progress: bool = True,
    evaluate: Evaluator | None = None,
    annotators: Sequence[Annotator] = (),
) -> EgosSummary:
    """Replay the scene once for every agent that moves at least ``min_travel_m``.

    Frames where an ego is not valid are left out of that ego's replay (not an error:
    each agent is present for part of the scene). Raises ReplayError when no agent moves
    enough. ``every`` is the frame stride of :func:`replay.core.engine.run_scene`.
    """
    stride = Stride.of(every)
    scene = load_scene(source)
    step = stride.frames_at(scene.frame_period_s)
    egos = moving_agent_ids(scene.frames(), min_travel_m)
    if egos.size == 0:
        raise ReplayError(
            f"{scene.path}: no agent moves {min_travel_m:g} m or more in this scene, so "
            "--ego all has no ego to replay; pick an agent with --ego ID"
        )
    # With a stride, an agent valid only between replayed frames has nothing to replay.
    strided = [f for index, f in scene.indexed if index % step == 0]
    present = np.unique(np.concatenate([f.ids[f.valid] for f in strided] or [np.zeros(0)]))
    egos = egos[np.isin(egos, present)]
    wrapped = [_KeepOpen(s) for s in sinks]
    runs: list[RunSummary] = []
    bar = tqdm(
        egos.tolist(), disable=None if progress else True, file=sys.stderr, unit="ego",
        desc=f"egos of {scene.path.name if scene.path else 'scene'}", leave=False,
    )  # fmt: skip
    try:
        with warnings.catch_warnings():
            # An ego missing from some frames is the normal case here: counted, not warned.
            warnings.simplefilter("ignore", ReplayWarning)
            for ego in bar:
                run = run_scene(
                    scene, sinks=wrapped, cascade=cascade, ego=int(ego), models=models,
                    params=params, prediction=prediction, progress=False, evaluate=evaluate,
                    every=step, annotators=annotators,
                )  # fmt: skip
                runs.append(run)
        for sink in sinks:
            sink.close()
    except BaseException:
        for sink in sinks:
            with contextlib.suppress(Exception):
                sink.abort()
        raise
    files = (getattr(s, "path", None) or getattr(s, "output", None) for s in sinks)
    return EgosSummary(
        source=scene.path,
        egos=tuple(int(e) for e in egos),
        min_travel_m=float(min_travel_m),
        every=stride,
        runs=tuple(runs),
        outputs=tuple(pathlib.Path(p) for p in files if p is not None),
    )


def pooled(summary: EgosSummary) -> RunSummary:
    """One RunSummary over every ego: sums of counts and times, means per ego-frame."""
    runs = summary.runs
    frames = sum(r.frames for r in runs)
    n = max(frames, 1)

    def mean(values: Sequence[tuple[float, ...]], weights: Sequence[int]) -> tuple[float, ...]:
        stacked = np.array(values, dtype=np.float64).reshape(len(weights), -1)
        return tuple((stacked * np.array(weights)[:, None]).sum(axis=0) / n)

    weights = [r.frames for r in runs]
    sink_time: dict[str, float] = {}
    for r in runs:
        for k, v in r.sink_time_s.items():
            sink_time[k] = sink_time.get(k, 0.0) + v
    first = runs[0]
    return dataclasses.replace(
        first,
        ego_id=-1,
        frames=frames,
        skipped_frames=sum(r.skipped_frames for r in runs),
        agents=max(r.agents for r in runs),
        mean_others=float(np.dot([r.mean_others for r in runs], weights) / n),
        mean_kept=mean([r.mean_kept for r in runs], weights),
        mean_tier=mean([r.mean_tier for r in runs], weights),
        baseline_agents=sum(r.baseline_agents for r in runs),
        false_negatives=tuple(int(x) for x in np.sum([r.false_negatives for r in runs], axis=0)),
        stage_time_s=tuple(float(x) for x in np.sum([r.stage_time_s for r in runs], axis=0)),
        sort_time_s=sum(r.sort_time_s for r in runs),
        survival_all_time_s=sum(r.survival_all_time_s for r in runs),
        models_time_s=sum(r.models_time_s for r in runs),
        cascade_time_s=sum(r.cascade_time_s for r in runs),
        read_time_s=first.read_time_s,
        sink_time_s=sink_time,
        outputs=summary.outputs,
    )
