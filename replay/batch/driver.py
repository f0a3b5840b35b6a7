"""The driver of a batch run: find the inputs, plan, run the tasks on an engine, write
the run's tables and the dataset statistics."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import pathlib
import re
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

from converters import sources
from converters.clock import TimeStep
from outputs.atomic import safe_name, write_text
from replay import __version__
from replay.analysis.stats import DEFAULT_ERRORS_MODEL
from replay.batch.markers import (
    MARKER_FORMAT,
    completed_conversion,
    completed_scene,
    fingerprint,
)
from replay.batch.records import ConvertTask, Failure, ReplayTask, SceneDone
from replay.batch.tasks import convert_one, replay_one
from replay.core.engine import EVERY_FRAME, Stride
from replay.errors import ReplayError
from replay.jobs.engines import Engine, make_engine
from replay.jobs.failures import (
    csv_text,
    one_line,
    worker_failure,
    write_failures,
)
from replay.jobs.scenes import file_identity
from risk.cascade import CascadeConfig
from risk.registry import MODELS

SCENE_COLUMNS: tuple[str, ...] = (
    "scene", "input", "status", "frames", "skipped_frames", "agents", "seconds", "table",
    "recording",
)  # fmt: skip

_KNOWN_SUFFIX = re.compile(r"\.(mcap|parquet|xml|csv|feather|tfrecords?)$", re.IGNORECASE)


@dataclass(frozen=True)
class BatchSettings:
    """What decides a batch run's outputs (besides its inputs)."""

    cascade: CascadeConfig
    rrd: bool = False  # also write a Rerun recording per scene
    convert: str | None = None  # source of every input; None: detected per file
    paths: str = "map"  # converters' path mode (map or hindsight)
    map_osm: pathlib.Path | None = None  # the Lanelet2 map of INTERACTION inputs
    ego: int | str | None = None  # None: each scene's recorded ego; "all": every mover
    every: Stride = EVERY_FRAME  # frame stride of the replays
    time_step: TimeStep = "auto"  # converters' time step: auto, file or seconds

    def replay_digest(self) -> str:
        """Hash of everything that decides a per-scene table: the cascade, the models, the
        package version. (``rrd`` is not in it: a marker lists the files it has.)"""
        return _digest(
            {
                "format": MARKER_FORMAT,
                "version": _package_version(),
                "cascade": self.cascade.to_dict(),
                "models": list(MODELS),
                "ego": self.ego,
                "every": [self.every.frames, self.every.seconds],
            }
        )

    def convert_digest(self) -> str:
        """Hash of everything that decides a conversion: kind, path mode, the map file, the
        time-step choice."""
        map_fp = None if self.map_osm is None else fingerprint(self.map_osm)
        return _digest(
            {
                "format": MARKER_FORMAT,
                "version": _package_version(),
                "convert": self.convert,
                "paths": self.paths,
                "time_step": self.time_step,
                "map": None if map_fp is None else [str(self.map_osm), *map_fp],
            }
        )


def _digest(data: dict[str, Any]) -> str:
    text = json.dumps(data, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _package_version() -> str:
    return __version__


@dataclass(frozen=True)
class Layout:
    """Where a batch run writes (see the docstring of replay.batch)."""

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


@dataclass(frozen=True)
class InputFile:
    """One input and the unique name its outputs get.

    ``source`` is the converter (a key of converters.sources.SOURCES) or None for an
    MCAP scene; ``extra`` more track files of the same scene, ``map`` a map found for it;
    ``problem`` says why no converter reads the file (it then becomes a failure)."""

    path: pathlib.Path  # absolute: a file, or an Argoverse 2 Sensor log folder
    name: str
    source: str | None = None
    extra: tuple[pathlib.Path, ...] = ()
    map: pathlib.Path | None = None
    problem: str | None = None


def discover(
    inputs: Sequence[str | os.PathLike[str]],
    *,
    convert: str | None = None,
    exclude: pathlib.Path | None = None,
) -> list[InputFile]:
    """The inputs named by ``inputs`` (files, log folders, or folders searched
    recursively), each with a unique output name.

    Without ``convert`` every file's source is detected (converters.sources.discover):
    MCAP scenes, raw files of every registered source (grouped into inputs, e.g. one
    recording's track CSVs), and data files no source reads (returned with a
    ``problem``). With ``convert`` every file matching that source's patterns is an input
    of it, unchecked (a file that is not one fails in its conversion).

    A name is the file name without its known suffix, restricted to letters, digits and
    ``._-``, under the sub-folders between the input folder that holds the file and the
    file (``sind/NAME`` for ``recorded/sind/NAME.xml`` found in ``recorded``), so that the
    outputs keep the inputs' folders: each dataset's scenes, tables and recordings stay
    in a folder of their own, and ``replay evaluate OUT/scenes`` groups them by dataset.
    Names that still collide (the same name twice in one folder, by case) get ``-`` and 8
    hex digits of a hash of the full path, so a rerun with the same inputs finds the same
    names. Files under ``exclude`` (the output folder) are ignored. Raises ReplayError
    for a missing input or when nothing is found.
    """
    try:
        if convert is None:
            found = sources.discover(inputs, exclude=exclude)
        else:
            found = _forced(inputs, sources.spec(convert), exclude)
    except FileNotFoundError as exc:
        raise ReplayError(f"{exc.filename}: no such file or folder") from None
    items = [InputFile(p, "") for p in found.scenes]
    items += [InputFile(i.path, "", i.source, i.extra, i.map) for i in found.inputs]
    items += [InputFile(p, "", problem=sources.unreadable_reason(p)) for p in found.unreadable]
    if not found.scenes and not found.inputs:
        patterns = (
            sources.SOURCES[convert].patterns
            if convert
            else sorted({p for s in sources.SOURCES.values() for p in s.patterns} | {"*.mcap"})
        )
        shown = ", ".join(str(i) for i in inputs[:3]) + (", ..." if len(inputs) > 3 else "")
        bad = f"; {len(found.unreadable)} file(s) no converter reads" if found.unreadable else ""
        raise ReplayError(f"no input files ({', '.join(patterns)}) found in {shown}{bad}")
    # A file found through two inputs (a folder and its sub-folder, a link) is one input.
    items = sorted({f.path: f for f in reversed(items)}.values(), key=lambda f: f.path)
    identities: set[tuple[int, int] | str] = set()
    kept = []
    for f in items:
        if file_identity(f.path) not in identities:
            identities.add(file_identity(f.path))
            kept.append(f)
    items = kept
    roots = [pathlib.Path(i).expanduser().absolute() for i in inputs]
    names = _unique_names([f.path for f in items], [r for r in roots if r.is_dir()])
    return [dataclasses.replace(f, name=n.name) for f, n in zip(items, names, strict=True)]


def _forced(
    inputs: Sequence[str | os.PathLike[str]], spec: sources.SourceSpec, exclude: pathlib.Path | None
) -> sources.Discovery:
    """Every file of ``inputs`` (folders: those matching ``spec.patterns``) as inputs of
    ``spec``."""
    files: dict[pathlib.Path, None] = {}
    for raw in inputs:
        path = pathlib.Path(raw).expanduser().absolute()
        if path.is_file():
            files[path] = None
        elif path.is_dir():
            for f in _walk(path, spec.patterns, exclude):
                files[f] = None
        else:
            raise FileNotFoundError(2, "no such file or folder", str(raw))
    chosen = list(files)
    if spec.group is not None:  # e.g. a log's pose file stands for its folder
        return sources.Discovery(inputs=spec.inputs(chosen))
    return sources.Discovery(inputs=[sources.SourceInput(source=spec.name, path=f) for f in chosen])


def _walk(
    folder: pathlib.Path, patterns: Sequence[str], exclude: pathlib.Path | None
) -> list[pathlib.Path]:
    hits: set[pathlib.Path] = set()
    for pattern in patterns:
        hits.update(p for p in folder.rglob(pattern) if p.is_file())
    ex = None if exclude is None else exclude.absolute()
    return sorted(p for p in hits if ex is None or not p.is_relative_to(ex))


def _unique_names(paths: list[pathlib.Path], roots: Sequence[pathlib.Path] = ()) -> list[InputFile]:
    base = [_folder_prefix(p, roots) + _file_name(p) for p in paths]
    counts: dict[str, int] = {}
    for b in base:
        counts[b.lower()] = counts.get(b.lower(), 0) + 1
    out = []
    for p, b in zip(paths, base, strict=True):
        if counts[b.lower()] > 1:
            b = f"{b}-{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"
        out.append(InputFile(p, b))
    return out


def _file_name(path: pathlib.Path) -> str:
    return safe_name(_KNOWN_SUFFIX.sub("", path.name).replace(".tfrecord", ""))


def _folder_prefix(path: pathlib.Path, roots: Sequence[pathlib.Path]) -> str:
    """``a/b/`` for a file in ``ROOT/a/b/`` under the deepest input folder ``ROOT`` that
    holds it; empty for a file given by itself or directly in its input folder."""
    holders = [r for r in roots if path.absolute().is_relative_to(r) and path.absolute() != r]
    if not holders:
        return ""
    root = max(holders, key=lambda r: len(r.parts))
    parts = path.absolute().parent.relative_to(root).parts
    return "".join(f"{safe_name(part)}/" for part in parts)


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
        self.convert_digest = settings.convert_digest()
        self.done: list[SceneDone] = []
        self.failures: list[Failure] = []
        self.replay_todo: list[ReplayTask] = []
        self.convert_todo: list[ConvertTask] = []
        self.conversions_skipped = 0

    def plan(self, files: Sequence[InputFile]) -> None:
        """Sort every input into complete (skipped) and to-do."""
        for f in files:
            if f.problem is not None:
                self.failures.append(
                    Failure(str(f.path), "", "convert", "ConversionError", one_line(f.problem))
                )
                continue
            if f.source is None:
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
            ego=self.settings.ego,
            every=self.settings.every,
        )

    def convert_task(self, f: InputFile, marker: pathlib.Path) -> ConvertTask:
        s = self.settings
        map_osm = s.map_osm or f.map
        return ConvertTask(
            input=str(f.path),
            name=f.name,
            kind=str(f.source),
            paths=s.paths,
            time_step=s.time_step,
            map_osm=None if map_osm is None else str(map_osm),
            scenes_dir=str(self.layout.scenes),
            marker=str(marker),
            digest=self.convert_digest,
            extra=tuple(str(e) for e in f.extra),
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
    an earlier run are skipped (see replay.batch). Failures never stop the run; they are
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
    eng = (
        make_engine(engine, workers=workers, address=ray_address)
        if isinstance(engine, str)
        else engine
    )
    bar = tqdm(
        total=len(run.replay_todo), unit="scene", desc=f"batch ({eng.name}, {eng.workers} workers)",
        file=sys.stderr, disable=None if progress else True, dynamic_ncols=True, smoothing=0.05,
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
        run.failures.append(worker_failure(task.input, "", outcome))
        return []
    run.failures += outcome.failures
    return [run.replay_task(name, task.input, pathlib.Path(p)) for name, p in outcome.scenes]


def _replayed(run: _Run, task: ReplayTask, outcome: Any) -> None:
    if isinstance(outcome, BaseException):
        run.failures.append(worker_failure(task.input, task.name, outcome))
    elif outcome.failure is not None:
        run.failures.append(outcome.failure)
    else:
        run.done.append(outcome.done)


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
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, csv_text(SCENE_COLUMNS, rows))


def dataset_stats(
    done: Sequence[SceneDone], out_dir: pathlib.Path, *, cascade: CascadeConfig
) -> list[pathlib.Path]:
    """The statistics of ``replay stats`` over the merged per-scene tables of ``done``
    (tables, ``summary.json``, plots) into ``out_dir``; returns the files written.

    Scenes are merged in the order given (the driver sorts them by name), so the result
    does not depend on the order in which workers finished.
    """
    # Imported here, not at the top: replay.analysis.stats.run loads matplotlib (about 1 s with
    # ``python -X importtime``), and every spawned worker imports this package to run
    # replay_one; only the driver ever gets here.
    from replay.analysis.stats.run import write_and_plot  # the tail shared with ``replay stats``
    from replay.analysis.stats.streaming import StatsPart, stream_stats

    # One scene's tables at a time, as ``replay stats`` reads its parts (issue 38): the
    # driver never holds the corpus's rows.
    parts = [StatsPart(pathlib.Path(d.table), pathlib.Path(d.frames_table)) for d in done]
    with tempfile.TemporaryDirectory(prefix="replay-batch-stats-") as scratch:
        stats = stream_stats(
            parts, pathlib.Path(scratch), models=None, errors_model=DEFAULT_ERRORS_MODEL,
            stage_names=cascade.stage_names, tier_names=[t.name for t in cascade.tiers],
            baseline_threshold=cascade.baseline_threshold,
            inputs=sorted({d.input for d in done}),
        )  # fmt: skip
        result = write_and_plot(stats, out_dir, plots=True, times={})
    return sorted(result.files.values())
