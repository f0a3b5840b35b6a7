"""The task functions that workers run: convert one raw file, replay one scene.

Both are module-level functions of one frozen dataclass argument, so every engine can
pickle them; both never raise for a bad input: every exception becomes a
:class:`~replay.batch.records.Failure` in the outcome.
"""

from __future__ import annotations

import contextlib
import pathlib
import time
import traceback
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from base.atomic import safe_name
from replay.batch.markers import write_convert_marker, write_parquet, write_replay_marker
from replay.batch.records import (
    ConvertOutcome,
    ConvertTask,
    Failure,
    ReplayOutcome,
    ReplayTask,
    SceneDone,
)
from replay.egos import ALL_EGOS
from replay.errors import ReplayError, SceneFormatError
from replay.reader import open_scene
from replay.user_errors import user_errors
from replay.worker import replay_scene

if TYPE_CHECKING:
    from risk.frame import Scene

CONVERT_KINDS: tuple[str, ...] = ("waymo", "av2", "commonroad", "interaction")
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
        from converters.mcap_io import write_scene
        from converters.tracks import Skipped
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


def _scene_builders(task: ConvertTask, skipped: Any) -> Iterator[tuple[str, Callable[[], Scene]]]:
    """(label, build) per scene of the file; ``build()`` converts that one scene.

    A label names the scene in failures before it is built: the input's name for
    one-scene formats, ``NAME/record-K`` for the records of a Waymo file.
    """
    path = pathlib.Path(task.input)
    if task.kind == "waymo":
        from converters import waymo

        for item in waymo.read_scenarios(path, skip_bad=True, skipped=skipped):

            def build(item: Any = item) -> Scene:
                return waymo.scenario_to_scene(
                    item.scenario, source=path, record=item.index, paths=task.paths
                )

            yield f"{task.name}/record-{item.index}", build
    elif task.kind == "av2":
        from converters import av2

        yield task.name, lambda: av2.parquet_to_scene(path, paths=task.paths)
    elif task.kind == "commonroad":
        from converters import commonroad

        yield task.name, lambda: commonroad.read_scene(path, paths=task.paths)
    elif task.kind == "interaction":
        from converters import interaction

        map_osm = _interaction_map(path, task.map_osm)
        yield task.name, lambda: interaction.read_scene(path, map_osm, paths=task.paths)
    else:  # pragma: no cover - the CLI offers only CONVERT_KINDS
        raise ReplayError(f"unknown --convert kind {task.kind!r}; valid: {CONVERT_KINDS}")


def _also_read(task: ConvertTask) -> list[pathlib.Path]:
    """The files a conversion reads besides its input: the map JSONs beside an
    Argoverse 2 parquet, the Lanelet2 map of an INTERACTION CSV."""
    path = pathlib.Path(task.input)
    if task.kind == "av2":
        return sorted(path.parent.glob("log_map_archive_*.json"))
    if task.kind == "interaction":
        with contextlib.suppress(Exception):  # no map: the conversion failed already
            return [_interaction_map(path, task.map_osm)]
    return []


def _interaction_map(csv_path: pathlib.Path, given: str | None) -> pathlib.Path:
    """The Lanelet2 map of an INTERACTION track file: ``--map``, else the only ``*.osm``
    beside the CSV (the dataset keeps maps apart: then ``--map`` is needed)."""
    if given is not None:
        return pathlib.Path(given)
    found = sorted(csv_path.parent.glob("*.osm"))
    if len(found) != 1:
        from converters.errors import ConversionError

        what = "no" if not found else f"{len(found)}"
        raise ConversionError(
            f"{csv_path}: {what} .osm map beside it; name the map with --map MAP.osm"
        )
    return found[0]


def _scene_name(task: ConvertTask, scene: Scene, label: str, used: set[str]) -> str:
    """A converted scene's name: the input's name for one-scene formats; for a Waymo
    file ``NAME/SCENARIO_ID`` (record index added when an id repeats)."""
    if task.kind != "waymo":
        return task.name
    scenario = safe_name(scene.metadata.get("scenario_id", ""), label.rsplit("/", 1)[-1])
    name = f"{task.name}/{scenario}"
    if name in used:
        name = f"{name}-{label.rsplit('-', 1)[-1]}"
    used.add(name)
    return name


def failure_from(input_: str, scene: str, stage: str, exc: BaseException) -> Failure:
    """A Failure from an exception; the stage follows the exception type where it says
    more than the step we were in (a damaged MCAP found mid-replay is a read error)."""
    # Imported on a failure only: the recordings package loads rerun (about 1 s with
    # ``python -X importtime``), which a worker that writes no recording need not pay.
    from recordings.errors import RecordingError

    if isinstance(exc, SceneFormatError):
        stage = "read"
    elif isinstance(exc, RecordingError):
        stage = "record"
    reason = one_line(str(exc)) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in reason:
        reason = f"{reason}: {exc.filename}"
    if not isinstance(exc, user_errors()):
        reason += _where(exc)  # an unexpected error: say where, for a bug report
    return Failure(input_, scene, stage, type(exc).__name__, reason)


def one_line(text: str, limit: int = 400) -> str:
    line = " ".join(text.split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _where(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    last = frames[-1]
    return f" (at {pathlib.Path(last.filename).name}:{last.lineno} in {last.name})"
