"""Engines: where the tasks run. One small interface (:class:`Engine`), two engines:
worker processes on this machine (:class:`replay.core.pool.LocalEngine`, the project's one
process pool) and Ray (:class:`RayEngine`)."""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import socket
from collections.abc import Callable
from typing import Any, Protocol

from replay.core.pool import LocalEngine, default_workers
from replay.errors import ReplayError
from replay.jobs.failures import one_line
from risk import kernel

ENGINES: tuple[str, ...] = ("local", "ray")
RAY_MISSING = "Ray is not installed; install it with: pip install 'riskreplay[ray]'"
#: The environment variable the raylet reads its workers' niceness from (default 15).
WORKER_NICENESS = "RAY_worker_niceness"
#: Ray's logger of its token-authentication default (Ray 2.5x and later).
RAY_AUTH_LOGGER = "ray._private.authentication.authentication_token_setup"


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
        kernel.warm_up(
            build_ahead_of_time=True
        )  # compile once here; workers on this machine load the cache
        if not ray.is_initialized():
            kwargs: dict[str, Any] = {"logging_level": logging.WARNING, "log_to_driver": False}
            try:
                if address:
                    ray.init(address=address, **kwargs)
                else:
                    cpus = workers or default_workers()
                    # Ray runs its workers at nice 15 (a cluster's raylet stays responsive);
                    # a local instance does this command's work on this machine, at its
                    # priority, as the local engine's processes do. On a busy machine nice
                    # 15 gave the workers a fraction of the CPU (measured: 5x slower).
                    os.environ.setdefault(WORKER_NICENESS, "0")
                    # Ray keeps its default (token authentication on for a new local
                    # instance) but would print a warning saying so into every command's
                    # output; only that logger is quietened, and only for this instance.
                    logging.getLogger(RAY_AUTH_LOGGER).setLevel(logging.ERROR)
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


def check_engine(name: str) -> None:
    """Refuse an engine that cannot start here (Ray not installed) before anything is
    written: found only when the batch opened its engine, it left ``.done/`` and
    ``tables/`` behind."""
    if name == "ray" and importlib.util.find_spec("ray") is None:
        raise ReplayError(RAY_MISSING)


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
