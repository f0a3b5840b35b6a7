"""Building the kernel ahead of time (:mod:`risk.kernel_aot` says what, where and why):
``python -m risk.kernel_aot_build`` in the foreground, or as
:func:`risk.kernel_aot.start_background_build` starts it, in a detached process.

Apart from :mod:`risk.kernel_aot` (which finds and loads the built module, and which
:mod:`risk.kernel` imports) because the build warms the just-in-time kernel up first
(:func:`risk.kernel.warm_up`): one module doing both would import :mod:`risk.kernel`,
which imports it.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import sys
import tempfile
import time
import types
import warnings

from risk import kernel, kernel_numba
from risk.errors import RiskReplayError
from risk.kernel_aot import (
    ENTRY_POINTS,
    MODULE_NAME,
    STALE_LOCK_S,
    _failed_marker,
    _lock_path,
    build_key,
    builds_dir,
    module_path,
    target_cpu,
)
from risk.kernel_shared import cache_dir

#: Builds kept in the cache folder (the newest; older sources and installations go).
KEEP_BUILDS = 4


class AotBuildError(RiskReplayError, RuntimeError):
    """The ahead-of-time module could not be built (no C compiler, a numba error, ...)."""


def _take_lock(lock: pathlib.Path) -> bool:
    lock.parent.mkdir(parents=True, exist_ok=True)
    try:
        if time.time() - lock.stat().st_mtime > STALE_LOCK_S:
            lock.unlink(missing_ok=True)
    except FileNotFoundError:
        pass
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    os.write(fd, str(os.getpid()).encode())
    os.close(fd)
    return True


def _wrappers(kernel_numba: types.ModuleType) -> dict[str, types.FunctionType]:
    """One plain function per entry point that calls the ``@njit`` function: compiled by
    ``pycc``, it keeps the callee's own options (numpy's error model) in the module."""
    out: dict[str, types.FunctionType] = {}
    for name in ENTRY_POINTS:
        dispatcher = getattr(kernel_numba, name)
        if not dispatcher.nopython_signatures:
            continue  # (cascade_agents where the CPU has no cycle counter)
        n_args = len(dispatcher.nopython_signatures[0].args)
        params = ", ".join(f"a{i}" for i in range(n_args))
        namespace: dict[str, object] = {"compiled": dispatcher}
        exec(f"def {name}({params}):\n    return compiled({params})\n", namespace)
        out[name] = namespace[name]  # type: ignore[assignment]
    return out


def build(cache_dir: str | os.PathLike[str]) -> pathlib.Path:
    """Build the module for this installation into ``cache_dir`` (no-op when it exists)
    and return its path. Raises :class:`AotBuildError` when it cannot be built, and
    ``FileExistsError`` while another process builds it."""
    key = build_key()
    target = module_path(cache_dir, key)
    if target.is_file():
        return target
    lock = _lock_path(cache_dir, key)
    if not _take_lock(lock):
        raise FileExistsError(f"another process is building {target.parent} ({lock})")
    work: pathlib.Path | None = None
    try:
        work = pathlib.Path(tempfile.mkdtemp(prefix=".build-", dir=builds_dir(cache_dir)))
        kernel.warm_up(kernel_numba)  # one signature per entry point, from the JIT cache
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # pycc's pending-deprecation warning
                from numba.pycc import CC  # (checks for a C compiler)

                cc = CC(MODULE_NAME)
                cc.output_dir = str(work)
                cc.target_cpu = target_cpu()  # the host, or NUMBA_CPU_NAME (in the key)
                cc.verbose = False
                for name, wrapper in _wrappers(kernel_numba).items():
                    signature = getattr(kernel_numba, name).nopython_signatures[0]
                    cc.export(name, signature)(wrapper)
                cc.compile()
        except Exception as exc:  # no C compiler, a linker or numba failure
            message = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
            _failed_marker(cache_dir, key).write_text(message + "\n")
            raise AotBuildError(message) from exc
        built = work / target.name
        final = work / "module"
        final.mkdir()
        built.rename(final / target.name)
        try:
            os.rename(final, target.parent)
        except OSError:
            if not target.is_file():
                raise
        _failed_marker(cache_dir, key).unlink(missing_ok=True)
        _prune(cache_dir, keep=target.parent)
        return target
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        lock.unlink(missing_ok=True)


def _prune(cache_dir: str | os.PathLike[str], keep: pathlib.Path) -> None:
    """Remove all but the newest :data:`KEEP_BUILDS` builds (``keep`` always stays)."""
    builds = [
        p for p in builds_dir(cache_dir).iterdir() if p.is_dir() and not p.name.startswith(".")
    ]
    builds.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    for old in [p for p in builds if p != keep][KEEP_BUILDS - 1 :]:
        shutil.rmtree(old, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m risk.kernel_aot_build",
        description="Build the risk kernel ahead of time into the kernel cache folder "
        "(NUMBA_CACHE_DIR, else ~/.cache/riskreplay/numba), so that new processes load it "
        "in about 1 ms instead of setting up numba (about 0.9 s). Needs a C compiler.",
    )
    parser.add_argument(
        "--background", action="store_true", help="quiet; as started by the replay commands"
    )
    args = parser.parse_args(argv)
    folder = cache_dir()
    start = time.perf_counter()
    try:
        path = build(folder)
    except FileExistsError as exc:
        print(f"riskreplay: {exc}; try again when it ends", file=sys.stderr)
        return 0 if args.background else 1
    except AotBuildError as exc:
        print(f"Error: the ahead-of-time kernel cannot be built: {exc}", file=sys.stderr)
        return 1
    if not args.background:
        print(f"Built in {time.perf_counter() - start:.1f} s: {path}")
    else:
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        print(f"{stamp} built {path} in {time.perf_counter() - start:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
