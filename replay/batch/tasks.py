"""The task functions that workers run: convert one raw file, replay one scene.

Both are module-level functions of one frozen dataclass argument, so every engine can
pickle them; both never raise for a bad input: every exception becomes a
:class:`~replay.batch.records.Failure` in the outcome.
"""

from __future__ import annotations

import contextlib
import pathlib
import sys
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from converters.scene.reader import open_scene
from converters.sources import SOURCES, ReadOptions, SourceInput, SourceSpec
from converters.tracks import Skipped
from outputs.atomic import safe_name
from replay.batch.markers import write_convert_marker, write_parquet, write_replay_marker
from replay.batch.records import (
    ConvertOutcome,
    ConvertTask,
    Failure,
    ReplayOutcome,
    ReplayTask,
    SceneDone,
)
from replay.core.egos import ALL_EGOS
from replay.core.worker import replay_scene
from replay.jobs.failures import failure_from, one_line

if TYPE_CHECKING:
    from risk.frame import Scene

CONVERT_KINDS: tuple[str, ...] = tuple(SOURCES)
_TRANSIENT = (OSError, MemoryError)


def replay_one(task: ReplayTask) -> ReplayOutcome:
    """Replay one scene into its tables (and recording), then write its done-marker.

    Never raises for a bad scene: every exception becomes the outcome's Failure.
    """
    start = time.perf_counter()
    stage = "read"
    try:
        reader = open_scene(task.scene)
        stage = "replay"
        # Frames without the ego are counted in scenes.csv, not warned about.
        tables = replay_scene(
            reader if task.ego != ALL_EGOS else task.scene, name=task.name,
            cascade=task.cascade, recording=task.recording, ego=task.ego, every=task.every,
        )  # fmt: skip
        summary = tables.summary
        stage = "write"
        write_parquet(pathlib.Path(task.table), tables.agents)
        write_parquet(pathlib.Path(task.frames_table), tables.frames)
        done = SceneDone(
            name=task.name,
            input=task.input,
            table=task.table,
            frames_table=task.frames_table,
            recording=task.recording,
            frames=summary.frames,
            skipped_frames=summary.skipped_frames,
            agents=summary.agents,
            seconds=time.perf_counter() - start,
        )
        write_replay_marker(task, done)
        return ReplayOutcome(task, done, None)
    except Exception as exc:
        return ReplayOutcome(task, None, failure_from(task.input, task.name, stage, exc))


def convert_one(task: ConvertTask) -> ConvertOutcome:
    """Convert one raw file into scenes; each scene fails alone where the format allows
    (a Waymo file's records), the whole file where it holds one scene.

    Writes the conversion marker when no failure could be transient. Never raises.
    """
    start = time.perf_counter()
    try:
        from converters.scene.writer import write_scene
    except Exception as exc:
        failure = failure_from(task.input, "", "setup", exc)
        return ConvertOutcome(task, (), (failure,), time.perf_counter() - start)
    skipped = Skipped()
    scenes: list[tuple[str, str]] = []
    failures: list[Failure] = []
    used: set[str] = set()
    transient = False
    try:
        for label, build in _scene_builders(task, skipped):
            try:
                scene = build()
                name = _scene_name(task, scene, label, used)
                path = pathlib.Path(task.scenes_dir) / f"{name}.mcap"
                path.parent.mkdir(parents=True, exist_ok=True)
                write_scene(path, scene)
                scenes.append((name, str(path)))
                if warning := scene.metadata.get("clock_warning"):
                    print(warning, file=sys.stderr, flush=True)  # one line per scene
            except Exception as exc:
                transient |= isinstance(exc, _TRANSIENT)
                failures.append(failure_from(task.input, label, "convert", exc))
    except Exception as exc:  # the file itself (unreadable framing, not the format, ...)
        transient |= isinstance(exc, _TRANSIENT)
        failures.append(failure_from(task.input, "", "convert", exc))
    failures += [
        Failure(task.input, "", "convert", "ConversionError", one_line(m)) for m in skipped.what
    ]
    if not scenes and not failures:
        failures.append(
            Failure(task.input, "", "convert", "ConversionError", "the file holds no scene")
        )
    if not transient:
        with contextlib.suppress(OSError):  # no marker: the file is converted again
            write_convert_marker(task, scenes, failures, _also_read(task))
    return ConvertOutcome(task, tuple(scenes), tuple(failures), time.perf_counter() - start)


def _source(task: ConvertTask) -> tuple[SourceSpec, SourceInput]:
    spec = SOURCES[task.kind]
    source = SourceInput(
        source=task.kind,
        path=pathlib.Path(task.input),
        extra=tuple(pathlib.Path(e) for e in task.extra),
        map=None if task.map_osm is None else pathlib.Path(task.map_osm),
    )
    return spec, source


def _scene_builders(
    task: ConvertTask, skipped: Skipped
) -> Iterator[tuple[str, Callable[[], Scene]]]:
    """(label, build) per scene of the input; ``build()`` converts that one scene.

    A label names the scene in failures before it is built: the input's name for
    one-scene sources, ``NAME/LABEL`` (e.g. ``NAME/record-K`` of a Waymo file) for
    sources whose inputs hold several scenes. Records of a multi-scene input that cannot
    be read fail alone (``skip_bad``); a one-scene input fails whole.
    """
    spec, source = _source(task)
    options = ReadOptions(paths=task.paths, skip_bad=spec.multi_scene, time_step=task.time_step)
    for label, build in spec.scenes(source, options, skipped):
        yield (f"{task.name}/{label}" if spec.multi_scene else task.name), build


def _also_read(task: ConvertTask) -> list[pathlib.Path]:
    """The files a conversion reads besides its input (maps, other track files, the
    other files of a log), so that a change to any of them converts it again."""
    spec, source = _source(task)
    return [pathlib.Path(p) for p in spec.companions(source)]


def _scene_name(task: ConvertTask, scene: Scene, label: str, used: set[str]) -> str:
    """A converted scene's name: the input's name for one-scene sources; for sources whose
    inputs hold several scenes ``NAME/SCENARIO_ID`` (the label's last part added when an
    id repeats); an input that is itself the scenario (an Argoverse 2 Sensor log folder
    named by its log id) keeps ``NAME``."""
    if not SOURCES[task.kind].multi_scene:
        return task.name
    scenario = safe_name(scene.metadata.get("scenario_id", ""), label.rsplit("/", 1)[-1])
    # the input's own name is the last part of its task name (``av2-sensor/LOG``)
    own = task.name.rsplit("/", 1)[-1]
    name = task.name if scenario == own else f"{task.name}/{scenario}"
    if name in used:
        name = f"{name}-{label.rsplit('-', 1)[-1]}"
    used.add(name)
    return name
