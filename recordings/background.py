"""The recording's writer in a second process: it imports rerun while the replay runs.

Importing rerun takes about 1 s, writing a recording a few tenths; both used to come on
top of the replay. :class:`WriterProcess` forks a process that imports
:mod:`recordings.writer` at once and then waits for one job: the scene's description,
its frames and where to write them. The replay hands them over at the end
(``SceneRecorder.close``) and waits for the file. With two CPUs the import costs no wall
time; on one CPU, or without ``fork`` (Windows, macOS, where forking is unsafe with many
system libraries), the recorder writes in its own process instead.

A command that will record can start the process before it imports the models
(:func:`start_early`); the recorder then adopts it (:func:`take_early`). This module
imports only the standard library (and the recordings' error type), so that starting
early costs nothing.

The process never removes or renames anything on its own behalf: the parent names the
temporary file, and removes it when the process fails or is stopped.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import os
import pathlib
import signal
import sys
import traceback
from typing import Any

from recordings.errors import RecordingError

#: Set (to anything but 0) to write recordings in the replay's own process.
INLINE_VARIABLE = "RISKREPLAY_RECORD_INLINE"

_early: WriterProcess | None = None


def can_write_in_background() -> bool:
    """Whether a writer process helps (a second CPU) and can start (``fork`` on Linux),
    and is not switched off by ``RISKREPLAY_RECORD_INLINE``."""
    if os.environ.get(INLINE_VARIABLE, "") not in ("", "0"):
        return False
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return (
        (cpus or 1) >= 2
        and sys.platform.startswith("linux")
        and "fork" in multiprocessing.get_all_start_methods()
    )


def start_early() -> None:
    """Start a writer process now, for the recorder of this command to adopt (does
    nothing when one is waiting already or the background cannot help)."""
    global _early
    if _early is None and can_write_in_background():
        _early = WriterProcess()


def take_early() -> WriterProcess | None:
    """The writer process started by :func:`start_early`, if any (once)."""
    global _early
    writer, _early = _early, None
    return writer


def discard_early() -> None:
    """Stop a writer process that was started early but not adopted (the command ended
    before recording, e.g. on bad input)."""
    writer = take_early()
    if writer is not None:
        writer.stop()


class WriterProcess:
    """A forked process that imports the writer (and rerun) at once, then writes one
    recording when :meth:`write` hands it the job."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("fork")
        self._conn, child_end = ctx.Pipe()
        self._process = ctx.Process(
            target=_writer_main,
            args=(child_end, self._conn),
            name="riskreplay-recording",
            daemon=True,
        )
        self._process.start()
        child_end.close()

    def write(
        self, output: pathlib.Path, tmp: pathlib.Path, info: Any, frames: list[Any], options: Any
    ) -> None:
        """Have the process write the recording to ``tmp`` and rename it to ``output``;
        raise what it raised. ``info`` must pickle (a ``SceneInfo`` without ``tracks``).
        Waits as long as the file takes, and notices when the process dies."""
        with contextlib.suppress(OSError):  # the process is gone: its exit code says why
            self._conn.send(("write", output, tmp, info, frames, options))
        reply = None
        while reply is None:
            if self._conn.poll(0.2):
                try:
                    reply = self._conn.recv()
                except EOFError:
                    break
            elif not self._process.is_alive():
                break
        self._process.join(timeout=5.0)
        self._conn.close()
        if reply is None:
            raise RecordingError(
                f"the recording process stopped (exit code {self._process.exitcode}) before "
                f"writing {output}; run again, and if it happens again set "
                f"{INLINE_VARIABLE}=1 to write in the replay's own process"
            )
        status, exc, text = reply
        if status == "failed":
            if text:
                exc.add_note(f"in the recording process:\n{text}")
            raise exc

    def stop(self) -> None:
        """End the process, whatever it is doing."""
        if self._process.is_alive():
            self._process.terminate()
        self._process.join(timeout=5.0)
        self._conn.close()


def _writer_main(
    conn: multiprocessing.connection.Connection, parent_end: multiprocessing.connection.Connection
) -> None:
    # Ctrl-C goes to the whole process group: the parent handles it and stops this one.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent_end.close()  # so that recv() ends (EOFError) when the parent is gone
    failure: BaseException | None = None
    try:
        from recordings import writer
    except BaseException as exc:  # reported when the parent asks for the file
        failure = exc
    try:
        message = conn.recv()
    except EOFError:
        return
    if message[0] != "write":
        return
    _, output, tmp, info, frames, options = message
    try:
        if failure is not None:
            raise failure
        writer.write_file(output, tmp, info, frames, options)
        reply: tuple[str, BaseException | None, str] = ("done", None, "")
    except BaseException as exc:
        expected = isinstance(exc, RecordingError)  # its message is the whole story
        reply = ("failed", exc, "" if expected else traceback.format_exc())
    try:
        conn.send(reply)
    except Exception:  # an exception that does not pickle: send its text instead
        conn.send(("failed", RuntimeError(f"{reply[1]!r}"), reply[2]))
