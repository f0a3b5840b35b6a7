"""The kernel compiled ahead of time: an extension module built by numba's ``pycc`` from
:mod:`risk.kernel_numba`, once per source, numba, CPU and Python, into the cache folder.

Why: the just-in-time form costs every new process about 0.9 s before its first result
(importing numba, setting up its compiler and loading the cached code), which is most of
``replay run``'s wall time on a typical scene. The extension module loads in about 1 ms
and imports neither numba nor LLVM. Its code is the same LLVM code numba compiles just in
time (the entry points call the same ``@njit`` functions), so the results agree bit for
bit (tested).

Where: ``<cache>/aot/<key>/riskreplay_kernel_aot<suffix>``, ``<key>`` a hash of the
kernel's source files, the numba and llvmlite installations, numpy's version, the Python
ABI and the CPU (the code is compiled for the host CPU, or the one ``NUMBA_CPU_NAME`` /
``NUMBA_CPU_FEATURES`` name). A changed source, an upgrade or
another machine sharing the folder gets its own build; the newest :data:`KEEP_BUILDS`
are kept.

Building needs a C compiler (``pycc`` compiles numba's runtime helpers) and takes about
10 s on top of the just-in-time compile. ``python -m risk.kernel_aot_build`` (the build,
:mod:`risk.kernel_aot_build`) builds it now;
:func:`start_background_build` starts that in a detached process (the replay's commands
do it the first time they run just in time). A failed build is remembered (a
``.failed`` file beside the builds, with the reason) so that later commands do not retry
it; the foreground build retries. ``pycc`` is pending deprecation in numba without a
replacement yet; if it goes, the just-in-time form stays, only slower to start.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import logging
import os
import pathlib
import platform
import subprocess
import sys
import time
import types

import numpy

log = logging.getLogger("risk")

MODULE_NAME = "riskreplay_kernel_aot"
#: The compiled functions that :mod:`risk.kernel` calls.
ENTRY_POINTS = ("evaluate_agents", "reachable", "tiers", "cascade_agents", "corridor_keep")
#: A build lock older than this is taken to be left by a killed build.
STALE_LOCK_S = 15 * 60
HERE = pathlib.Path(__file__).resolve().parent
#: The files whose content the compiled code depends on: every kernel module (its parts,
#: :mod:`risk.kernel_numba` lists them, the layout, the build) and the registry, from
#: which the layout of the kernel's arguments is generated (:mod:`risk.kernel_shared`).
SOURCES = (*sorted(p.name for p in HERE.glob("kernel*.py")), "registry.py")


def _package_stamp(name: str) -> str:
    """Where a package is installed and when its files were written (changes on any
    reinstall), without importing it."""
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        return f"{name}:absent"
    st = os.stat(spec.origin)
    return f"{name}:{spec.origin}:{st.st_size}:{st.st_mtime_ns}"


def _cpu_stamp() -> str:
    """The CPU model and features (the module is compiled for the host CPU)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            wanted = ("model name", "flags", "Features", "CPU part")
            lines = {ln.split(":", 1)[0].strip(): ln for ln in f if ln.startswith(wanted)}
        return "".join(sorted(lines.values()))
    except OSError:
        return f"{platform.processor()}:{platform.machine()}"


#: Environment variables that choose the CPU numba compiles for (``NUMBA_CPU_NAME=generic``
#: for code that runs on any CPU of the architecture): part of the key, so that a module
#: built for the host is not loaded by a process asked for generic code, or the other way.
CPU_VARIABLES = ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES")


def target_cpu() -> str:
    """The CPU the module is compiled for: ``NUMBA_CPU_NAME`` when set, else the host."""
    return os.environ.get("NUMBA_CPU_NAME", "").strip() or "host"


def build_key() -> str:
    """The key of the build that fits this source, installation, Python and CPU (the
    host's, and the one :data:`CPU_VARIABLES` ask for)."""
    h = hashlib.sha256()
    for name in SOURCES:
        h.update((HERE / name).read_bytes())
    for part in (
        _package_stamp("numba"),
        _package_stamp("llvmlite"),
        numpy.__version__,
        sys.implementation.cache_tag,
        platform.machine(),
        _cpu_stamp(),
        *(f"{name}={os.environ.get(name, '')}" for name in CPU_VARIABLES),
    ):
        h.update(part.encode())
    return h.hexdigest()[:24]


def builds_dir(cache_dir: str | os.PathLike[str]) -> pathlib.Path:
    return pathlib.Path(cache_dir) / "aot"


def module_path(cache_dir: str | os.PathLike[str], key: str | None = None) -> pathlib.Path:
    """Where the module of ``key`` (default: this installation's) lives."""
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return builds_dir(cache_dir) / (key or build_key()) / f"{MODULE_NAME}{suffix}"


def load(cache_dir: str | os.PathLike[str]) -> types.ModuleType | None:
    """The built module for this installation, or None when there is none (or it does not
    load: then the just-in-time form is used, with a warning)."""
    path = module_path(cache_dir)
    try:
        if not path.is_file():
            return None
    except OSError:  # (an unreadable cache folder: numba's own caching will say so)
        return None
    if MODULE_NAME in sys.modules:
        return sys.modules[MODULE_NAME]
    try:
        loader = importlib.machinery.ExtensionFileLoader(MODULE_NAME, str(path))
        spec = importlib.util.spec_from_file_location(MODULE_NAME, path, loader=loader)
        assert spec is not None
        module = importlib.util.module_from_spec(spec)
        loader.exec_module(module)
        for name in ENTRY_POINTS[:3]:
            getattr(module, name)
    except (ImportError, OSError, AttributeError) as exc:
        log.warning("riskreplay: the ahead-of-time kernel %s does not load (%s)", path, exc)
        return None
    sys.modules[MODULE_NAME] = module
    return module


def _failed_marker(cache_dir: str | os.PathLike[str], key: str) -> pathlib.Path:
    return builds_dir(cache_dir) / f"{key}.failed"


def _lock_path(cache_dir: str | os.PathLike[str], key: str) -> pathlib.Path:
    return builds_dir(cache_dir) / f"{key}.lock"


def start_background_build(cache_dir: str | os.PathLike[str]) -> bool:
    """Start ``python -m risk.kernel_aot_build --background`` in a detached process unless the
    module exists, is being built, or failed to build for this installation. True when
    started. Its output goes to ``<cache>/aot/build.log``."""
    key = build_key()
    lock = _lock_path(cache_dir, key)
    try:
        if module_path(cache_dir, key).is_file() or _failed_marker(cache_dir, key).exists():
            return False
        if lock.exists() and time.time() - lock.stat().st_mtime <= STALE_LOCK_S:
            return False
        builds_dir(cache_dir).mkdir(parents=True, exist_ok=True)
        with open(builds_dir(cache_dir) / "build.log", "ab") as out:
            subprocess.Popen(
                [sys.executable, "-m", "risk.kernel_aot_build", "--background"],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=out,
                start_new_session=True,  # outlives the command, spared its Ctrl-C
                env={**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)},
                cwd=HERE.parent,
            )
    except OSError as exc:
        log.warning("riskreplay: cannot start the ahead-of-time kernel build (%s)", exc)
        return False
    return True


if __name__ == "__main__":
    # ``python -m risk.kernel_aot`` (the README's command) runs the build, which lives in
    # risk/kernel_aot_build.py: it imports risk.kernel, which imports this module.
    import runpy

    runpy.run_module("risk.kernel_aot_build", run_name="__main__", alter_sys=True)
