"""The job runner: one pure function per scene, on an engine, its results streamed to files.

A :class:`Job` is what a corpus command hands the runner: a module-level function
``run(ref, settings) -> SceneOutput`` (``ref`` a :class:`~replay.jobs.scenes.SceneRef`,
``settings`` a frozen, picklable dataclass) and the settings' **fingerprint** (a digest of
everything that decides a scene's output). The runner (:func:`run_jobs`):

1. **plans**: a scene is *complete*, and skipped, when its marker
   ``OUT/parts/.done/<job>/<key>.json`` is readable, has the job's name and fingerprint, names
   the same input file with the same size and modification time, and every part file it
   lists exists with its recorded size (two jobs can share ``OUT``). A marker with another fingerprint (the settings
   changed) is not an error: that scene is **recomputed**, and the report counts it;
2. **runs** the other scenes on an engine (:mod:`replay.jobs.engines`: local processes or
   Ray), a few tasks per worker in flight, with a progress bar on a terminal (none into
   pipes). A worker writes each table of its scene to
   ``OUT/parts/<table>/<key>.parquet`` atomically, then the marker, so a scene is either
   complete or absent, whatever stops the run; its small ``partial`` summary (JSON) goes
   into the marker and back to the driver;
3. **lists** every scene that failed in ``OUT/failures.csv`` (input, scene key, stage,
   error type, one line; a header only when none did). Failures never stop the run; a
   rerun tries them again. When no scene is complete the command fails (one line
   with the first reason) and no ``failures.csv`` is written.

The driver never receives a scene's rows: it reads the part files back (lazily,
:meth:`JobReport.scan`) in key order, so the result does not depend on the engine or on
the order in which scenes finished.

With ``engine="local"`` and ``workers=1`` the scenes run in this process (no spawn, no
pickling; a scene that crashes the interpreter then ends the command, as before).
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
import re
import sys
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import astuple, dataclass, field
from typing import Any

import polars as pl
from tqdm import tqdm

from outputs.atomic import place, safe_name, temp_path_beside
from replay import __version__
from replay.errors import ReplayError
from replay.jobs.engines import Engine, make_engine
from replay.jobs.failures import (
    FAILURE_COLUMNS,
    Failure,
    csv_text,
    failure_from,
    worker_failure,
)
from replay.jobs.scenes import SceneRef

MARKER_FORMAT = 1
PARTS = "parts"


@dataclass(frozen=True)
class SceneOutput:
    """What a job returns for one scene: named tables (each written to its part file)
    and a small JSON-able ``partial`` summary (kept in the marker, given to the driver)."""

    tables: Mapping[str, pl.DataFrame]
    partial: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Job:
    """A per-scene job: ``run(ref, settings)`` must be a module-level function (every
    engine pickles it by reference) and pure: its output depends on the scene file and
    ``settings`` only. ``fingerprint``: see :func:`fingerprint`."""

    name: str
    run: Callable[[SceneRef, Any], SceneOutput]
    settings: Any
    fingerprint: str


def fingerprint(name: str, settings: Mapping[str, Any]) -> str:
    """A digest of a job's name, its settings (JSON, ``str`` for other values) and the
    package version: what decides whether an earlier scene's parts can be reused."""
    text = json.dumps(
        {"job": name, "version": __version__, "format": MARKER_FORMAT, "settings": settings},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class SceneDone:
    """A complete scene: its part files (table name -> path), partial and seconds."""

    ref: SceneRef
    tables: Mapping[str, str]
    partial: Mapping[str, Any]
    seconds: float
    status: str = "computed"  # or "skipped" (complete from an earlier run)


@dataclass
class JobReport:
    """What :func:`run_jobs` did. ``done`` is sorted by key."""

    out_dir: pathlib.Path
    engine: str
    workers: int
    done: list[SceneDone]
    failures: list[Failure]
    recomputed: int = 0  # scenes whose parts were made with other settings
    seconds: float = 0.0
    job: str = ""  # the job's name

    @property
    def computed(self) -> int:
        return sum(d.status == "computed" for d in self.done)

    @property
    def skipped(self) -> int:
        return sum(d.status == "skipped" for d in self.done)

    @property
    def failures_csv(self) -> pathlib.Path:
        return self.out_dir / "failures.csv"

    def parts(self, table: str) -> list[pathlib.Path]:
        """The part files of ``table``, in key order."""
        return [pathlib.Path(d.tables[table]) for d in self.done if table in d.tables]

    def scan(self, table: str) -> pl.LazyFrame:
        """Every scene's ``table`` as one lazy frame, in key order (columns a scene lacks
        are null; types that differ are widened)."""
        files = self.parts(table)
        if not files:
            raise ReplayError(f"no scene has a {table} table")
        return pl.concat([pl.scan_parquet(f) for f in files], how="diagonal_relaxed")

    def describe(self) -> str:
        """One line: computed, skipped, recomputed, failed."""
        parts = [f"{self.computed} scene(s) computed", f"{self.skipped} skipped (complete)"]
        if self.recomputed:
            parts.append(f"{self.recomputed} recomputed (made with other settings)")
        if self.failures:
            parts.append(f"{len(self.failures)} failed (see {self.failures_csv})")
        return f"{', '.join(parts)}; {self.engine} engine, {self.workers} worker(s)"


@dataclass(frozen=True)
class _Task:
    """One scene for a worker (picklable: paths as strings for a shared file system)."""

    job: str
    run: Callable[[SceneRef, Any], SceneOutput]
    settings: Any
    fingerprint: str
    ref: SceneRef
    parts: str  # OUT/parts


@dataclass(frozen=True)
class _Outcome:
    done: SceneDone | None
    failure: Failure | None


def part_path(parts: pathlib.Path, table: str, key: str) -> pathlib.Path:
    return parts / table / f"{_file_key(key)}.parquet"


def marker_path(parts: pathlib.Path, job: str, key: str) -> pathlib.Path:
    """A scene's marker, per job: two jobs (a study's open and closed loop) may share an
    output folder (their tables need distinct names)."""
    return parts / ".done" / safe_name(job) / f"{_file_key(key)}.json"


def _file_key(key: str) -> str:
    """The key as a relative file path: each part :func:`outputs.atomic.safe_name`d; a key
    that this changes gets 8 hex digits of its hash, so that two keys never share a file
    (``a b`` and ``a_b``)."""
    safe = "/".join(safe_name(p) for p in key.split("/"))
    if safe == key:
        return safe
    return f"{safe}-{hashlib.sha256(key.encode()).hexdigest()[:8]}"


def run_task(task: _Task) -> _Outcome:
    """Run one scene, write its tables and then its marker. Never raises for a bad
    scene: every exception becomes the outcome's Failure."""
    start = time.perf_counter()
    ref = task.ref
    stage = "run"
    try:
        output = task.run(ref, task.settings)
        stage = "write"
        parts = pathlib.Path(task.parts)
        tables = {}
        for name, df in output.tables.items():
            path = part_path(parts, name, ref.key)
            _write_durable(path, _parquet_writer(df))
            tables[name] = str(path)
        done = SceneDone(ref, tables, dict(output.partial), time.perf_counter() - start)
        _write_marker(task, done)
        return _Outcome(done, None)
    except Exception as exc:
        return _Outcome(None, failure_from(str(ref.path), ref.key, stage, exc))


def _parquet_writer(df: pl.DataFrame) -> Callable[[str], None]:
    def write(tmp: str) -> None:
        df.write_parquet(tmp, compression="zstd")

    return write


def _write_durable(path: pathlib.Path, write: Callable[[str], Any]) -> None:
    """Write through a temporary file renamed into place at once, also inside a command's
    output transaction (part files must survive a run that fails later: resuming)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_beside(path)
    try:
        write(str(tmp))
        place(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _entry(path: str | os.PathLike[str]) -> dict[str, Any]:
    st = os.stat(path)
    return {"path": os.fspath(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _write_marker(task: _Task, done: SceneDone) -> None:
    data = {
        "format": MARKER_FORMAT,
        "job": task.job,
        "fingerprint": task.fingerprint,
        "key": task.ref.key,
        "input": _entry(task.ref.path),
        "tables": {n: _entry(p) for n, p in done.tables.items()},
        "partial": done.partial,
        "seconds": round(done.seconds, 4),
    }
    text = json.dumps(data, indent=1, sort_keys=True, default=str) + "\n"
    path = marker_path(pathlib.Path(task.parts), task.job, task.ref.key)
    _write_durable(path, lambda tmp: pathlib.Path(tmp).write_text(text, encoding="utf-8"))


def _intact(entry: Any, *, check_time: bool) -> bool:
    try:
        st = os.stat(entry["path"])
        return st.st_size == entry["size"] and (
            not check_time or st.st_mtime_ns == entry["mtime_ns"]
        )
    except (OSError, KeyError, TypeError):
        return False


def completed(job: Job, ref: SceneRef, parts: pathlib.Path) -> SceneDone | str | None:
    """The scene's result when its parts are complete; ``"stale"`` when they were made
    with other settings; None otherwise (missing, damaged, input changed)."""
    try:
        data = json.loads(marker_path(parts, job.name, ref.key).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("format") != MARKER_FORMAT:
        return None
    if data.get("job") != job.name or data.get("key") != ref.key:
        return None
    source = data.get("input", {})
    if source.get("path") != os.fspath(ref.path) or not _intact(source, check_time=True):
        return None
    if data.get("fingerprint") != job.fingerprint:
        return "stale"
    tables = data.get("tables")
    if not isinstance(tables, dict) or not all(
        _intact(e, check_time=False) for e in tables.values()
    ):
        return None
    try:
        return SceneDone(
            ref,
            {str(n): str(e["path"]) for n, e in tables.items()},
            dict(data.get("partial") or {}),
            float(data.get("seconds", 0.0)),
            status="skipped",
        )
    except (KeyError, TypeError, ValueError):
        return None


def run_jobs(
    job: Job,
    refs: Sequence[SceneRef],
    out_dir: str | os.PathLike[str],
    *,
    engine: str | Engine = "local",
    workers: int | None = None,
    ray_address: str | None = None,
    progress: bool = True,
    desc: str = "",
) -> JobReport:
    """Run ``job`` on every scene of ``refs`` not complete in ``out_dir`` (see the module
    docstring) and write ``OUT/failures.csv``. ``engine``: ``local``, ``ray`` or an open
    :class:`Engine` (left open). Raises ReplayError only for bad arguments (an engine
    that cannot start)."""
    start = time.perf_counter()
    out = pathlib.Path(out_dir).absolute()
    parts = out / PARTS
    keys = [r.key for r in refs]
    if len(set(keys)) != len(keys):
        raise ReplayError("two inputs have the same scene key")  # scene_refs prevents it
    _remove_stale_temps(parts)
    done: list[SceneDone] = []
    todo: list[_Task] = []
    recomputed = 0
    for ref in refs:
        prior = completed(job, ref, parts)
        if isinstance(prior, SceneDone):
            done.append(prior)
            continue
        recomputed += prior == "stale"
        todo.append(_Task(job.name, job.run, job.settings, job.fingerprint, ref, str(parts)))
    failures: list[Failure] = []
    try:
        name, n_workers = _execute(
            todo, done, failures, engine, workers, ray_address, progress, desc or job.name
        )
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP: say what a rerun reuses
        if done and not getattr(exc, "kept", None):
            exc.kept = (  # type: ignore[attr-defined]
                f"{len(done)} complete scene(s) of {job.name} are kept in {parts}; run the "
                "same command again to resume (the final outputs were not written)"
            )
        raise
    done.sort(key=lambda d: d.ref.key)
    failures.sort(key=lambda f: (f.scene, f.input, f.stage))
    if done:  # when nothing is complete the command fails and leaves no file behind
        write_failures_now(out / "failures.csv", failures)
    seconds = time.perf_counter() - start
    return JobReport(out, name, n_workers, done, failures, recomputed, seconds, job.name)


#: The temporary files of outputs.atomic: ``.NAME.<12 hex>.tmp``.
_TEMP = re.compile(r"^\..+\.[0-9a-f]{12}\.tmp$")


def _remove_stale_temps(parts: pathlib.Path) -> None:
    """Temporary part files of workers killed mid-write in an earlier run (the command's
    output lock says no other run writes here now)."""
    if parts.is_dir():
        for f in parts.rglob(".*.tmp"):
            if _TEMP.match(f.name):
                f.unlink(missing_ok=True)


def write_failures_now(path: pathlib.Path, failures: Sequence[Failure]) -> None:
    """``failures.csv`` at once, also inside an output transaction: it describes the
    parts, which are in place already."""
    text = csv_text(FAILURE_COLUMNS, [astuple(f) for f in failures])
    _write_durable(path, lambda tmp: pathlib.Path(tmp).write_text(text, encoding="utf-8"))


def _execute(
    todo: list[_Task],
    done: list[SceneDone],
    failures: list[Failure],
    engine: str | Engine,
    workers: int | None,
    ray_address: str | None,
    progress: bool,
    desc: str,
) -> tuple[str, int]:
    name = engine if isinstance(engine, str) else engine.name
    if not todo:
        return name, 0
    bar = tqdm(
        total=len(todo), unit="scene", desc=desc, file=sys.stderr,
        disable=None if progress else True, dynamic_ncols=True, leave=False,
    )  # fmt: skip
    with bar:
        if engine == "local" and workers == 1 and not ray_address:
            for task in todo:  # one worker: this process (no spawn, no pickling)
                _collect(task, run_task(task), done, failures)
                bar.update()
            return "local", 1
        own = isinstance(engine, str)
        n = None if workers is None else min(workers, len(todo))
        eng: Engine = (
            make_engine(engine, workers=n, address=ray_address)
            if isinstance(engine, str)
            else engine
        )
        try:
            _drive(eng, todo, done, failures, bar)
        except BaseException:
            if own:
                eng.close(cancel=True)
            raise
        if own:
            eng.close()
        return eng.name, eng.workers


def _drive(
    eng: Engine, todo: list[_Task], done: list[SceneDone], failures: list[Failure], bar: Any
) -> None:
    """At most a few tasks per worker in the engine at a time: every worker stays busy,
    Ctrl-C drops the rest at once and a cluster's waits stay cheap."""
    queue = deque(todo)
    in_flight = 2 * max(1, eng.workers) + 2
    while queue or eng.pending:
        while queue and eng.pending < in_flight:
            eng.submit(run_task, queue.popleft())
        for task, outcome in eng.results():
            _collect(task, outcome, done, failures)
            bar.update()
            bar.set_postfix({"failed": len(failures)}, refresh=False)


def _collect(task: _Task, outcome: Any, done: list[SceneDone], failures: list[Failure]) -> None:
    if isinstance(outcome, BaseException):  # the worker died, or Ray lost the task
        failures.append(worker_failure(str(task.ref.path), task.ref.key, outcome))
    elif outcome.failure is not None:
        failures.append(outcome.failure)
    else:
        done.append(outcome.done)
