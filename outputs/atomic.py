"""Atomic file output: write beside the target, rename into place only on success.

Every writer of the project (MCAP scenes, tables, recordings, cascade files, statistics,
plots) goes through here (:func:`atomic_output`, :func:`atomic_write`, :func:`write_text`),
so that an interrupted run never leaves a half-written file and every output gets the
permissions of an ordinary new file (``mkstemp`` would make it 0600). Standard library
only, so every layer can use it (see :mod:`outputs`).

Outputs that are not files. A target that is a character device (``-o /dev/null``: the
user means "discard") is never renamed over: the finished temporary file is copied into
the device (:func:`place`), so that the node stays, and a device that refuses the bytes
(``/dev/full``) fails the command. The temporary file of a device lives in the system's
temporary folder, not in ``/dev``. A named pipe, socket or block device as a target is
refused (:func:`check_target`): a pipe without a reader would block, and the others are
not files to write a result to.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import pathlib
import re
import shutil
import stat
import tempfile
import uuid
from collections.abc import Callable, Iterator
from typing import Any

CommitHook = Callable[[pathlib.Path, pathlib.Path], None]
_commit_hook: CommitHook | None = None  # set by outputs.transaction.OutputGuard while it is active


#: Longest file name (bytes) of most file systems; a hidden name beside the target must
#: fit too (``NAME_MAX`` of ext4, xfs, btrfs, tmpfs).
NAME_MAX = 255
_SUFFIX_BYTES = len(".0123456789ab.tmp")


def hidden_stem(name: str, reserve: int = _SUFFIX_BYTES) -> str:
    """``name`` as it appears in the hidden files beside it (``.STEM.<hex>.tmp``,
    ``.STEM.lock``): the name itself, or, when that would make a file name longer than
    :data:`NAME_MAX` bytes, its start and a hash of the whole (a 249-character output
    name is legal, so its temporary file must be too)."""
    encoded = name.encode("utf-8", "surrogateescape")
    if 1 + len(encoded) + reserve <= NAME_MAX:
        return name
    digest = hashlib.sha1(encoded).hexdigest()[:10]
    keep = encoded[: NAME_MAX - 1 - reserve - len(digest) - 1]
    return keep.decode("utf-8", "ignore") + "~" + digest


def target_kind(path: str | os.PathLike[str]) -> str:
    """What ``path`` is now: ``missing``, ``file``, ``folder``, ``device`` (a character
    device: /dev/null, /dev/full, a terminal), ``pipe``, ``socket`` or
    ``block device``."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return "missing"
    if stat.S_ISREG(mode):
        return "file"
    if stat.S_ISDIR(mode):
        return "folder"
    if stat.S_ISCHR(mode):
        return "device"
    if stat.S_ISFIFO(mode):
        return "pipe"
    return "socket" if stat.S_ISSOCK(mode) else "block device"


_REFUSED = {"pipe": "a named pipe", "socket": "a socket", "block device": "a block device"}


def check_target(path: str | os.PathLike[str]) -> str:
    """:func:`target_kind` of an output, refusing the kinds no output may be written to
    (``OSError`` naming the path and what to give instead)."""
    kind = target_kind(path)
    if kind in _REFUSED:
        raise OSError(
            errno.EINVAL,
            f"is {_REFUSED[kind]}, not a file; give a file name for this output"
            " (or /dev/null to discard it)",
            os.fspath(path),
        )
    return kind


def temp_path_beside(path: str | os.PathLike[str]) -> pathlib.Path:
    """Create and return an empty, uniquely named temporary file in ``path``'s folder.

    The file is hidden (``.NAME.<random>.tmp``), created exclusively, with mode 0666 less
    the umask, like any new file. ``os.replace`` from it to ``path`` is atomic because both
    are on the same file system. For a character device (``/dev/null``) the file is made
    in the system's temporary folder instead; :func:`place` copies it into the device.
    """
    target = pathlib.Path(path)
    folder = target.parent
    if check_target(target) == "device":
        folder = pathlib.Path(tempfile.gettempdir())
    tmp = folder / f".{hidden_stem(target.name)}.{uuid.uuid4().hex[:12]}.tmp"
    os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
    return tmp


#: Files this process has put in place, in order (the last :data:`_PLACED_KEPT`): a
#: failure after them (stdout full) can say what was written before it.
_placed: list[pathlib.Path] = []
_PLACED_KEPT = 1000


def placed_outputs() -> list[pathlib.Path]:
    """The files this process has renamed into place so far (the latest 1,000)."""
    del _placed[:-_PLACED_KEPT]
    return list(_placed)


def place(tmp: str | os.PathLike[str], target: str | os.PathLike[str]) -> None:
    """Put a finished temporary file in place: rename it onto ``target``, or, when
    ``target`` is a character device, copy its bytes into the device and remove it (the
    device node is never replaced). A device that does not take the bytes raises
    ``OSError`` naming ``target``."""
    if check_target(target) != "device":
        os.replace(tmp, target)
        _placed.append(pathlib.Path(target))
        return
    try:
        with open(tmp, "rb") as src, open(target, "wb") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), os.fspath(target)) from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


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
        place(tmp, target)


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


#: Longest stem :func:`safe_name` returns: a file name holds 255 bytes, and the stem
#: still gets a suffix, a ``-2`` when names collide and a temporary name around it.
MAX_STEM = 120


def safe_name(name: str, fallback: str = "scene") -> str:
    """A file name stem from data (a scenario id, a file name): letters, digits, ``-``,
    ``_`` and ``.`` only, every other run of characters one ``_``; ``fallback`` when
    nothing is left. A longer stem than :data:`MAX_STEM` is cut and ends in 12 hex digits
    of a hash of the whole name (a 300-character scenario id failed with "File name too
    long"; two long ids that share a beginning stay apart)."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")
    if len(cleaned) > MAX_STEM:
        digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:12]
        cleaned = f"{cleaned[: MAX_STEM - 13]}-{digest}"
    return cleaned or fallback
