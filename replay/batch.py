"""Batch runs over whole datasets: convert, replay and tabulate every scene, in parallel.

One **task** is one unit of work a worker runs from start to finish:

- a *convert task* turns one raw dataset file (``--convert waymo|av2|commonroad|
  interaction``) into MCAP scenes under ``OUT/scenes/`` (a Waymo TFRecord may hold many
  scenarios: one scene each);
- a *replay task* replays one MCAP scene through every model and the cascade
  (:func:`replay.engine.run_scene`) into its per-scene table (and, with ``rrd``, its
  Rerun recording).

The driver (:func:`run_batch`) plans the tasks, hands them to an :class:`Engine`, starts
the replay of a converted file's scenes as soon as its conversion is back, merges the
per-scene tables and runs the dataset statistics of ``replay stats`` on them.

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

    scenes/NAME.mcap          converted scenes (only with --convert)
    tables/NAME.parquet       per-scene agents tables (replay.tables' columns + scene)
    frames/NAME.parquet       per-scene frames tables (replay.stats: cascade per frame)
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

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import csv
import dataclasses
import functools
import hashlib
import io
import json
import multiprocessing
import os
import pathlib
import re
import sys
import tempfile
import time
import traceback
import warnings
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from replay.errors import ReplayError
from risk.cascade import CascadeConfig

if TYPE_CHECKING:
    from risk.frame import Scene

MARKER_FORMAT = 1
CONVERT_KINDS: tuple[str, ...] = ("waymo", "av2", "commonroad", "interaction")
ENGINES: tuple[str, ...] = ("local", "ray")
RAY_MISSING = "Ray is not installed; install it with: pip install 'riskreplay[ray]'"
STAGES: tuple[str, ...] = ("setup", "convert", "read", "replay", "record", "write", "worker")
"""Where a scene can fail: loading riskreplay in the worker (a cluster node without the
package), converting, reading the MCAP, replaying (models, cascade, missing ego), writing
the recording, writing the tables or marker, and the worker process itself dying."""

FAILURE_COLUMNS: tuple[str, ...] = ("input", "scene", "stage", "error_type", "reason")
SCENE_COLUMNS: tuple[str, ...] = (
    "scene", "input", "status", "frames", "skipped_frames", "agents", "seconds", "table",
    "recording",
)  # fmt: skip

# Files each converter reads, when a folder is given (searched recursively).
_PATTERNS: dict[str | None, tuple[str, ...]] = {
    None: ("*.mcap",),
    "waymo": ("*.tfrecord", "*.tfrecord-*", "*.tfrecords"),
    "av2": ("scenario_*.parquet",),
    "commonroad": ("*.xml",),
    "interaction": ("*.csv",),
}
_KNOWN_SUFFIX = re.compile(r"\.(mcap|parquet|xml|csv|tfrecords?)$", re.IGNORECASE)
_TRANSIENT = (OSError, MemoryError)


# ---------------------------------------------------------------------- settings
@dataclass(frozen=True)
class BatchSettings:
    """What decides a batch run's outputs (besides its inputs)."""

    cascade: CascadeConfig
    rrd: bool = False  # also write a Rerun recording per scene
    convert: str | None = None  # raw dataset kind of the inputs; None: MCAP scenes
    paths: str = "map"  # converters' path mode (map or hindsight)
    map_osm: pathlib.Path | None = None  # the Lanelet2 map of INTERACTION inputs

    def replay_digest(self) -> str:
        """Hash of everything that decides a per-scene table: the cascade, the models, the
        package version. (``rrd`` is not in it: a marker lists the files it has.)"""
        from risk import MODELS

        return _digest(
            {
                "format": MARKER_FORMAT,
                "version": _package_version(),
                "cascade": self.cascade.to_dict(),
                "models": list(MODELS),
            }
        )

    def convert_digest(self) -> str:
        """Hash of everything that decides a conversion: kind, path mode, the map file."""
        map_fp = None if self.map_osm is None else _fingerprint(self.map_osm)
        return _digest(
            {
                "format": MARKER_FORMAT,
                "version": _package_version(),
                "convert": self.convert,
                "paths": self.paths,
                "map": None if self.map_osm is None else [str(self.map_osm), *map_fp],
            }
        )


def _digest(data: dict[str, Any]) -> str:
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _package_version() -> str:
    from replay import __version__

    return __version__


@dataclass(frozen=True)
class Layout:
    """Where a batch run writes (see the module docstring)."""

    root: pathlib.Path

    @property
    def scenes(self) -> pathlib.Path:
        return self.root / "scenes"

    @property
    def tables(self) -> pathlib.Path:
        return self.root / "tables"

    @property
    def frames(self) -> pathlib.Path:
        return self.root / "frames"

    @property
    def recordings(self) -> pathlib.Path:
        return self.root / "recordings"

    @property
    def done(self) -> pathlib.Path:
        return self.root / ".done"

    @property
    def stats(self) -> pathlib.Path:
        return self.root / "stats"

    @property
    def failures_csv(self) -> pathlib.Path:
        return self.root / "failures.csv"

    @property
    def scenes_csv(self) -> pathlib.Path:
        return self.root / "scenes.csv"

    def scene_mcap(self, name: str) -> pathlib.Path:
        return self.scenes / f"{name}.mcap"

    def table(self, name: str) -> pathlib.Path:
        return self.tables / f"{name}.parquet"

    def frames_table(self, name: str) -> pathlib.Path:
        return self.frames / f"{name}.parquet"

    def recording(self, name: str) -> pathlib.Path:
        return self.recordings / f"{name}.rrd"

    def replay_marker(self, name: str) -> pathlib.Path:
        return self.done / f"{name}.json"

    def convert_marker(self, name: str) -> pathlib.Path:
        return self.done / "convert" / f"{name}.json"


# ---------------------------------------------------------------------- tasks, outcomes
@dataclass(frozen=True)
class Failure:
    """One failed scene (or input): a row of ``failures.csv``."""

    input: str  # the file the user's inputs named
    scene: str  # the scene's name; "" when the whole input failed before naming scenes
    stage: str  # one of STAGES
    error_type: str  # exception class name
    reason: str  # one line


@dataclass(frozen=True)
class ReplayTask:
    """Replay one MCAP scene into its table (and recording). Paths are strings so that
    the task reads the same on every node of a cluster (a shared file system)."""

    input: str
    scene: str  # the MCAP file
    name: str
    table: str  # agents table (replay.tables columns + scene)
    frames_table: str  # frames table of replay.stats (cascade counts and times per frame)
    recording: str | None
    marker: str
    digest: str
    cascade: CascadeConfig


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
    """Convert one raw dataset file into MCAP scenes under ``scenes_dir``."""

    input: str
    name: str
    kind: str
    paths: str
    map_osm: str | None
    scenes_dir: str
    marker: str
    digest: str


@dataclass(frozen=True)
class ConvertOutcome:
    task: ConvertTask
    scenes: tuple[tuple[str, str], ...]  # (scene name, MCAP path) of every scene written
    failures: tuple[Failure, ...]
    seconds: float


# ---------------------------------------------------------------------- discovery
@dataclass(frozen=True)
class InputFile:
    """One input file and the unique name its outputs get."""

    path: pathlib.Path  # absolute
    name: str


def discover(
    inputs: Sequence[str | os.PathLike[str]],
    *,
    convert: str | None = None,
    exclude: pathlib.Path | None = None,
) -> list[InputFile]:
    """The input files named by ``inputs`` (files, or folders searched recursively for
    ``*.mcap``, or for the raw files of ``convert``), each with a unique output name.

    A name is the file name without its known suffix, restricted to letters, digits and
    ``._-``; names that collide (same file name in two folders) get ``-`` and 8 hex
    digits of a hash of the full path, so a rerun with the same inputs finds the same
    names. Files under ``exclude`` (the output folder) are ignored. Raises ReplayError
    for a missing input or when nothing is found.
    """
    patterns = _PATTERNS[convert]
    found: dict[pathlib.Path, None] = {}
    for raw in inputs:
        path = pathlib.Path(raw).expanduser().absolute()
        if path.is_file():
            found[path] = None
        elif path.is_dir():
            for f in _walk(path, patterns, exclude):
                found[f] = None
        else:
            raise ReplayError(f"{raw}: no such file or folder")
    if not found:
        what = ", ".join(patterns)
        shown = ", ".join(str(i) for i in inputs[:3]) + (", ..." if len(inputs) > 3 else "")
        hint = "" if convert else " (raw dataset files need --convert KIND)"
        raise ReplayError(f"no input files ({what}) found in {shown}{hint}")
    return _unique_names(list(found))


def _walk(
    folder: pathlib.Path, patterns: Sequence[str], exclude: pathlib.Path | None
) -> list[pathlib.Path]:
    hits: set[pathlib.Path] = set()
    for pattern in patterns:
        hits.update(p for p in folder.rglob(pattern) if p.is_file())
    ex = None if exclude is None else exclude.absolute()
    return sorted(p for p in hits if ex is None or not p.is_relative_to(ex))


def _unique_names(paths: list[pathlib.Path]) -> list[InputFile]:
    base = [_safe_name(_KNOWN_SUFFIX.sub("", p.name).replace(".tfrecord", "")) for p in paths]
    counts: dict[str, int] = {}
    for b in base:
        counts[b.lower()] = counts.get(b.lower(), 0) + 1
    out = []
    for p, b in zip(paths, base, strict=True):
        if counts[b.lower()] > 1:
            b = f"{b}-{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"
        out.append(InputFile(p, b))
    return out


def _safe_name(name: str, fallback: str = "scene") -> str:
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    return cleaned or fallback


# ---------------------------------------------------------------------- markers
def _fingerprint(path: str | os.PathLike[str]) -> tuple[int, int]:
    st = os.stat(path)
    return st.st_size, st.st_mtime_ns


def _file_entry(path: str | os.PathLike[str]) -> dict[str, Any]:
    size, mtime_ns = _fingerprint(path)
    return {"path": os.fspath(path), "size": size, "mtime_ns": mtime_ns}


def _entry_intact(entry: Any, *, check_time: bool = True) -> bool:
    """True when a marker's file entry (path, size, mtime_ns) still matches the file."""
    try:
        size, mtime_ns = _fingerprint(entry["path"])
        return size == entry["size"] and (not check_time or mtime_ns == entry["mtime_ns"])
    except (OSError, KeyError, TypeError):
        return False


def _read_marker(path: pathlib.Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == MARKER_FORMAT else None


def completed_scene(
    marker: pathlib.Path, scene: pathlib.Path, digest: str, *, rrd: bool
) -> SceneDone | None:
    """The scene's result when its outputs are complete (module docstring), else None."""
    data = _read_marker(marker)
    if data is None or data.get("settings") != digest:
        return None
    source = data.get("scene", {})
    if source.get("path") != os.fspath(scene) or not _entry_intact(source):
        return None
    outputs = data.get("outputs", {})
    if not {"table", "frames"} <= outputs.keys() or (rrd and "recording" not in outputs):
        return None
    # Outputs are checked by size only: a copy of OUT elsewhere keeps its sizes.
    if not all(_entry_intact(e, check_time=False) for e in outputs.values()):
        return None
    try:
        return SceneDone(
            name=str(data["name"]),
            input=str(data["input"]),
            table=str(outputs["table"]["path"]),
            frames_table=str(outputs["frames"]["path"]),
            recording=str(outputs["recording"]["path"]) if "recording" in outputs else None,
            frames=int(data["frames"]),
            skipped_frames=int(data["skipped_frames"]),
            agents=int(data["agents"]),
            seconds=float(data["seconds"]),
            status="skipped",
        )
    except (KeyError, TypeError, ValueError):
        return None


def completed_conversion(
    marker: pathlib.Path, source: pathlib.Path, digest: str
) -> tuple[list[tuple[str, str]], list[Failure]] | None:
    """(scenes, failures) of a complete conversion of ``source``, else None."""
    data = _read_marker(marker)
    if data is None or data.get("settings") != digest:
        return None
    entry = data.get("input", {})
    if entry.get("path") != os.fspath(source) or not _entry_intact(entry):
        return None
    try:
        scenes = [(str(s["name"]), str(s["path"])) for s in data["scenes"]]
        if not all(_entry_intact(s) for s in data["scenes"]):
            return None
        failures = [Failure(**f) for f in data["failures"]]
    except (KeyError, TypeError, ValueError):
        return None
    return scenes, failures


@functools.cache
def _file_mode() -> int:
    """The mode a new file gets from the umask (``mkstemp`` makes its files 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _write_json(path: pathlib.Path, data: dict[str, Any]) -> None:
    _atomic_write(path, json.dumps(data, indent=1, sort_keys=True) + "\n")


def _atomic_write(path: pathlib.Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same folder + os.replace."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)
        os.chmod(tmp, _file_mode())
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------------- worker side
def init_worker() -> None:
    """Process-pool initializer: one thread per worker for the libraries that would
    otherwise start one per core each (parallelism comes from the processes). Runs
    before polars is imported in a spawned worker, which reads it at import."""
    for var in ("POLARS_MAX_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def replay_one(task: ReplayTask) -> ReplayOutcome:
    """Replay one scene into its tables (and recording), then write its done-marker.

    Never raises for a bad scene: every exception becomes the outcome's Failure.
    """
    start = time.perf_counter()
    stage = "setup"
    try:
        from replay.engine import ReplayWarning, run_scene
        from replay.reader import open_scene
        from replay.stats import StatsSink

        stage = "read"
        reader = open_scene(task.scene)
        stage = "replay"
        collect = StatsSink(task.name)
        sinks: list[Any] = [collect]
        if task.recording is not None:
            from recordings import SceneRecorder

            pathlib.Path(task.recording).parent.mkdir(parents=True, exist_ok=True)
            sinks.append(SceneRecorder(task.recording))
        # Warnings (frames without the ego) are counted in scenes.csv, not printed by
        # every worker over the progress bar.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ReplayWarning)
            summary = run_scene(reader, sinks=sinks, cascade=task.cascade, progress=False)
        stage = "write"
        _write_parquet(pathlib.Path(task.table), collect.agents())
        _write_parquet(pathlib.Path(task.frames_table), collect.frames())
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
        _write_replay_marker(task, done)
        return ReplayOutcome(task, done, None)
    except Exception as exc:
        return ReplayOutcome(task, None, _failure(task.input, task.name, stage, exc))


def _write_parquet(path: pathlib.Path, df: Any) -> None:
    """A polars DataFrame to ``path`` atomically (temp file in the folder, os.replace)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        df.write_parquet(tmp, compression="zstd")
        os.chmod(tmp, _file_mode())
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise


def _write_replay_marker(task: ReplayTask, done: SceneDone) -> None:
    outputs = {"table": _file_entry(task.table), "frames": _file_entry(task.frames_table)}
    if task.recording is not None:
        outputs["recording"] = _file_entry(task.recording)
    _write_json(
        pathlib.Path(task.marker),
        {
            "format": MARKER_FORMAT,
            "name": task.name,
            "input": task.input,
            "scene": _file_entry(task.scene),
            "settings": task.digest,
            "outputs": outputs,
            "frames": done.frames,
            "skipped_frames": done.skipped_frames,
            "agents": done.agents,
            "seconds": round(done.seconds, 4),
        },
    )


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
        failure = _failure(task.input, "", "setup", exc)
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
                failures.append(_failure(task.input, label, "convert", exc))
    except Exception as exc:  # the file itself (unreadable framing, not the format, ...)
        transient |= isinstance(exc, _TRANSIENT)
        failures.append(_failure(task.input, "", "convert", exc))
    failures += [
        Failure(task.input, "", "convert", "ConversionError", _one_line(m)) for m in skipped.what
    ]
    if not scenes and not failures:
        failures.append(
            Failure(task.input, "", "convert", "ConversionError", "the file holds no scene")
        )
    if not transient:
        with contextlib.suppress(OSError):  # no marker: the file is converted again
            _write_convert_marker(task, scenes, failures)
    return ConvertOutcome(task, tuple(scenes), tuple(failures), time.perf_counter() - start)


def _write_convert_marker(
    task: ConvertTask, scenes: list[tuple[str, str]], failures: list[Failure]
) -> None:
    _write_json(
        pathlib.Path(task.marker),
        {
            "format": MARKER_FORMAT,
            "input": _file_entry(task.input),
            "settings": task.digest,
            "scenes": [{"name": n, **_file_entry(p)} for n, p in scenes],
            "failures": [dataclasses.asdict(f) for f in failures],
        },
    )


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
    scenario = _safe_name(scene.metadata.get("scenario_id", ""), label.rsplit("/", 1)[-1])
    name = f"{task.name}/{scenario}"
    if name in used:
        name = f"{name}-{label.rsplit('-', 1)[-1]}"
    used.add(name)
    return name


def _failure(input_: str, scene: str, stage: str, exc: BaseException) -> Failure:
    """A Failure from an exception; the stage follows the exception type where it says
    more than the step we were in (a damaged MCAP found mid-replay is a read error)."""
    from recordings.errors import RecordingError
    from replay.cli import user_errors
    from replay.errors import SceneFormatError

    if isinstance(exc, SceneFormatError):
        stage = "read"
    elif isinstance(exc, RecordingError):
        stage = "record"
    reason = _one_line(str(exc)) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in reason:
        reason = f"{reason}: {exc.filename}"
    if not isinstance(exc, user_errors()):
        reason += _where(exc)  # an unexpected error: say where, for a bug report
    return Failure(input_, scene, stage, type(exc).__name__, reason)


def _one_line(text: str, limit: int = 400) -> str:
    line = " ".join(text.split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _where(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    last = frames[-1]
    return f" (at {pathlib.Path(last.filename).name}:{last.lineno} in {last.name})"


# ---------------------------------------------------------------------- engines
class WorkerDied(ReplayError):
    """The worker process running a task died (a crash in native code, out of memory)."""

    def __init__(self) -> None:
        super().__init__(
            "the worker process died while running this task (a crash in native code or "
            "out of memory)"
        )


class Engine(Protocol):
    """Runs task functions somewhere; the driver knows nothing else about it.

    ``submit(fn, task)`` queues ``fn(task)``; ``results()`` blocks until at least one
    queued call is done and returns ``(task, outcome)`` pairs, where the outcome is what
    ``fn`` returned or the exception that kept it from returning (``[]`` when nothing is
    pending); ``close(cancel=...)`` releases the workers, dropping queued calls when
    ``cancel`` is set.
    """

    name: str
    workers: int  # task slots (a cluster's CPUs for Ray)

    @property
    def pending(self) -> int: ...

    def submit(self, fn: Callable[[Any], Any], task: Any) -> None: ...

    def results(self) -> list[tuple[Any, Any]]: ...

    def close(self, *, cancel: bool = False) -> None: ...


def default_workers() -> int:
    """The CPUs this process may run on (the affinity mask, where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def _quiet_worker() -> None:
    """Initializer of local workers: leave Ctrl-C to the driver, which stops queueing and
    lets running tasks finish (their outputs are atomic), and set thread counts."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    init_worker()


class LocalEngine:
    """Worker processes on this machine (``ProcessPoolExecutor``, ``spawn`` start).

    When a worker dies, its pool is broken and every task running there fails with it;
    the engine starts a fresh pool and runs those tasks again one at a time, alone, so
    that only the task that kills its worker is reported (as :class:`WorkerDied`), while
    the other tasks wait. A pool found broken when submitting (a worker killed while
    idle) is replaced at once.
    """

    name = "local"

    def __init__(self, workers: int | None = None) -> None:
        self.workers = default_workers() if workers is None else int(workers)
        if self.workers < 1:
            raise ReplayError(f"--workers must be >= 1, got {self.workers}")
        self._pool = self._new_pool()
        # future -> (function, task, the pool it runs in)
        self._running: dict[cf.Future, tuple[Callable, Any, cf.ProcessPoolExecutor]] = {}
        self._suspects: deque[tuple[Callable, Any]] = deque()  # lost with a dead pool
        self._held: deque[tuple[Callable, Any]] = deque()  # waiting while suspects run
        self._alone = False  # one suspect is running alone

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_quiet_worker,
        )

    def _replace_pool(self) -> None:
        self._pool.shutdown(wait=False)
        self._pool = self._new_pool()

    @property
    def pending(self) -> int:
        return len(self._running) + len(self._suspects) + len(self._held)

    def submit(self, fn: Callable[[Any], Any], task: Any) -> None:
        if self._suspects or self._alone:
            self._held.append((fn, task))
        else:
            self._start(fn, task)

    def _start(self, fn: Callable[[Any], Any], task: Any) -> None:
        try:
            future = self._pool.submit(fn, task)
        except cf.process.BrokenProcessPool:
            self._replace_pool()
            future = self._pool.submit(fn, task)
        self._running[future] = (fn, task, self._pool)

    def results(self) -> list[tuple[Any, Any]]:
        out: list[tuple[Any, Any]] = []
        self._schedule()
        while not out and self._running:
            done, _ = cf.wait(self._running, return_when=cf.FIRST_COMPLETED)
            dead = {self._running[f][2] for f in done if _lost(f)}
            if dead:  # every call in a dead pool is lost with it: collect them all
                lost = [f for f, (_, _, pool) in self._running.items() if pool in dead]
                done = set(done) | cf.wait(lost)[0]
            broken: list[tuple[Callable, Any]] = []
            for f in done:
                fn, task, _ = self._running.pop(f)
                if _lost(f):
                    broken.append((fn, task))
                else:
                    exc = f.exception()
                    out.append((task, f.result() if exc is None else exc))
            if broken and self._alone:  # it ran alone, so it is the culprit
                out += [(task, WorkerDied()) for _, task in broken]
            else:
                self._suspects.extend(broken)
            if self._pool in dead:
                self._replace_pool()
            self._alone = self._alone and bool(self._running)
            self._schedule()
        return out

    def _schedule(self) -> None:
        if self._running:
            return
        if self._suspects:
            self._start(*self._suspects.popleft())
            self._alone = True
        else:
            while self._held:
                self._start(*self._held.popleft())

    def close(self, *, cancel: bool = False) -> None:
        if cancel:
            self._held.clear()
            self._suspects.clear()
        self._pool.shutdown(wait=True, cancel_futures=cancel)


def _lost(future: cf.Future) -> bool:
    """True when the call was lost with its pool (a worker process died)."""
    return isinstance(future.exception(), cf.process.BrokenProcessPool)


class RayEngine:
    """Ray tasks on the cluster at ``address`` (``auto``, ``ray://host:10001``, ...) or,
    without an address, on a local Ray instance with ``workers`` CPUs. A Ray instance
    that is already initialised in this process is used as it is (and left running).

    Ray retries a task once when its worker dies (``max_retries=1``); a task lost twice
    comes back as the exception Ray raises for it.
    """

    name = "ray"

    def __init__(self, workers: int | None = None, address: str | None = None) -> None:
        ray = _import_ray()
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            import logging

            kwargs: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": False}
            try:
                if address:
                    ray.init(address=address, **kwargs)
                else:
                    cpus = workers or default_workers()
                    ray.init(num_cpus=cpus, include_dashboard=False, **kwargs)
            except Exception as exc:  # Ray raises ConnectionError, RuntimeError, ...
                where = f"the Ray cluster at {address}" if address else "a local Ray instance"
                raise ReplayError(
                    f"could not start or reach {where}: {_one_line(str(exc))}"
                ) from None
            self._started = True
        self.workers = int(ray.cluster_resources().get("CPU", workers or 1))
        self._remote: dict[Callable, Any] = {}
        self._running: dict[Any, Any] = {}  # ObjectRef -> task

    @property
    def pending(self) -> int:
        return len(self._running)

    def submit(self, fn: Callable[[Any], Any], task: Any) -> None:
        if fn not in self._remote:
            self._remote[fn] = self._ray.remote(num_cpus=1, max_retries=1)(fn)
        self._running[self._remote[fn].remote(task)] = task

    def results(self) -> list[tuple[Any, Any]]:
        if not self._running:
            return []
        refs = list(self._running)
        ready, rest = self._ray.wait(refs, num_returns=1)
        if rest:  # collect whatever else is ready too, without waiting
            more, _ = self._ray.wait(rest, num_returns=len(rest), timeout=0)
            ready += more
        out = []
        for ref in ready:
            task = self._running.pop(ref)
            try:
                out.append((task, self._ray.get(ref)))
            except Exception as exc:  # the task's worker died twice, or Ray lost it
                out.append((task, exc))
        return out

    def close(self, *, cancel: bool = False) -> None:
        if cancel:
            for ref in self._running:
                with contextlib.suppress(Exception):
                    self._ray.cancel(ref)
            self._running.clear()
        if self._started:
            self._ray.shutdown()


def _import_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise ReplayError(RAY_MISSING) from None
    return ray


def make_engine(name: str, *, workers: int | None = None, address: str | None = None) -> Engine:
    """The engine called ``name`` (one of :data:`ENGINES`)."""
    if name == "local":
        if address:
            raise ReplayError("--ray-address needs --engine ray")
        return LocalEngine(workers)
    if name == "ray":
        if workers is not None and workers < 1:
            raise ReplayError(f"--workers must be >= 1, got {workers}")
        return RayEngine(workers, address)
    raise ReplayError(f"unknown engine {name!r}; valid: {', '.join(ENGINES)}")


# ---------------------------------------------------------------------- the driver
@dataclass
class BatchReport:
    """What a batch run did; ``scenes`` holds replayed and skipped scenes, by name."""

    out_dir: pathlib.Path
    engine: str
    workers: int
    inputs: int  # input files
    scenes: list[SceneDone]
    failures: list[Failure]
    conversions: int = 0  # files converted in this run
    conversions_skipped: int = 0  # files whose conversion was complete already
    seconds: float = 0.0  # the whole run, statistics included
    run_seconds: float = 0.0  # converting and replaying (the engine's part)
    stats_files: list[pathlib.Path] = field(default_factory=list)

    @property
    def replayed(self) -> int:
        return sum(s.status == "replayed" for s in self.scenes)

    @property
    def skipped(self) -> int:
        return sum(s.status == "skipped" for s in self.scenes)

    @property
    def all_failed(self) -> bool:
        return not self.scenes and bool(self.failures)


class _Run:
    """The state of one batch run: planned tasks, results so far, the progress bar."""

    def __init__(self, layout: Layout, settings: BatchSettings) -> None:
        self.layout = layout
        self.settings = settings
        self.replay_digest = settings.replay_digest()
        self.convert_digest = settings.convert_digest() if settings.convert else ""
        self.done: list[SceneDone] = []
        self.failures: list[Failure] = []
        self.replay_todo: list[ReplayTask] = []
        self.convert_todo: list[ConvertTask] = []
        self.conversions_skipped = 0

    def plan(self, files: Sequence[InputFile]) -> None:
        """Sort every input into complete (skipped) and to-do."""
        for f in files:
            if self.settings.convert is None:
                self.plan_scene(f.name, str(f.path), f.path)
                continue
            marker = self.layout.convert_marker(f.name)
            prior = completed_conversion(marker, f.path, self.convert_digest)
            if prior is None:
                self.convert_todo.append(self.convert_task(f, marker))
                continue
            self.conversions_skipped += 1
            scenes, failures = prior
            self.failures += failures
            for name, path in scenes:
                self.plan_scene(name, str(f.path), pathlib.Path(path))

    def plan_scene(self, name: str, input_: str, scene: pathlib.Path) -> None:
        marker = self.layout.replay_marker(name)
        prior = completed_scene(marker, scene, self.replay_digest, rrd=self.settings.rrd)
        if prior is not None:
            self.done.append(prior)
        else:
            self.replay_todo.append(self.replay_task(name, input_, scene))

    def replay_task(self, name: str, input_: str, scene: pathlib.Path) -> ReplayTask:
        lay = self.layout
        return ReplayTask(
            input=input_,
            scene=str(scene),
            name=name,
            table=str(lay.table(name)),
            frames_table=str(lay.frames_table(name)),
            recording=str(lay.recording(name)) if self.settings.rrd else None,
            marker=str(lay.replay_marker(name)),
            digest=self.replay_digest,
            cascade=self.settings.cascade,
        )

    def convert_task(self, f: InputFile, marker: pathlib.Path) -> ConvertTask:
        s = self.settings
        return ConvertTask(
            input=str(f.path),
            name=f.name,
            kind=str(s.convert),
            paths=s.paths,
            map_osm=None if s.map_osm is None else str(s.map_osm),
            scenes_dir=str(self.layout.scenes),
            marker=str(marker),
            digest=self.convert_digest,
        )


def run_batch(
    inputs: Sequence[str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    settings: BatchSettings,
    *,
    engine: str | Engine = "local",
    workers: int | None = None,
    ray_address: str | None = None,
    progress: bool = True,
) -> BatchReport:
    """Convert (with ``settings.convert``), replay and tabulate every input scene into
    ``out_dir``, then the dataset statistics over all complete scenes.

    ``engine``: ``local``, ``ray`` or an :class:`Engine` instance. Scenes complete from
    an earlier run are skipped (module docstring). Failures never stop the run; they are
    in the report and ``failures.csv``. Raises ReplayError only for bad arguments (no
    inputs, a missing input, Ray absent).
    """
    start = time.perf_counter()
    layout = Layout(pathlib.Path(out_dir).absolute())
    if layout.root.exists() and not layout.root.is_dir():
        raise ReplayError(f"{layout.root}: exists and is not a folder")
    files = discover(inputs, convert=settings.convert, exclude=layout.root)
    for folder in (layout.tables, layout.done):
        folder.mkdir(parents=True, exist_ok=True)
    run = _Run(layout, settings)
    run.plan(files)
    run_start = time.perf_counter()
    engine_name, n_workers = _execute(run, engine, workers, ray_address, progress)
    run_seconds = time.perf_counter() - run_start
    run.done.sort(key=lambda d: d.name)
    run.failures.sort(key=lambda f: (f.input, f.scene, f.stage))
    write_failures(layout.failures_csv, run.failures)
    write_scenes(layout.scenes_csv, run.done, run.failures)
    report = BatchReport(
        out_dir=layout.root,
        engine=engine_name,
        workers=n_workers,
        inputs=len(files),
        scenes=run.done,
        failures=run.failures,
        conversions=len(run.convert_todo),
        conversions_skipped=run.conversions_skipped,
        run_seconds=run_seconds,
    )
    if run.done:
        report.stats_files = dataset_stats(run.done, layout.stats, cascade=settings.cascade)
    report.seconds = time.perf_counter() - start
    return report


def _execute(
    run: _Run,
    engine: str | Engine,
    workers: int | None,
    ray_address: str | None,
    progress: bool,
) -> tuple[str, int]:
    """Run the planned tasks (none: no engine is started at all). Returns the engine's
    name and worker count. An engine passed in is left open for its owner."""
    if not (run.replay_todo or run.convert_todo):
        return (engine if isinstance(engine, str) else engine.name), 0
    own = isinstance(engine, str)
    eng = make_engine(engine, workers=workers, address=ray_address) if own else engine
    from tqdm import tqdm

    bar = tqdm(
        total=len(run.replay_todo), unit="scene", desc=f"batch ({eng.name}, {eng.workers} workers)",
        file=sys.stderr, disable=not progress, dynamic_ncols=True, smoothing=0.05,
    )  # fmt: skip
    try:
        with bar:
            _drive(run, eng, bar)
    except BaseException:
        if own:
            eng.close(cancel=True)
        raise
    if own:
        eng.close()
    return eng.name, eng.workers


def _drive(run: _Run, eng: Engine, bar: Any) -> None:
    """Feed the engine and collect its results until every task is back.

    At most a few tasks per worker are queued in the engine at a time (``in_flight``):
    enough to keep every worker busy, few enough that Ctrl-C drops the rest at once and
    that waiting on a cluster's results stays cheap with many thousands of scenes. A
    converted file's scenes go to the front of the queue, so replaying starts early.
    """
    queue: deque[tuple[Callable[[Any], Any], Any]] = deque(
        [(convert_one, t) for t in run.convert_todo] + [(replay_one, t) for t in run.replay_todo]
    )
    in_flight = 2 * max(1, eng.workers) + 2
    converting = len(run.convert_todo)
    while queue or eng.pending:
        while queue and eng.pending < in_flight:
            eng.submit(*queue.popleft())
        _postfix(bar, run, converting)
        for task, outcome in eng.results():
            if isinstance(task, ConvertTask):
                converting -= 1
                new = _converted(run, task, outcome)
                queue.extendleft((replay_one, t) for t in reversed(new))
                bar.total += len(new)
                bar.refresh()
            else:
                _replayed(run, task, outcome)
                bar.update()
    _postfix(bar, run, converting)


def _postfix(bar: Any, run: _Run, converting: int) -> None:
    info = {"failed": len(run.failures)}
    if converting:
        info["converting"] = converting
    bar.set_postfix(info, refresh=False)


def _converted(run: _Run, task: ConvertTask, outcome: Any) -> list[ReplayTask]:
    """Record a conversion's outcome; the replay tasks of the scenes it wrote."""
    if isinstance(outcome, BaseException):
        run.failures.append(_worker_failure(task.input, "", outcome))
        return []
    run.failures += outcome.failures
    return [run.replay_task(name, task.input, pathlib.Path(p)) for name, p in outcome.scenes]


def _replayed(run: _Run, task: ReplayTask, outcome: Any) -> None:
    if isinstance(outcome, BaseException):
        run.failures.append(_worker_failure(task.input, task.name, outcome))
    elif outcome.failure is not None:
        run.failures.append(outcome.failure)
    else:
        run.done.append(outcome.done)


def _worker_failure(input_: str, scene: str, exc: BaseException) -> Failure:
    reason = _one_line(str(exc)) or type(exc).__name__
    return Failure(input_, scene, "worker", type(exc).__name__, reason)


# ---------------------------------------------------------------------- outputs
def write_failures(path: pathlib.Path, failures: Iterable[Failure]) -> None:
    """``failures.csv``: one row per failure (a header only when nothing failed)."""
    rows = [dataclasses.astuple(f) for f in failures]
    _atomic_write(path, _csv_text(FAILURE_COLUMNS, rows))


def write_scenes(
    path: pathlib.Path, done: Iterable[SceneDone], failures: Iterable[Failure]
) -> None:
    """``scenes.csv``: every scene of the run, replayed, skipped or failed (failures of a
    whole input, before any scene had a name, are only in ``failures.csv``)."""
    rows: list[tuple] = [
        (d.name, d.input, d.status, d.frames, d.skipped_frames, d.agents, f"{d.seconds:.3f}",
         d.table, d.recording or "")
        for d in done
    ]  # fmt: skip
    rows += [(f.scene, f.input, "failed", "", "", "", "", "", "") for f in failures if f.scene]
    rows.sort(key=lambda r: r[0])
    _atomic_write(path, _csv_text(SCENE_COLUMNS, rows))


def _csv_text(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()


def read_failures(path: str | os.PathLike[str]) -> list[Failure]:
    """The rows of a ``failures.csv``."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [Failure(**row) for row in csv.DictReader(fh)]


def dataset_stats(
    done: Sequence[SceneDone], out_dir: pathlib.Path, *, cascade: CascadeConfig
) -> list[pathlib.Path]:
    """The statistics of ``replay stats`` over the merged per-scene tables of ``done``
    (tables, ``summary.json``, plots) into ``out_dir``; returns the files written.

    Scenes are merged in the order given (the driver sorts them by name), so the result
    does not depend on the order in which workers finished.
    """
    import polars as pl

    from replay.plots import plot_all
    from replay.stats import compute_stats, concat_agents, write_stats

    agents = concat_agents([pl.read_parquet(d.table) for d in done])
    frames = pl.concat([pl.read_parquet(d.frames_table) for d in done], how="vertical_relaxed")
    stats = compute_stats(
        agents,
        frames,
        stage_names=cascade.stage_names,
        tier_names=[t.name for t in cascade.tiers],
        baseline_threshold=cascade.baseline_threshold,
        inputs=sorted({d.input for d in done}),
    )
    written = write_stats(stats, out_dir)
    written |= plot_all(stats, out_dir)
    return sorted(written.values())
