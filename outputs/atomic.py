"""Atomic file output: write beside the target, rename into place only on success.

Every writer of the project (MCAP scenes, tables, recordings, cascade files, statistics,
plots) goes through here (:func:`atomic_output`, :func:`atomic_write`, :func:`write_text`),
so that an interrupted run never leaves a half-written file and every output gets the
permissions of an ordinary new file (``mkstemp`` would make it 0600). Standard library
only, so every layer can use it (see :mod:`outputs`).
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import re
import uuid
from collections.abc import Callable, Iterator
from typing import Any

CommitHook = Callable[[pathlib.Path, pathlib.Path], None]
_commit_hook: CommitHook | None = None  # set by outputs.transaction.OutputGuard while it is active


def temp_path_beside(path: str | os.PathLike[str]) -> pathlib.Path:
    """Create and return an empty, uniquely named temporary file in ``path``'s folder.

    The file is hidden (``.NAME.<random>.tmp``), created exclusively, with mode 0666 less
    the umask, like any new file. ``os.replace`` from it to ``path`` is atomic because both
    are on the same file system.
    """
    target = pathlib.Path(path)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}.tmp")
    os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
    return tmp


def set_commit_hook(hook: CommitHook | None) -> CommitHook | None:
    """Route :func:`commit` through ``hook`` (None: rename at once); returns the old hook.

    ``outputs.transaction.OutputGuard`` uses it to commit a command's outputs all together."""
    global _commit_hook
    previous, _commit_hook = _commit_hook, hook
    return previous


def commit(tmp: str | os.PathLike[str], target: str | os.PathLike[str]) -> None:
    """Move a finished temporary file onto its target: at once, or, inside an
    ``OutputGuard``, together with the command's other outputs when it succeeds."""
    if _commit_hook is not None:
        _commit_hook(pathlib.Path(tmp), pathlib.Path(target))
    else:
        os.replace(tmp, target)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike[str]) -> Iterator[pathlib.Path]:
    """Yield a temporary path to write to; on success it replaces ``path`` atomically.

    On any exception (including KeyboardInterrupt) the temporary file is removed and an
    existing ``path`` is left untouched.
    """
    target = pathlib.Path(path)
    tmp = temp_path_beside(target)
    try:
        yield tmp
        commit(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_bytes(path: str | os.PathLike[str], data: bytes) -> pathlib.Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(data)
    return pathlib.Path(path)


def write_text(path: str | os.PathLike[str], text: str) -> pathlib.Path:
    """Write UTF-8 ``text`` to ``path`` atomically; returns the path."""
    return write_bytes(path, text.encode("utf-8"))


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], Any]) -> pathlib.Path:
    """Call ``write(tmp)`` with a temporary file beside ``path`` (for writers that take a
    file name: polars, matplotlib), which then replaces ``path`` atomically; returns the
    path."""
    with atomic_output(path) as tmp:
        write(str(tmp))
    return pathlib.Path(path)


def safe_name(name: str, fallback: str = "scene") -> str:
    """A file name stem from data (a scenario id, a file name): letters, digits, ``-``,
    ``_`` and ``.`` only, every other run of characters one ``_``; ``fallback`` when
    nothing is left."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    return cleaned or fallback
