"""The replay engine: a scene's frames through every model and the cascade, out to sinks.

Per frame the engine evaluates every registered model on all agents (for the per-agent
timelines), runs the filter cascade (:mod:`risk.cascade`) and hands a :class:`FrameResult`
to every sink (the Rerun recorder, the table writer, ...). Sinks are finalised with
``close()`` when the scene is done, or discarded with ``abort()`` on any error, so that no
half-written output is ever left behind.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import os
import pathlib
import sys
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from tqdm import tqdm

import risk
from converters.scene.reader import open_scene
from outputs.sinks import (  # also importable from here, as before
    Annotator,
    FrameResult,
    SceneInfo,
    Sink,
)
from replay.errors import ReplayError
from risk import kernel
from risk.cascade import SURVIVAL_MODEL, CascadeConfig, CascadeResult, Evaluator, run_cascade
from risk.frame import Frame, LaneMap, Scene
from risk.hindsight import Tracks, tracks_from_frames
from risk.prediction import PredictionSettings
from risk.registry import resolve_models


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
    cascade_time_s: float  # total time of run_cascade (stages, sort, survival on all)
    read_time_s: float  # total time spent reading frames
    sink_time_s: dict[str, float] = field(default_factory=dict)  # per sink class
    outputs: tuple[pathlib.Path, ...] = ()


class ReplayWarning(UserWarning):
    """Something the user should know about a replay that did not stop it."""


class StoredFrame(Protocol):
    """One stored frame of a :class:`SceneSource` (``converters.scene.reader.FrameEntry``)."""

    @property
    def index(self) -> int: ...  # position in the scene, 0-based

    @property
    def ego_id(self) -> int: ...  # the ego the recording names for this frame

    @property
    def frame(self) -> Frame | None: ...  # None: that ego is not a valid agent here


class SceneSource(Protocol):
    """What the engine reads: ``converters.scene.reader.SceneReader``, an in-memory scene
    (:class:`InMemoryScene`) or the every-ego loop's scene read once
    (``replay.core.egos``)."""

    @property
    def map(self) -> LaneMap: ...

    @property
    def metadata(self) -> dict[str, str]: ...

    @property
    def labels(self) -> dict[str, tuple[int, ...]]: ...

    @property
    def frame_period_s(self) -> float: ...

    @property
    def n_frames(self) -> int: ...

    @property
    def ego_id(self) -> int | None: ...  # the scene's one ego (None: see the metadata)

    def entries(self) -> Iterator[StoredFrame]: ...

    def frames(self) -> Iterator[Frame]: ...

    def tracks(self) -> Tracks: ...  # every recorded state, for the hindsight truth


@dataclass(frozen=True, eq=False)
class InMemoryScene:
    """A :class:`risk.Scene` seen as a :class:`SceneSource` (tests, the demo)."""

    scene: Scene

    @property
    def map(self) -> LaneMap:
        return self.scene.map

    @property
    def metadata(self) -> dict[str, str]:
        return dict(self.scene.metadata)

    @property
    def labels(self) -> dict[str, tuple[int, ...]]:
        return dict(self.scene.labels)

    @property
    def frame_period_s(self) -> float:
        return self.scene.frame_period_s

    @property
    def n_frames(self) -> int:
        return len(self.scene.frames)

    @property
    def ego_id(self) -> int | None:
        """The scene's ego (None: the frames' own, see :class:`risk.Scene`)."""
        return self.scene.ego_id

    def entries(self) -> Iterator[StoredFrame]:
        for index, frame in enumerate(self.scene.frames):
            yield _Stored(index, frame.ego_id, frame)

    def frames(self) -> Iterator[Frame]:
        return iter(self.scene.frames)

    def tracks(self) -> Tracks:
        return tracks_from_frames(self.scene.frames, frame_period_s=self.scene.frame_period_s)


@dataclass(frozen=True)
class _Stored:
    index: int
    ego_id: int
    frame: Frame | None


class _Totals:
    """Running sums over the processed frames (for RunSummary)."""

    def __init__(self, n_stages: int, n_tiers: int):
        self.frames = 0
        self.skipped: list[int] = []
        self.ids: set[int] = set()  # valid agents of the processed frames
        self.ids_skipped: set[int] = set()  # valid agents of the skipped frames
        self.others = 0
        self.kept = np.zeros(n_stages, dtype=np.int64)
        self.tiers = np.zeros(n_tiers, dtype=np.int64)
        self.baseline = 0
        self.fn = np.zeros(n_stages, dtype=np.int64)
        self.stage_time_s = np.zeros(n_stages)
        self.sort_time_s = 0.0
        self.survival_all_time_s = 0.0
        self.models_time_s = 0.0
        self.cascade_time_s = 0.0
        self.read_time_s = 0.0
        self.sink_time_s: dict[str, float] = {}

    def add(self, frame: Frame, res: CascadeResult) -> None:
        self.frames += 1
        self.ids.update(frame.ids[frame.valid].tolist())
        self.others += int(res.others.sum())
        self.kept += res.n_kept
        self.tiers += res.tier_counts(self.tiers.size)
        self.baseline += int(res.baseline.sum())
        self.fn += res.false_negatives
        self.stage_time_s += res.stage_time_s
        self.sort_time_s += res.sort_time_s
        self.survival_all_time_s += res.survival_all_time_s


def warm_up() -> None:
    """Load (or compile) every risk kernel (:func:`risk.kernel.warm_up`). On the
    just-in-time form, also start the ahead-of-time build in the background, so that
    later processes start about 0.9 s faster (:mod:`risk.kernel_aot`)."""
    kernel.warm_up(build_ahead_of_time=True)


def run_scene(
    source: str | os.PathLike[str] | SceneSource | Scene,
    *,
    sinks: Sequence[Sink] = (),
    cascade: CascadeConfig | None = None,
    ego: int | None = None,
    models: Sequence[str] | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    progress: bool = True,
    evaluate: Evaluator | None = None,
    every: int | Stride = 1,
    annotators: Sequence[Annotator] = (),
) -> RunSummary:
    """Replay a scene through every model and the cascade, feeding ``sinks``.

    ``source``: a scene file (opened with ``converters.scene.reader.open_scene``), a reader, or an
    in-memory :class:`risk.Scene`. ``ego``: the agent id to see the scene from (default:
    the recording's ego). ``models``: the models evaluated on all agents for the
    timelines (default: every registered model). ``params`` (model name -> parameters)
    and ``prediction`` (``risk.PredictionSettings``) go to every model evaluation, the
    cascade's included. Frames where the ego is absent or
    invalid are skipped and counted (one :class:`ReplayWarning` at the end). ``every``: a
    :class:`Stride` (or a whole number of frames); only frames whose index is a multiple
    of it are replayed, which keeps dataset-wide runs affordable (the others are neither
    processed nor counted as skipped). On any error every sink is aborted, so no partial
    output stays behind.
    """
    stride = Stride.of(every)
    reader, path = _open(source)
    cascade = CascadeConfig.default() if cascade is None else cascade
    if evaluate is None:
        evaluate = risk.evaluate  # looked up per call: tests and notebooks may replace it
    named = cascade.model_settings()  # the cascade TOML's [params.*] / [prediction]
    params = named.params_or_none() if params is None else params
    prediction = named.prediction_or_none() if prediction is None else prediction
    if prediction is not None:
        evaluate = functools.partial(evaluate, prediction=prediction)
    model_names = _model_names(models)
    # (a SceneReader holds no open file between reads: nothing to close afterwards)
    return _run(
        reader, path, sinks, cascade, ego, model_names, params, progress, evaluate,
        stride.frames_at(float(reader.frame_period_s)), annotators,
    )  # fmt: skip


def _run(
    reader: SceneSource,
    path: pathlib.Path | None,
    sinks: Sequence[Sink],
    cascade: CascadeConfig,
    ego: int | None,
    model_names: tuple[str, ...],
    params: Mapping[str, Any] | None,
    progress: bool,
    evaluate: Evaluator,
    every: int = 1,
    annotators: Sequence[Annotator] = (),
) -> RunSummary:
    entries = _entries(reader)
    start = time.perf_counter()
    first = next(entries, None)
    read_first_s = time.perf_counter() - start
    if first is None:
        raise ReplayError(f"{path or 'scene'}: the scene has no frames")
    ego_id = _scene_ego_id(reader, first[1]) if ego is None else int(ego)
    info = SceneInfo(
        map=reader.map,
        metadata=dict(reader.metadata),
        labels=dict(reader.labels),
        frame_period_s=float(reader.frame_period_s),
        ego_id=ego_id,
        cascade=cascade,
        model_names=model_names,
        source=path,
        n_frames=int(reader.n_frames),
        tracks=functools.cache(reader.tracks),
    )
    totals = _Totals(len(cascade.stages), len(cascade.tiers))
    totals.read_time_s = read_first_s
    begun: list[Sink] = []
    try:
        for annotator in annotators:
            annotator.begin(info)
        for sink in sinks:
            _timed_sink(totals, sink, "begin", info)
            begun.append(sink)
        # Load (or compile) every kernel now, so that the first frame's stage times
        # measure the frame and not numba loading compiled code (tens of ms per kernel).
        # After the sinks' begin(): a recorder writing in the background starts its
        # process there, and it imports rerun while the kernels load.
        warm_up()
        bar = tqdm(
            total=info.n_frames, disable=None if progress else True, file=sys.stderr, unit="frame",
            desc=f"replay {path.name if path else 'scene'}", leave=False,
        )  # fmt: skip
        with bar:
            for index, frame in _timed(totals, itertools.chain([first], entries)):
                bar.update()
                if index % every:
                    continue
                seen = None if frame is None else seen_from(frame, ego_id)
                if seen is None:
                    totals.skipped.append(index)
                    if frame is not None:
                        totals.ids_skipped.update(frame.ids[frame.valid].tolist())
                    continue
                result = _process(index, seen, cascade, model_names, params, evaluate, totals)
                for annotator in annotators:
                    _annotate(totals, annotator, result)
                for sink in begun:
                    _timed_sink(totals, sink, "add", result)
        if totals.frames == 0:
            raise ReplayError(_no_ego_message(ego_id, totals.ids_skipped))
        for sink in begun:  # sinks that write elsewhere start first, the rest meanwhile
            if callable(getattr(sink, "start_close", None)):
                _timed_sink(totals, sink, "start_close")
        for sink in begun:
            _timed_sink(totals, sink, "close")
    except BaseException:
        for sink in begun:
            with contextlib.suppress(Exception):
                sink.abort()
        raise
    if totals.skipped:
        warnings.warn(_skipped_message(ego_id, totals.skipped), ReplayWarning, stacklevel=3)
    return _summary(totals, info, sinks)


@dataclass(frozen=True)
class Stride:
    """Which frames to replay: every ``frames``-th, or one per ``seconds`` of scene time.

    A stride in seconds becomes ``max(1, round(seconds / frame_period_s))`` frames for each
    scene, so datasets recorded at 5, 10 or 25 Hz are sampled alike.
    """

    frames: int = 1
    seconds: float | None = None

    def __post_init__(self) -> None:
        if self.seconds is not None:
            if not (isinstance(self.seconds, (int, float)) and 0 < self.seconds < 1e6):
                raise ReplayError(f"a stride in seconds must be in (0, 1e6), got {self.seconds!r}")
        elif (
            isinstance(self.frames, bool)
            or not isinstance(self.frames, (int, np.integer))
            or not 1 <= self.frames <= 1_000_000
        ):
            raise ReplayError(f"a frame stride must be a whole number >= 1, got {self.frames!r}")

    @classmethod
    def of(cls, value: int | Stride) -> Stride:
        return value if isinstance(value, Stride) else cls(frames=value)

    @classmethod
    def parse(cls, text: str) -> Stride:
        """``"10"``: every 10th frame; ``"1s"`` or ``"0.5s"``: one frame per that time."""
        text = str(text).strip().lower()
        try:
            if text.endswith("s"):
                return cls(seconds=float(text[:-1]))
            return cls(frames=int(text))
        except ValueError:
            raise ReplayError(
                f"{text!r} is not a stride: give a whole number of frames (10) or seconds (1s)"
            ) from None

    def frames_at(self, frame_period_s: float) -> int:
        """The stride in frames for a scene with this frame period."""
        if self.seconds is None:
            return int(self.frames)
        return max(1, round(self.seconds / frame_period_s))

    def __str__(self) -> str:
        if self.seconds is not None:
            return f"one frame per {self.seconds:g} s"
        return "every frame" if self.frames == 1 else f"every {self.frames}th frame"


#: The default stride: every frame.
EVERY_FRAME = Stride()


# ---------------------------------------------------------------------- helpers
def _open(
    source: str | os.PathLike[str] | SceneSource | Scene,
) -> tuple[SceneSource, pathlib.Path | None]:
    if isinstance(source, Scene):
        return InMemoryScene(source), None
    if isinstance(source, (str, os.PathLike)):
        path = pathlib.Path(source)
        return open_scene(path), path
    where = getattr(source, "path", None)  # (a reader of a file: named in messages)
    return source, None if where is None else pathlib.Path(where)


def _model_names(models: Sequence[str] | None) -> tuple[str, ...]:
    return tuple(resolve_models(models))  # validated, unique, in the order given


def _entries(reader: SceneSource) -> Iterator[tuple[int, int, Frame | None]]:
    """(index, ego id named by the recording, frame or None) of every stored frame.

    The reader gives None for a frame whose recorded ego is missing (a Frame cannot exist
    without a valid ego); such frames are skipped whatever ``--ego`` says.
    """
    for entry in reader.entries():
        yield int(entry.index), int(entry.ego_id), entry.frame


def _scene_ego_id(reader: SceneSource, first_ego_id: int) -> int:
    """The recording's ego: the scene's ``ego_id`` when every frame shares one, else the
    first frame's ego."""
    value: int | str | None = reader.ego_id
    if value is None:
        value = dict(reader.metadata).get("ego_id")
    try:
        return int(value) if value is not None else first_ego_id
    except ValueError:
        return first_ego_id


def seen_from(frame: Frame, ego_id: int) -> Frame | None:
    """The frame with ``ego_id`` as its ego; None when that agent is absent or invalid."""
    if frame.ego_id == ego_id:
        return frame
    hits = np.flatnonzero(frame.ids == ego_id)
    if hits.size == 0 or not frame.valid[hits[0]]:
        return None
    return frame.with_ego(int(hits[0]))


def _timed(
    totals: _Totals, entries: Iterator[tuple[int, int, Frame | None]]
) -> Iterator[tuple[int, Frame | None]]:
    """(index, frame) of ``entries``, adding the time spent reading to ``read_time_s``."""
    while True:
        start = time.perf_counter()
        entry = next(entries, None)
        totals.read_time_s += time.perf_counter() - start
        if entry is None:
            return
        yield entry[0], entry[2]


def _annotate(totals: _Totals, annotator: Annotator, result: FrameResult) -> None:
    start = time.perf_counter()
    result.extras.update(annotator.annotate(result))
    name = annotator.name
    totals.sink_time_s[name] = totals.sink_time_s.get(name, 0.0) + time.perf_counter() - start


def _timed_sink(totals: _Totals, sink: Sink, method: str, *args: Any) -> None:
    start = time.perf_counter()
    getattr(sink, method)(*args)
    name = getattr(sink, "timing_name", type(sink).__name__)
    totals.sink_time_s[name] = totals.sink_time_s.get(name, 0.0) + time.perf_counter() - start


def _process(
    index: int,
    frame: Frame,
    cascade: CascadeConfig,
    model_names: tuple[str, ...],
    params: Mapping[str, Any] | None,
    evaluate: Evaluator,
    totals: _Totals,
) -> FrameResult:
    # Survival on all agents is the cascade's baseline; it is computed (and timed) there
    # once and reused for the timeline instead of evaluating it twice.
    timeline_models = [m for m in model_names if m != SURVIVAL_MODEL]
    start = time.perf_counter()
    risks = evaluate(frame, models=timeline_models, params=params) if timeline_models else {}
    totals.models_time_s += time.perf_counter() - start
    start = time.perf_counter()
    result = run_cascade(frame, cascade, params=params, evaluate=evaluate)
    totals.cascade_time_s += time.perf_counter() - start
    risks = {**risks, SURVIVAL_MODEL: result.survival_all}
    totals.add(frame, result)
    return FrameResult(
        index=index,
        frame=frame,
        risks={m: np.asarray(risks[m], dtype=np.float64) for m in model_names},
        cascade=result,
    )


def _no_ego_message(ego_id: int, ids_seen: set[int]) -> str:
    some = ", ".join(str(i) for i in sorted(ids_seen)[:8])
    more = ", ..." if len(ids_seen) > 8 else ""
    if not ids_seen:
        return (
            f"agent id {ego_id} is not a valid agent in any frame, and the scene has no valid"
            " agents at all; convert the source again"
        )
    return (
        f"agent id {ego_id} is not a valid agent in any frame of the scene; "
        f"valid ids include {some}{more}"
    )


def _skipped_message(ego_id: int, skipped: list[int]) -> str:
    shown = ", ".join(str(i) for i in skipped[:5]) + (", ..." if len(skipped) > 5 else "")
    return (
        f"{len(skipped)} frame(s) skipped because the ego (id {ego_id}) is missing or "
        f"invalid there (frames {shown})"
    )


def _summary(totals: _Totals, info: SceneInfo, sinks: Sequence[Sink]) -> RunSummary:
    n = max(totals.frames, 1)
    # A sink names its file as ``path`` (TableSink) or ``output`` (SceneRecorder).
    files = (getattr(s, "path", None) or getattr(s, "output", None) for s in sinks)
    outputs = tuple(pathlib.Path(p) for p in files if p is not None)
    return RunSummary(
        source=info.source,
        ego_id=info.ego_id,
        frames=totals.frames,
        skipped_frames=len(totals.skipped),
        agents=len(totals.ids),
        mean_others=totals.others / n,
        stage_names=info.cascade.stage_names,
        mean_kept=tuple(float(k) / n for k in totals.kept),
        tier_names=tuple(t.name for t in info.cascade.tiers),
        mean_tier=tuple(float(k) / n for k in totals.tiers),
        baseline_agents=totals.baseline,
        false_negatives=tuple(int(f) for f in totals.fn),
        stage_time_s=tuple(float(t) for t in totals.stage_time_s),
        sort_time_s=totals.sort_time_s,
        survival_all_time_s=totals.survival_all_time_s,
        models_time_s=totals.models_time_s,
        cascade_time_s=totals.cascade_time_s,
        read_time_s=totals.read_time_s,
        sink_time_s=dict(totals.sink_time_s),
        outputs=outputs,
    )
