"""Where a command's jobs run and write (:class:`JobPlace`), one engine shared by a
command's several jobs (:func:`shared_engine`), and the one-line failure when no scene
is complete (:func:`every_done`). Used by ``replay plan`` (matching, open loop, closed
loop: several jobs into one folder) and ``replay calibrate``."""

from __future__ import annotations

import contextlib
import dataclasses
import pathlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from replay.core.pool import default_workers
from replay.errors import ReplayError
from replay.jobs.engines import Engine, make_engine
from replay.jobs.failures import Failure
from replay.jobs.runner import Job, JobReport, run_jobs, write_failures_now
from replay.jobs.scenes import SceneRef


@dataclasses.dataclass(frozen=True)
class JobPlace:
    """Where a command's jobs run and write: ``out_dir`` (its ``parts/`` and
    ``failures.csv``), the engine (``local`` or ``ray``, or an open :class:`Engine`
    shared by the command's jobs), ``workers``, the Ray address, the progress bar."""

    out_dir: pathlib.Path
    engine: str | Engine = "local"
    workers: int | None = None
    address: str | None = None
    progress: bool = True


def run_job(job: Job, refs: Sequence[SceneRef], place: JobPlace, desc: str) -> JobReport:
    """``job`` on ``refs`` at ``place`` (see :func:`replay.jobs.run_jobs`)."""
    return run_jobs(
        job, refs, place.out_dir, engine=place.engine, workers=place.workers,
        ray_address=place.address, progress=place.progress, desc=desc,
    )  # fmt: skip


@contextlib.contextmanager
def shared_engine(place: JobPlace, scenes: int) -> Iterator[JobPlace]:
    """``place`` with one engine open for all of a command's jobs (a local Ray instance is
    started once, not once per job; a local pool's workers stay warm). Local work on one
    worker (or one scene) stays in this process, as :func:`replay.jobs.run_jobs` does."""
    if not isinstance(place.engine, str):
        yield place
        return
    workers = place.workers
    if place.engine == "local" and not place.address:
        workers = max(1, min(workers or default_workers(), scenes))
        if workers == 1:
            yield dataclasses.replace(place, workers=1)
            return
    engine = OnFirstUse(place.engine, workers, place.address)
    try:
        yield dataclasses.replace(place, engine=engine)
    except BaseException:
        engine.close(cancel=True)
        raise
    engine.close()


class OnFirstUse:
    """An engine that starts when a job first needs it: a rerun whose scenes are all
    complete neither starts a local Ray instance nor connects to a cluster."""

    def __init__(self, name: str, workers: int | None, address: str | None) -> None:
        self.name = name
        self._args = (workers, address)
        self._engine: Engine | None = None

    @property
    def started(self) -> bool:
        return self._engine is not None

    def _open(self) -> Engine:
        if self._engine is None:
            workers, address = self._args
            self._engine = make_engine(self.name, workers=workers, address=address)
        return self._engine

    @property
    def workers(self) -> int:
        return self._open().workers

    @workers.setter
    def workers(self, value: int) -> None:  # the protocol's attribute; never set here
        self._open().workers = value

    @property
    def pending(self) -> int:
        return 0 if self._engine is None else self._engine.pending

    def submit(self, fn: Callable[[Any], Any], task: Any) -> None:
        self._open().submit(fn, task)

    def results(self) -> list[tuple[Any, Any]]:
        return [] if self._engine is None else self._engine.results()

    def close(self, *, cancel: bool = False) -> None:
        if self._engine is not None:
            self._engine.close(cancel=cancel)


def every_done(report: JobReport) -> None:
    """Fail (one line, the first reason) when no scene of ``report`` is complete."""
    if not report.done:
        first = report.failures[0] if report.failures else None
        why = f": {first.scene}: {first.reason}" if first is not None else ""
        raise ReplayError(f"every scene failed ({len(report.failures)}){why}")


def all_failures(reports: Sequence[JobReport]) -> list[Failure]:
    """Every job's failures, each once (a scene that cannot be read fails every job with
    the same line), in scene order."""
    unique = {
        (f.input, f.scene, f.stage, f.error_type, f.reason): f for r in reports for f in r.failures
    }
    return [unique[k] for k in sorted(unique, key=lambda k: (k[1], k[0], k[2], k[4]))]


def write_all_failures(out_dir: pathlib.Path, reports: Sequence[JobReport]) -> list[Failure]:
    """``out_dir/failures.csv`` listing :func:`all_failures` of ``reports`` (several jobs
    into one folder: each wrote only its own). Returns them."""
    failures = all_failures(reports)
    write_failures_now(out_dir.absolute() / "failures.csv", failures)
    return failures
