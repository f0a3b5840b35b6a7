"""Output files written by a second process while the replay computes.

Importing rerun takes about 1 s and polars about 0.3 s, and writing a recording or a table
a few tenths more; all of it used to come on top of the replay. The outputs' ``close()``
can instead hand their collected arrays to an **output process**: a new Python interpreter
that imports the writers' modules as soon as it starts, then runs one job per output
(``"module:function"`` with its arguments) and sends back the result or the exception.
With two CPUs the imports cost no wall time.

- A command that knows what it will write starts the process before it loads the models
  (:func:`start`, ``replay run`` / ``replay demo`` do); outputs adopt it with
  :func:`acquire`, which starts one if none runs, and give it back with :func:`release`.
  The process ends when the last user releases it, or when its parent dies.
- Jobs write temporary files only. The parent names them, renames them into place
  (so that ``outputs.transaction.OutputGuard`` still commits a command's outputs together) and
  removes them when a job fails or the process dies.
- A new interpreter, not ``fork``: rerun and polars run native thread pools, which a
  forked copy of a process that has used them inherits in a broken state (a recording
  written in a fork of a process that had written one before hung, seen in the tests).
- Started with :mod:`subprocess` and one end of a socket pair (a
  :class:`multiprocessing.connection.Connection`: pickled messages), not with
  multiprocessing's ``spawn``. ``spawn`` first starts its resource tracker (one more
  interpreter), and its child runs the parent's main script again: for ``replay``, the
  console script's ``from replay.cli.app import main`` (click and the CLI, 0.1-0.2 s measured
  on the output process's path before it reaches its own imports).
- ``RISKREPLAY_OUTPUT_PROCESS``: ``auto`` (the default) uses the process when a second
  CPU is idle (:func:`available`), ``off`` never (the outputs write in the replay's own
  process), ``on`` always.

Standard library only, so that starting the process early costs nothing.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import multiprocessing.connection
import os
import signal
import socket
import subprocess
import sys
import threading
import traceback
from collections.abc import Iterable
from typing import Any

from risk.errors import RiskReplayError  # standard library only (risk/__init__.py is lazy)

#: ``auto`` (default), ``on`` or ``off``: when to write outputs in the output process.
MODE_VARIABLE = "RISKREPLAY_OUTPUT_PROCESS"


class OutputProcessError(RiskReplayError, RuntimeError):
    """The output process ended before it finished a job (it was killed, or crashed)."""


def available() -> bool:
    """Whether to use an output process. ``RISKREPLAY_OUTPUT_PROCESS=on`` / ``off`` decide;
    by default only when it helps: a second CPU that is idle (the load average of the
    last minute leaves one free). On a busy machine the process only competes with the
    replay for a CPU and adds its own start (measured: 0.5 s slower with a neighbour
    busy on the other CPU)."""
    mode = os.environ.get(MODE_VARIABLE, "auto").strip().lower()
    if mode in ("on", "off"):
        return mode == "on"
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # Windows has no load average
        load = 0.0
    return (cpus or 1) >= 2 and load <= (cpus or 1) - 1


class OutputProcess:
    """A new process that imports ``preload`` at once, then runs jobs one at a time."""

    def __init__(self, preload: Iterable[str]) -> None:
        self._lock = threading.Lock()
        self._idle = True  # no job sent whose reply is not read
        self.users = 0
        ours, theirs = socket.socketpair()
        try:
            # (the parent's sys.path, as multiprocessing passes it: modules found there,
            # e.g. a test's, are found in the process too)
            self._process = subprocess.Popen(
                [sys.executable, "-c", _CHILD, json.dumps(sys.path), str(theirs.fileno()),
                 *preload],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
            )  # fmt: skip
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self._conn = multiprocessing.connection.Connection(ours.detach())

    def alive(self) -> bool:
        return self._process.poll() is None

    def run(self, function: str, *args: Any) -> Any:
        """Run ``function`` (``"module:name"``) on ``args`` in the process and return its
        result, or raise its exception (with the process's traceback as a note, unless
        the exception says all: see :func:`_quiet`). Waits as long as the job takes, and
        raises :class:`OutputProcessError` if the process dies meanwhile."""
        return self.submit(function, *args).result()

    def submit(self, function: str, *args: Any) -> Pending:
        """Send a job and return at once; :meth:`Pending.result` waits for it (as
        :meth:`run`). One job at a time: the next waits until this one's result is read.

        The job is sent by a thread: a pipe takes only about 64 kB until the process
        reads, and it reads only once its imports are done."""
        self._lock.acquire()
        self._idle = False
        sent: list[BaseException] = []

        def send() -> None:
            try:
                self._conn.send((function, args))
            except OSError:
                pass  # a dead process: its exit code says why
            except BaseException as exc:  # (does not pickle)
                sent.append(exc)

        sender = threading.Thread(target=send, name="riskreplay-output-send", daemon=True)
        try:
            sender.start()
        except BaseException:
            self._lock.release()
            raise
        return Pending(self, function, sender, sent)

    def _reply(self, function: str, sender: threading.Thread, sent: list[BaseException]) -> Any:
        try:
            while sender.is_alive():
                sender.join(0.2)
                if not self.alive():
                    break
            if sent:
                raise sent[0]
            reply = None
            while reply is None:
                if self._conn.poll(0.2):
                    try:
                        reply = self._conn.recv()
                    except EOFError:
                        break
                elif not self.alive():
                    break
        finally:
            self._lock.release()
        if reply is not None:
            self._idle = True
        if reply is None:
            self.stop()
            raise OutputProcessError(
                f"the output process stopped (exit code {self._process.returncode}) while "
                f"running {function}; run again, and if it happens again set "
                f"{MODE_VARIABLE}=off to write in the replay's own process"
            )
        ok, value, text = reply
        if ok:
            return value
        if text:
            value.add_note(f"in the output process:\n{text}")
        raise value

    def stop(self, *, wait: bool = True) -> None:
        """End the process, whatever it is doing. ``wait=False``: when it is idle (every
        reply read), only tell it to leave; it does on its own, and a command's own exit
        does not wait for its interpreter's shutdown (about 0.15 s with rerun). A busy
        process (a job abandoned: an error, Ctrl-C) is waited for or ended either way, so
        that it writes no file after its user has cleaned up."""
        with contextlib.suppress(OSError):
            self._conn.close()  # an idle process sees EOF and leaves
        if not wait and self._idle:
            # reaped by a thread, so that no exited process lingers as a zombie while
            # this one goes on (tests, batch)
            threading.Thread(target=self._process.wait, name="riskreplay-output-reap",
                             daemon=True).start()  # fmt: skip
            return
        try:
            self._process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._process.terminate()
            try:
                self._process.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()


class Pending:
    """A job sent to the output process (:meth:`OutputProcess.submit`)."""

    def __init__(
        self,
        process: OutputProcess,
        function: str,
        sender: threading.Thread,
        sent: list[BaseException],
    ) -> None:
        self._process = process
        self._function = function
        self._sender = sender
        self._sent = sent
        self._done = False

    def result(self) -> Any:
        """Wait for the job; its result, or its exception (read once)."""
        if self._done:
            raise RuntimeError(f"the result of {self._function} was read already")
        self._done = True
        return self._process._reply(self._function, self._sender, self._sent)


_shared: OutputProcess | None = None
_shared_lock = threading.Lock()


def start(preload: Iterable[str]) -> OutputProcess | None:
    """Start the shared output process now, importing ``preload``, and hold it until
    :func:`release` (None when :func:`available` says no). A running one is reused."""
    return acquire(preload)


def acquire(preload: Iterable[str] = ()) -> OutputProcess | None:
    """The shared output process, started (importing ``preload``) if none runs; each call
    must be paired with :func:`release`. None when :func:`available` says no."""
    global _shared
    if not available():
        return None
    with _shared_lock:
        if _shared is None or not _shared.alive():
            _shared = OutputProcess(preload)
        _shared.users += 1
        return _shared


def release(process: OutputProcess | None) -> None:
    """Give back a process from :func:`acquire`; the last user's release stops it."""
    global _shared
    if process is None:
        return
    with _shared_lock:
        process.users -= 1
        if process.users > 0:
            return
        if process is _shared:
            _shared = None
    process.stop(wait=False)


def _quiet(exc: BaseException) -> bool:
    """Errors whose message is the whole story (the user's, not the program's): no
    traceback note. Judged by name, so that this module imports nothing of the project."""
    return any(k.__name__ in ("RecordingError", "ReplayError") for k in type(exc).__mro__)


#: What the output process runs: ``python -c _CHILD SYS_PATH FD MODULE...``.
_CHILD = (
    "import json, sys; sys.path[:] = json.loads(sys.argv[1]); "
    "from outputs.process import _child_main; _child_main(int(sys.argv[2]), sys.argv[3:])"
)


def _child_main(fd: int, preload: list[str]) -> None:
    # Ctrl-C goes to the whole process group: the parent handles it and stops this one.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    code = 0
    try:
        _serve(multiprocessing.connection.Connection(fd), tuple(preload))
    except BaseException:
        traceback.print_exc()
        code = 1
    # Out without the interpreter's teardown, as multiprocessing's children leave:
    # unloading rerun and pyarrow costs about 0.3 s of CPU, and a caller that reads the
    # command's output waits for it. Every job's file is closed by then.
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _serve(conn: multiprocessing.connection.Connection, preload: tuple[str, ...]) -> None:
    failures: dict[str, BaseException] = {}
    for name in preload:
        try:
            importlib.import_module(name)
        except BaseException as exc:  # reported when a job needs the module
            failures[name] = exc
    while True:
        try:
            function, args = conn.recv()
        except (EOFError, OSError):
            return
        module, _, attr = function.partition(":")
        try:
            if module in failures:
                raise failures[module]
            value = getattr(importlib.import_module(module), attr)(*args)
            reply: tuple[bool, Any, str] = (True, value, "")
        except BaseException as exc:
            reply = (False, exc, "" if _quiet(exc) else traceback.format_exc())
        try:
            conn.send(reply)
        except OSError:  # the parent is gone (stopped by a signal): no one to tell
            return
        except Exception:  # a result or exception that does not pickle: send its text
            try:
                conn.send((False, RuntimeError(repr(reply[1])), reply[2]))
            except OSError:
                return
