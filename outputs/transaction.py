"""Guards around a command's outputs: nothing lost, nothing half-written, nothing left behind.

Every command that writes files runs inside one :class:`OutputGuard`::

    with OutputGuard(inputs=[scene], files=[rrd, table], folders=[]) as guard:
        ...  # the command's work; writers go through outputs.atomic as always

Entering the guard, before any work starts:

1. **Same file.** An output that is the same file as an input, or as another output of
   the command, is refused. Paths are compared by inode identity when both exist and by
   resolved path otherwise, so symlinks and hard links count as the same file.
2. **Paths.** An output file must not be a folder and its folder must exist (or be
   creatable, for commands that create folders); an output folder must not be a file.
   An output that is a character device (``/dev/null``) is written through, never
   replaced (see :mod:`outputs.atomic`); a named pipe, socket or block device is refused,
   as is an input that is not a file or folder (a named pipe with no writer would block
   the command for ever).
3. **Lock.** Each output takes a lock file beside it (``.NAME.lock``, ``flock``): a second
   command writing the same outputs is refused with a clear message instead of mixing
   its files with the first one's. Creating the lock file also proves the folder is
   writable, at once rather than after the replay.
4. **Stale temporary files.** Temporary files of the atomic writers
   (``.NAME.<12 hex>.tmp``, see :mod:`outputs.atomic`) for these outputs can only be
   left over from an earlier run that was killed (a live writer would hold the lock), so
   they are named on stderr and removed.

While the guard is active, :func:`outputs.atomic.commit` does not rename temporary files
into place; it hands them to the guard. Leaving the guard without an error renames
them all at once (after checking once more that no target is an input); leaving with any
error (``KeyboardInterrupt`` and ``SystemExit`` included) removes them, so a command's
outputs appear all together or not at all. Folders the guard or the command created are
removed again on failure when they are empty, and the lock files are always removed.

A writer that must read back what it wrote (``replay demo`` replays the scene it just
generated) calls :meth:`OutputGuard.commit_now`; that target is rolled back on failure
(a previous version is restored from a hard-link backup).

Also here: :func:`same_file`, :func:`run_with_stall_timeout` (an I/O call that stops
making progress, e.g. on a full disk, fails instead of hanging) and
:func:`free_bytes`. Standard library only.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import pathlib
import re
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from types import TracebackType

from outputs import atomic
from risk.errors import RiskReplayError

TEMP_NAME = re.compile(r"^\.(?P<target>.+)\.[0-9a-f]{12}\.tmp$")
"""Names of :func:`outputs.atomic.temp_path_beside` files (``.NAME.<12 hex>.tmp``)."""

LOCK_SUFFIX = ".lock"

_KIND_NAMES = {
    "device": "a device", "pipe": "a named pipe", "socket": "a socket",
    "block device": "a block device",
}  # fmt: skip


class OutputError(RiskReplayError, RuntimeError):
    """An output path cannot be used: it is an input, used twice, locked or unwritable,
    or a save stalled. The message is meant for the user (``replay.cli.app`` prints it as one
    ``Error:`` line)."""


def same_file(a: str | os.PathLike[str], b: str | os.PathLike[str]) -> bool:
    """True when ``a`` and ``b`` name the same file: same inode when both exist (hard and
    symbolic links included), else the same fully resolved path."""
    try:
        sa, sb = os.stat(a), os.stat(b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)
    return (sa.st_dev, sa.st_ino) == (sb.st_dev, sb.st_ino)


def free_bytes(folder: str | os.PathLike[str]) -> int | None:
    """Bytes available to this user in ``folder``'s file system (None if unknown)."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


def target_of_temp(path: str | os.PathLike[str]) -> str | os.PathLike[str]:
    """The target a temporary file of :mod:`outputs.atomic` stands for (else ``path``; a
    target whose name was too long to keep whole in the temporary name is not known)."""
    m = TEMP_NAME.match(os.path.basename(os.fspath(path)))
    if m is None:
        return path
    return os.path.join(os.path.dirname(os.fspath(path)), m.group("target"))


def lock_path(target: pathlib.Path) -> pathlib.Path:
    """The lock file of an output file or folder: ``.NAME.lock`` beside it."""
    return target.with_name(f".{atomic.hidden_stem(target.name, len(LOCK_SUFFIX))}{LOCK_SUFFIX}")


def stale_temps(target: pathlib.Path, *, folder: bool = False) -> list[pathlib.Path]:
    """Temporary files of the atomic writers for ``target``: ``.NAME.<hex>.tmp`` beside a
    file, or any such file anywhere inside a folder."""
    found: list[pathlib.Path] = []
    if folder:
        if target.is_dir():
            for root, _dirs, names in os.walk(target):
                found += [pathlib.Path(root, n) for n in names if TEMP_NAME.match(n)]
        return sorted(found)
    parent = target.parent
    if parent.is_dir():
        stem = atomic.hidden_stem(target.name)
        prefix = f".{stem}."
        with os.scandir(parent) as entries:
            for e in entries:
                m = TEMP_NAME.match(e.name)
                if m and e.name.startswith(prefix) and m.group("target") == stem:
                    found.append(pathlib.Path(e.path))
    return sorted(found)


class _Lock:
    """An exclusive, non-blocking ``flock`` on a lock file, removed on release."""

    def __init__(self, path: pathlib.Path, target: pathlib.Path) -> None:
        self.path = path
        self.target = target
        self.fd: int | None = None

    def acquire(self) -> None:
        for _ in range(20):  # the file may be removed by its previous holder meanwhile
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError as exc:
                raise OutputError(
                    f"{self.target}: cannot write in folder {self.path.parent}"
                    f" ({exc.strerror or exc}); choose another output"
                ) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = _read_pid(fd)
                os.close(fd)
                if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    who = f" (process {holder})" if holder else ""
                    raise OutputError(
                        f"{self.target}: another replay command{who} is writing this output"
                        " now; wait for it to finish or choose another output"
                    ) from None
                raise
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.write(fd, f"{os.getpid()}\n".encode())
                self.fd = fd
                return
            os.close(fd)  # we locked a file its holder had just removed: try again
        raise OutputError(f"{self.target}: could not take the lock {self.path}; try again")

    def release(self) -> None:
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            self.path.unlink()
        os.close(self.fd)
        self.fd = None


def _read_pid(fd: int) -> str:
    with contextlib.suppress(OSError, ValueError):
        text = os.pread(fd, 32, 0).decode().strip()
        if text.isdigit():
            return text
    return ""


class OutputGuard:
    """Checks, locks and commits a command's outputs all together; see the module docstring.

    ``inputs``: files the command reads (never written). ``files``: output files.
    ``folders``: output folders (created by the command; their contents are outputs).
    ``create_folders``: create missing folders of output files at once (else a missing
    folder is an error). ``transaction``: defer the renames to the end (set False for a
    command whose writers must be durable one by one, e.g. a resumable batch).
    ``report``: where notes about removed stale files go (default: stderr).
    """

    def __init__(
        self,
        *,
        inputs: Iterable[str | os.PathLike[str] | None] = (),
        files: Iterable[str | os.PathLike[str] | None] = (),
        folders: Iterable[str | os.PathLike[str] | None] = (),
        create_folders: bool = False,
        transaction: bool = True,
        report: Callable[[str], None] | None = None,
    ) -> None:
        self.inputs = [pathlib.Path(p) for p in inputs if p is not None]
        self.files = [pathlib.Path(p) for p in files if p is not None]
        self.folders = [pathlib.Path(p) for p in folders if p is not None]
        self.create_folders = create_folders
        self.transaction = transaction
        self.report = report or (lambda text: print(text, file=sys.stderr))
        self._locks: list[_Lock] = []
        self._created: list[pathlib.Path] = []  # folders that did not exist at the start
        self._pending: dict[pathlib.Path, pathlib.Path] = {}  # target -> temporary file
        self._device_writes: list[tuple[pathlib.Path, pathlib.Path]] = []  # (device, tmp)
        self._backups: list[tuple[pathlib.Path, pathlib.Path | None]] = []  # committed early
        self._previous_hook: Callable[[pathlib.Path, pathlib.Path], None] | None = None
        self._pid = os.getpid()

    # ------------------------------------------------------------------ checks
    def check(self) -> None:
        """The path checks alone (1 and 2 of the module docstring)."""
        for inp in self.inputs:
            kind = atomic.target_kind(inp)
            if kind not in ("file", "folder", "missing"):
                raise OutputError(
                    f"{inp}: is {_KIND_NAMES[kind]}, not a file; give the file itself"
                    " (a pipe or device would be read for ever or not at all)"
                )
        for path in [*self.files, *self.folders]:
            blocker = _file_among_parents(path)
            if blocker is not None:
                raise OutputError(
                    f"{path}: {blocker} is a file, not a folder, so nothing can be written"
                    " under it; choose an output path in a folder"
                )
        devices = [p for p in self.files if self._device(p)]
        outputs = [p for p in [*self.files, *self.folders] if p not in devices]
        for path in self.files:
            if path in devices:
                continue  # written through (outputs.atomic.place)
            if path.is_dir():
                raise OutputError(f"{path}: is a folder; give a file name for this output")
            parent = path.parent
            if parent.exists() and not parent.is_dir():
                raise OutputError(f"{path}: {parent} is not a folder")
            created = any(parent == d or d in parent.parents for d in self.folders)
            if not parent.exists() and not (self.create_folders or created):
                raise OutputError(
                    f"cannot write {path}: folder {parent} does not exist; create it first"
                )
        for path in self.folders:
            if path.exists() and not path.is_dir():
                raise OutputError(f"{path}: exists and is not a folder; give a folder")
        for out in outputs:
            for inp in self.inputs:
                if same_file(out, inp):
                    raise OutputError(
                        f"{out}: is also an input ({inp}); writing it would destroy the input."
                        " Choose another output path"
                    )
        for i, a in enumerate(outputs):
            for b in outputs[i + 1 :]:
                if same_file(a, b):
                    raise OutputError(
                        f"{b}: the same file is given for two outputs ({_which(a, b)});"
                        " give each output its own path"
                    )

    @staticmethod
    def _device(path: pathlib.Path) -> bool:
        try:
            return atomic.check_target(path) == "device"
        except OSError as exc:
            raise OutputError(f"{path}: {exc.strerror}") from None

    def _check_target(self, target: pathlib.Path) -> None:
        for inp in self.inputs:
            if same_file(target, inp):
                raise OutputError(
                    f"{target}: is also an input ({inp}); refusing to write over it."
                    " Choose another output folder"
                )

    # ------------------------------------------------------------------ enter / exit
    def __enter__(self) -> OutputGuard:
        self.check()
        try:
            for folder in self._folders_to_create():
                folder.mkdir()
                self._created.append(folder)
            devices = {p for p in self.files if self._device(p)}
            for target in sorted({*self.files, *self.folders} - devices, key=str):
                lock = _Lock(lock_path(target), target)
                lock.acquire()
                self._locks.append(lock)
            for target in set(self.files) - devices:
                self._remove_stale(stale_temps(target))
            for target in self.folders:
                self._remove_stale(stale_temps(target, folder=True))
        except BaseException:
            self._release()
            self._remove_created()
            raise
        if self.transaction:
            self._previous_hook = atomic.set_commit_hook(self._defer)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self.transaction:
            atomic.set_commit_hook(self._previous_hook)
        failed = exc_type is not None
        try:
            if failed:
                self._rollback()
            else:
                self._commit_all()
        except BaseException:
            failed = True
            self._rollback()
            raise
        finally:
            self._release()  # the lock files first: they sit in folders we may remove
            if failed:
                self._remove_created()
        if isinstance(exc, OSError) and not exc.filename and exc.strerror:
            # e.g. ENOSPC from a writer that holds only a file object: name the outputs
            names = ", ".join(str(p) for p in [*self.files, *self.folders])
            raise OutputError(
                f"could not write {names}: {exc.strerror}; nothing was written (free some"
                " space or choose another output and run again)"
            ) from None

    # ------------------------------------------------------------------ transaction
    def _defer(self, tmp: pathlib.Path, target: pathlib.Path) -> None:
        if os.getpid() != self._pid:  # a forked child: not ours to defer
            os.replace(tmp, target)
            return
        self._check_target(target)
        if atomic.target_kind(target) == "device":  # (-o /dev/null --table /dev/null: fine)
            self._device_writes.append((target, tmp))
            return
        old = self._pending.pop(target, None)
        if old is not None and old != tmp:
            old.unlink(missing_ok=True)
            tmp.unlink(missing_ok=True)
            raise OutputError(
                f"{target}: two outputs of this command would be written to this one file;"
                " give each output its own path"
            )
        self._pending[target] = tmp

    def pending(self) -> dict[pathlib.Path, pathlib.Path]:
        """Targets waiting for the commit -> their temporary files (devices included)."""
        return {**dict(self._device_writes), **self._pending}

    def commit_now(self, target: str | os.PathLike[str]) -> pathlib.Path:
        """Move one pending target into place now (to read it back); on a later failure
        it is removed, or its previous version restored."""
        target = pathlib.Path(target)
        if atomic.target_kind(target) == "device":  # written through: nothing to restore
            for entry in [e for e in self._device_writes if e[0] == target]:
                self._device_writes.remove(entry)
                atomic.place(entry[1], target)
            return target
        tmp = self._pending.pop(target)
        backup = None
        if target.exists():
            backup = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}.tmp")
            os.link(target, backup)
        self._backups.append((target, backup))
        os.replace(tmp, target)
        return target

    def _commit_all(self) -> None:
        for target in self._pending:
            self._check_target(target)
        # devices first: a device that refuses the bytes (/dev/full) fails the command
        # before any file has been renamed into place
        while self._device_writes:
            target, tmp = self._device_writes.pop(0)
            atomic.place(tmp, target)
        for target, tmp in list(self._pending.items()):
            atomic.place(tmp, target)
            del self._pending[target]
        for _, backup in self._backups:
            if backup is not None:
                backup.unlink(missing_ok=True)
        self._backups.clear()

    def _rollback(self) -> None:
        for _, tmp in self._device_writes:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        self._device_writes.clear()
        for tmp in self._pending.values():
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
        self._pending.clear()
        for target, backup in reversed(self._backups):
            with contextlib.suppress(OSError):
                if backup is None:
                    target.unlink(missing_ok=True)
                else:
                    os.replace(backup, target)
        self._backups.clear()

    # ------------------------------------------------------------------ housekeeping
    def _folders_to_create(self) -> list[pathlib.Path]:
        wanted: list[pathlib.Path] = []
        roots = [*self.folders]
        if self.create_folders:
            roots += [p.parent for p in self.files]
        else:
            roots += [p.parent for p in self.files if p.parent in self.folders]
        for root in roots:
            missing = []
            p = root
            while not p.exists() and p != p.parent:
                missing.append(p)
                p = p.parent
            wanted += [m for m in reversed(missing) if m not in wanted]
        return wanted

    def _remove_created(self) -> None:
        for folder in reversed(self._created):
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty
        self._created.clear()

    def _remove_stale(self, paths: list[pathlib.Path]) -> None:
        for path in paths:
            try:
                size = path.stat().st_size
                path.unlink()
            except FileNotFoundError:
                continue
            self.report(
                f"Removed a stale temporary file left by an interrupted run: {path} ({size} bytes)"
            )

    def _release(self) -> None:
        for lock in reversed(self._locks):
            lock.release()
        self._locks.clear()


# ---------------------------------------------------------------------- stalled I/O
STALL_ENV = "RISKREPLAY_STALL_TIMEOUT_S"
DEFAULT_STALL_S = 60.0
#: Free space above which a stalled save is not blamed on a full disk.
ROOMY_BYTES = 1 << 30


def stall_timeout_s() -> float:
    """Seconds without progress after which :func:`run_with_stall_timeout` gives up
    (``RISKREPLAY_STALL_TIMEOUT_S``, default 60)."""
    try:
        value = float(os.environ.get(STALL_ENV, DEFAULT_STALL_S))
    except ValueError:
        return DEFAULT_STALL_S
    return value if value > 0 else DEFAULT_STALL_S


def run_with_stall_timeout(
    work: Callable[[], None],
    *,
    watch: pathlib.Path,
    target: pathlib.Path,
    stall_s: float | None = None,
    poll_s: float = 0.2,
) -> None:
    """Run ``work`` (which writes ``watch``) in a helper thread; if ``watch`` stops growing
    for ``stall_s`` seconds while ``work`` is still running, raise :class:`OutputError`
    naming ``target`` (the helper thread, stuck in native code, is abandoned: it is a
    daemon thread). Exceptions of ``work`` are re-raised here."""
    limit = stall_timeout_s() if stall_s is None else stall_s
    outcome: list[BaseException] = []

    def body() -> None:
        try:
            work()
        except BaseException as exc:
            outcome.append(exc)

    thread = threading.Thread(target=body, name=f"write {target.name}", daemon=True)
    thread.start()
    last_size, last_change = -1, time.monotonic()
    while True:
        thread.join(poll_s)
        if not thread.is_alive():
            break
        try:
            size = watch.stat().st_size
        except OSError:
            size = -1
        now = time.monotonic()
        if size != last_size:
            last_size, last_change = size, now
        elif now - last_change > limit:
            free = free_bytes(target.parent)
            if free is not None and free > ROOMY_BYTES:
                # Not the disk: the writer itself is stuck, or still encoding before it
                # writes (a false "disk full" sent users to free space for nothing).
                raise OutputError(
                    f"could not write {target}: the writer made no progress for {limit:g} s"
                    f" although {free / 2**30:.1f} GiB are free in {target.parent}; the"
                    f" output may be too large to write in time (set {STALL_ENV} to wait"
                    " longer) or the writer is stuck"
                )
            space = "" if free is None else f", {free} bytes free in {target.parent}"
            raise OutputError(
                f"could not write {target}: the save made no progress for {limit:g} s"
                f" (disk full or stalled{space}); free some space and run again"
            )
    if outcome:
        raise outcome[0]


def _which(a: pathlib.Path, b: pathlib.Path) -> str:
    """How two outputs that are one file were given: the command-line options whose value
    is that file (``-o and --table``), else the two paths (issue 36: "out and out")."""
    args = sys.argv[1:]
    options = []
    for k, arg in enumerate(args):
        option, eq, value = arg.partition("=")
        if not option.startswith("-"):
            continue
        if not eq:
            if k + 1 >= len(args):
                continue
            value = args[k + 1]
        with contextlib.suppress(OSError, ValueError):
            if value and same_file(pathlib.Path(value), a) and option not in options:
                options.append(option)
    if len(options) >= 2:
        return " and ".join(options)
    return f"{a} and {b}" if str(a) != str(b) else "the same path twice"


def _file_among_parents(path: pathlib.Path) -> pathlib.Path | None:
    """The nearest existing parent of ``path`` when it is not a folder (``out/x`` with a
    file ``out``: mkdir failed with a bare "Not a directory", issue 36), else None."""
    for parent in path.absolute().parents:
        if parent.exists():
            return None if parent.is_dir() else _shown(parent, path)
    return None


def _shown(parent: pathlib.Path, path: pathlib.Path) -> pathlib.Path:
    """``parent`` as the user wrote it (relative when ``path`` was)."""
    for given in path.parents:
        if given.absolute() == parent:
            return given
    return parent
