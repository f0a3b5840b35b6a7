"""Engines: where the tasks run. One small interface (:class:`Engine`), two engines:
worker processes on this machine (:class:`LocalEngine`) and Ray (:class:`RayEngine`)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import socket
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

from replay.batch.tasks import init_worker, one_line
from replay.errors import ReplayError
from replay.lifeline import exit_with_parent

ENGINES: tuple[str, ...] = ("local", "ray")
RAY_MISSING = "Ray is not installed; install it with: pip install 'riskreplay[ray]'"


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


def _quiet_worker(driver: int) -> None:
    """Initializer of local workers: leave Ctrl-C to the driver, which stops queueing and
    lets running tasks finish (their outputs are atomic), and set thread counts."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    exit_with_parent(driver)  # a killed driver leaves no orphan workers
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
        if address:
            _check_reachable(address)
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
                    f"could not start or reach {where}: {one_line(str(exc))}"
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


def _check_reachable(address: str, timeout_s: float = 10.0) -> None:
    """Fail at once when an explicit ``HOST:PORT`` or ``ray://HOST:PORT`` accepts no
    connection: Ray itself keeps retrying such an address for minutes. Other forms
    (``auto``, ``local``) are left to Ray, which reports them quickly."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not (sep and host and port.isdigit()):
        return
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ReplayError(
            f"cannot reach the Ray cluster at {address} ({exc.strerror or exc}); is it "
            "running ('ray start --head' on the head node) and is the port open?"
        ) from None


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
