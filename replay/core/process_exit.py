"""Worker processes that never outlive their driver.

A worker of ``replay batch`` (or of any process pool of the project) calls
:func:`exit_with_parent` once when it starts: a daemon thread checks twice a second
whether the process that started it is still its parent, and ends the worker at once
when it is not (the driver was killed with SIGKILL, crashed, or ended without shutting
its pool down). :func:`sigterm_as_interrupt` makes SIGTERM to a driver behave like
Ctrl-C, so that its usual clean-up runs. Standard library only.
"""

from __future__ import annotations

import os
import signal
import threading
import time

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


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def sigterm_as_interrupt() -> None:
    """In the main thread: SIGTERM raises KeyboardInterrupt, like SIGINT."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _interrupt)
