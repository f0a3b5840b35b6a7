"""The project's one process pool: :class:`LocalEngine`, and :func:`parallel_map` on it.

``replay batch`` drives :class:`LocalEngine` through its engine interface
(:mod:`replay.batch.engines`); ``replay stats`` and ``replay experiment`` use
:func:`parallel_map`, an ordered map with a progress bar. Either way the workers are
spawned processes with one thread each for polars and the BLAS libraries
(:func:`init_worker`), Ctrl-C is left to the driver, and a worker that dies (a crash in
native code, out of memory) is replaced and its task reported as :class:`WorkerDied`.

This module must not import polars (not even indirectly): a spawned worker imports it to
run :func:`init_worker`, which has to set ``POLARS_MAX_THREADS`` before polars loads.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import math
import multiprocessing
import os
import signal
import sys
import threading
from collections import deque
from collections.abc import Callable, Sequence
from multiprocessing import resource_tracker
from typing import Any

from tqdm import tqdm

from replay.core.process_exit import exit_with_parent, interrupts_held
from replay.errors import ReplayError
from risk import kernel


class WorkerDied(ReplayError):
    """The worker process running a task died (a crash in native code, out of memory)."""

    def __init__(self) -> None:
        super().__init__(
            "the worker process died while running this task (a crash in native code or "
            "out of memory)"
        )


def default_workers() -> int:
    """The CPUs this process may run on (the affinity mask, where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # macOS, Windows
        return max(1, os.cpu_count() or 1)


def _quiet_worker(driver: int) -> None:
    """Initializer of local workers: leave Ctrl-C to the driver, which stops queueing and
    lets running tasks finish (their outputs are atomic), exit when the driver (pid
    ``driver``) dies, so that no worker outlives it, and set thread counts."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # SIGTERM / SIGHUP to the whole process group (a closed terminal, ``kill -- -PGID``)
    # are the driver's to handle too: it stops the workers itself, after which the
    # pool's queues are released (workers dying on their own left the pool's
    # semaphores leaked, seen as resource_tracker warnings).
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    exit_with_parent(driver)
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
        kernel.warm_up(
            build_ahead_of_time=True
        )  # compile once here; the workers load the cached kernels
        _start_resource_tracker()
        return cf.ProcessPoolExecutor(
            max_workers=self.workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_quiet_worker,
            initargs=(os.getpid(),),
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
        with interrupts_held():  # (submit starts the workers: no Ctrl-C while they import)
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

    def cancel_pending(self) -> None:
        """Drop the queued calls and wait for the running ones; the engine stays usable."""
        self._held.clear()
        self._suspects.clear()
        for future in self._running:
            future.cancel()
        cf.wait(self._running)
        self._running.clear()
        self._alone = False

    def close(self, *, cancel: bool = False, stop: bool = False) -> None:
        """Shut the pool down; ``cancel``: drop queued calls; ``stop`` (Ctrl-C, SIGTERM):
        also end the running ones at once (their outputs are atomic: nothing partial)."""
        if cancel or stop:
            self._held.clear()
            self._suspects.clear()
        if stop:
            self._kill_workers()
        self._pool.shutdown(wait=True, cancel_futures=cancel or stop)

    def _kill_workers(self) -> None:
        # ProcessPoolExecutor has no public way to end running calls. A worker killed
        # while sending its result leaves half a message in the result pipe, and the
        # pool's manager thread would wait for the rest for ever (seen: a hang after
        # Ctrl-C); closing our copy of the pipe's write end, once the workers are gone,
        # turns that into end-of-file, which the manager handles as a broken pool.
        processes = list((getattr(self._pool, "_processes", None) or {}).values())
        for process in processes:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                process.kill()
        for process in processes:
            with contextlib.suppress(OSError, ValueError, AttributeError, AssertionError):
                process.join(5.0)
        queue = getattr(self._pool, "_result_queue", None)
        with contextlib.suppress(OSError, AttributeError):
            queue._writer.close()  # type: ignore[union-attr]


def _start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker with SIGHUP ignored (it ignores SIGINT
    and SIGTERM itself): a hang-up of the terminal, sent to the whole process group,
    killed it, and the pool's semaphores were then reported leaked."""
    if threading.current_thread() is not threading.main_thread():
        resource_tracker.ensure_running()
        return
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        resource_tracker.ensure_running()
    finally:
        signal.signal(signal.SIGHUP, previous)


def _lost(future: cf.Future) -> bool:
    """True when the call was lost with its pool (a worker process died)."""
    return isinstance(future.exception(), cf.process.BrokenProcessPool)


def init_worker() -> None:
    """Process-pool initializer: one thread per worker for the libraries that would
    otherwise start one per core each (parallelism comes from the processes). Runs
    before polars is imported in a spawned worker, which reads it at import."""
    for var in ("POLARS_MAX_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    # tqdm's default lock is a multiprocessing RLock, a named semaphore even for a
    # disabled bar: a worker stopped mid-task left it leaked (resource_tracker warned).
    # A worker's bars never share a terminal with another process's.
    tqdm.set_lock(threading.RLock())


def parallel_map(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    *,
    workers: int,
    progress: bool = True,
    desc: str = "",
    weights: Sequence[int] | None = None,
    engine: LocalEngine | None = None,
    unit: str = "situation",
) -> list[Any]:
    """``[fn(t) for t in tasks]`` on ``workers`` processes, in the order of ``tasks``.

    ``workers <= 1`` (and no ``engine``) runs in this process. ``weights``: units of each
    task for the progress bar (e.g. situations per chunk). ``engine``: an open
    :class:`LocalEngine` to reuse (it stays open). The first exception of a task (a
    :class:`WorkerDied` when its worker died) is raised once the running tasks are done;
    the tasks not yet started are dropped.
    """
    weights = list(weights) if weights is not None else [1] * len(tasks)
    bar = tqdm(
        total=sum(weights),
        disable=None if progress else True,
        file=sys.stderr,
        desc=desc,
        unit=unit,
        leave=False,
    )
    results: list[Any] = [None] * len(tasks)
    with bar:
        if workers <= 1 and engine is None:
            for k, task in enumerate(tasks):
                results[k] = fn(task)
                bar.update(weights[k])
            return results
        own = engine is None
        pool = engine if engine is not None else LocalEngine(workers)
        try:
            for k, task in enumerate(tasks):
                pool.submit(_call, (fn, k, task))
            while pool.pending:
                for (_, k, _), outcome in pool.results():
                    if isinstance(outcome, BaseException):
                        raise outcome
                    results[k] = outcome
                    bar.update(weights[k])
        except KeyboardInterrupt:  # Ctrl-C, SIGTERM, SIGHUP: stop the workers now
            if own:
                pool.close(stop=True)
            else:
                pool.cancel_pending()
            raise
        except BaseException:
            if own:
                pool.close(cancel=True)
            else:
                pool.cancel_pending()
            raise
        if own:
            pool.close()
    return results


def _call(item: tuple[Callable[[Any], Any], int, Any]) -> Any:
    fn, _, task = item
    return fn(task)


def chunks(items: Sequence[Any], workers: int, per_worker: int = 6) -> list[list[Any]]:
    """``items`` in about ``workers * per_worker`` contiguous chunks (load balance vs
    per-task overhead)."""
    n = len(items)
    if n == 0:
        return []
    size = max(1, math.ceil(n / max(1, workers * per_worker)))
    return [list(items[i : i + size]) for i in range(0, n, size)]
