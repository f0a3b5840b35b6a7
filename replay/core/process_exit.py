"""Worker processes that never outlive their driver.

A worker of ``replay batch`` (or of any process pool of the project) calls
:func:`exit_with_parent` once when it starts: a daemon thread checks twice a second
whether the process that started it is still its parent, and ends the worker at once
when it is not (the driver was killed with SIGKILL, crashed, or ended without shutting
its pool down).

Stopping. :func:`stop_on_signals` (installed once, by ``replay.cli`` around every
command) turns SIGTERM and SIGHUP (a closed terminal) into :class:`Stopped`, a
``KeyboardInterrupt`` like Ctrl-C's, so that the same clean-up runs for all three: the
output guard removes temporary and partial files, the process pool shuts its workers
down (no leaked semaphores), and the CLI exits with ``128 + signal`` (130, 143, 129).
Standard library only.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator

CHECK_EVERY_S = 0.5


def exit_with_parent(
    parent: int | None = None, interval_s: float = CHECK_EVERY_S
) -> threading.Thread:
    """Start watching the parent (``parent``: the pid the caller was started by, passed
    from there, so that a driver that died while this process was still starting is
    noticed too); the calling process exits (status 1) when it is gone."""
    parent = os.getppid() if parent is None else parent
    if os.getppid() != parent:
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(interval_s)
            if os.getppid() != parent:  # re-parented: the driver is dead
                os._exit(1)

    thread = threading.Thread(target=watch, name="exit-with-parent", daemon=True)
    thread.start()
    return thread


#: The signals that stop a command, besides SIGINT (Ctrl-C, Python's own).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class Stopped(KeyboardInterrupt):
    """A command stopped by a signal; ``signum`` says which (SIGINT for Ctrl-C)."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(f"stopped by {signal_name(signum)}")
        self.signum = signum


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def exit_status(exc: BaseException) -> int:
    """The shell's status for a command stopped by ``exc``: 128 + the signal number."""
    return 128 + int(getattr(exc, "signum", signal.SIGINT))


def _interrupt(signum: int, frame: object) -> None:
    # Raised once: a second signal while the clean-up runs must not cut it short.
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    raise Stopped(signum)


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """While active (in the main thread; elsewhere it does nothing): SIGTERM and SIGHUP
    raise :class:`Stopped`; the previous handlers come back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig, handler in previous.items():
        if handler is not signal.SIG_IGN:  # (nohup: a hang-up is to be ignored)
            signal.signal(sig, _interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold back Ctrl-C, SIGTERM and SIGHUP while starting processes, then act on them.

    Two layers, because the kernel hands a process-directed signal to any thread that
    does not block it (a pool's threads, tqdm's) and Python then runs the handler in the
    main thread at its next instruction, in the middle of writing a new worker's start-up
    data (the worker then died printing EOFError: seen under CI). So: SIGINT is blocked
    in this thread (a new process inherits the mask, so a Ctrl-C while it imports cannot
    interrupt it), and in the main thread the three signals' Python handlers are swapped
    for ones that only remember the signal; when the block ends, the first one
    remembered runs its own handler (a KeyboardInterrupt, a stop)."""
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    held: list[tuple[int, object]] = []
    previous: dict[int, object] = {}
    if threading.current_thread() is threading.main_thread():
        previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, *STOP_SIGNALS)}
        for sig, handler in previous.items():
            if callable(handler):  # (an ignored or default signal stays as it is)
                signal.signal(sig, lambda signum, frame: held.append((signum, frame)))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            if callable(handler):
                signal.signal(sig, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        if held:
            signum, frame = held[0]
            handler = previous[signum]
            if callable(handler):
                handler(signum, frame)
