"""The ahead-of-time kernel (risk/kernel_aot.py): built from the same code, it loads
without numba and agrees with the just-in-time kernel built on the same machine bit for
bit (the exact side of the contract in tests/exactness.py); a broken, failed or running
build leaves the just-in-time kernel in charge."""

from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from risk import kernel, kernel_aot, kernel_aot_build

#: A new process: evaluate every model and run the default cascade on random frames
#: (N = 2 to 120, the mixed oracle frames too); save every array to ``argv[1]`` (.npz)
#: and print which kernel ran and whether numba was imported.
RESULTS = """
import sys
import numpy as np
sys.path.insert(0, {tests!r})
sys.path.insert(0, {benchmarks!r})
from bench_models import random_frame
from frames import mixed_frame
from risk import evaluate, kernel
from risk.cascade import CascadeConfig, run_cascade
out = {{}}
for seed in range(12):
    rng = np.random.default_rng(seed)
    frames = [mixed_frame(rng), random_frame((2, 30, 120)[seed % 3], rng)]
    for j, frame in enumerate(frames):
        for name, values in evaluate(frame).items():
            out[f"{{seed}}/{{j}}/{{name}}"] = values
        res = run_cascade(frame, CascadeConfig.default())
        for field in ("kept", "dropped_at", "tier", "survival", "baseline", "false_negatives",
                      "unreachable"):
            out[f"{{seed}}/{{j}}/cascade.{{field}}"] = np.asarray(getattr(res, field))
np.savez(sys.argv[1], **out)
print(kernel.IMPLEMENTATION, "numba" in sys.modules)
"""


def _run(code: str, cache: pathlib.Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        env={**os.environ, "NUMBA_CACHE_DIR": str(cache), **env},
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def built_cache(tmp_path_factory) -> pathlib.Path:
    """A cache folder with this source's just-in-time kernels (copied from the session's
    folder, warmed by conftest) and the ahead-of-time module built by the documented
    command."""
    cache = tmp_path_factory.mktemp("kernel-cache")
    shutil.copytree(
        kernel.CACHE_DIR, cache, dirs_exist_ok=True, ignore=shutil.ignore_patterns("aot")
    )
    build = subprocess.run(
        [sys.executable, "-m", "risk.kernel_aot_build"],
        env={**os.environ, "NUMBA_CACHE_DIR": str(cache)},
        capture_output=True, text=True, timeout=900, cwd=ROOT,
    )  # fmt: skip
    assert build.returncode == 0, build.stderr
    assert build.stdout.startswith("Built in "), build.stdout
    return cache


@pytest.mark.exactness
@pytest.mark.slow  # (the build: about 10 s)
def test_built_module_loads_without_numba_and_agrees_bit_for_bit(built_cache, tmp_path):
    path = kernel_aot.module_path(built_cache)
    assert path.is_file() and path.stat().st_size > 0
    code = RESULTS.format(tests=str(ROOT / "tests"), benchmarks=str(ROOT / "benchmarks"))
    # (auto: also when the tests run with RISKREPLAY_KERNEL=jit, as .ci/run's second pass)
    aot = _run(code, built_cache, str(tmp_path / "aot.npz"), RISKREPLAY_KERNEL="auto")
    jit = _run(code, built_cache, str(tmp_path / "jit.npz"), RISKREPLAY_KERNEL="jit")
    assert aot.returncode == 0, aot.stderr
    assert jit.returncode == 0, jit.stderr
    assert aot.stdout.split() == ["aot", "False"]
    assert jit.stdout.split() == ["jit", "True"]
    with np.load(tmp_path / "aot.npz") as a, np.load(tmp_path / "jit.npz") as b:
        assert sorted(a.files) == sorted(b.files) and len(a.files) > 200
        for name in a.files:
            assert a[name].dtype == b[name].dtype, name
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)  # NaN == NaN


@pytest.mark.slow
def test_building_again_is_a_no_op(built_cache):
    before = kernel_aot.module_path(built_cache).stat().st_mtime_ns
    assert kernel_aot_build.build(built_cache) == kernel_aot.module_path(built_cache)
    assert kernel_aot.module_path(built_cache).stat().st_mtime_ns == before
    assert not kernel_aot.start_background_build(built_cache)


def test_a_module_that_does_not_load_leaves_the_jit_kernel(tmp_path):
    shutil.copytree(
        kernel.CACHE_DIR, tmp_path, dirs_exist_ok=True, ignore=shutil.ignore_patterns("aot")
    )
    broken = kernel_aot.module_path(tmp_path)
    broken.parent.mkdir(parents=True)
    broken.write_bytes(b"not a shared object")
    code = "from risk import kernel; kernel.warm_up(); print(kernel.IMPLEMENTATION)"
    run = _run(code, tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["jit"]
    assert "does not load" in run.stderr


def test_the_key_follows_the_kernel_source(tmp_path, monkeypatch):
    key = kernel_aot.build_key()
    assert kernel_aot.build_key() == key  # (stable)
    for name in kernel_aot.SOURCES:
        shutil.copy(kernel_aot.HERE / name, tmp_path / name)
    monkeypatch.setattr(kernel_aot, "HERE", tmp_path)
    assert kernel_aot.build_key() == key
    # every part of the kernel, and the registry its argument layout is generated from
    parts = {"kernel_numba.py", "kernel_paths.py", "kernel_evaluate.py", "kernel_cascade.py",
             "kernel_shared.py", "registry.py"}  # fmt: skip
    assert parts <= set(kernel_aot.SOURCES)
    for name in sorted(parts):
        source = tmp_path / name
        text = source.read_text()
        source.write_text(text + "\n# an edit\n")
        assert kernel_aot.build_key() != key, name
        source.write_text(text)
    assert kernel_aot.build_key() == key


def test_background_build_starts_once_and_not_after_a_failure(tmp_path, monkeypatch):
    started: list[list[str]] = []

    class FakePopen:
        def __init__(self, args, **kwargs) -> None:
            started.append(args)
            assert kwargs["start_new_session"] and kwargs["env"]["NUMBA_CACHE_DIR"] == str(tmp_path)

    monkeypatch.setattr(kernel_aot.subprocess, "Popen", FakePopen)
    key = kernel_aot.build_key()
    assert kernel_aot.start_background_build(tmp_path)
    assert started == [[sys.executable, "-m", "risk.kernel_aot_build", "--background"]]
    lock = tmp_path / "aot" / f"{key}.lock"
    lock.write_text("123")  # a build running
    assert not kernel_aot.start_background_build(tmp_path)
    old = lock.stat().st_mtime - kernel_aot.STALE_LOCK_S - 60
    os.utime(lock, (old, old))  # left by a killed build
    assert kernel_aot.start_background_build(tmp_path)
    lock.unlink()
    (tmp_path / "aot" / f"{key}.failed").write_text("CompileError: no compiler\n")
    assert not kernel_aot.start_background_build(tmp_path)
    assert len(started) == 2


def _copy_if_still_there(src: str, dst: str) -> None:
    """copytree's copy, skipping a file that another test process replaced meanwhile
    (numba writes its cache files under temporary names and renames them)."""
    with contextlib.suppress(FileNotFoundError):
        shutil.copy2(src, dst)


def test_a_failed_build_is_remembered_and_reported(tmp_path, monkeypatch):
    shutil.copytree(
        kernel.CACHE_DIR, tmp_path, dirs_exist_ok=True, ignore=shutil.ignore_patterns("aot"),
        copy_function=_copy_if_still_there,
    )  # fmt: skip
    # no C compiler: pycc's toolchain finds none
    run = subprocess.run(
        [sys.executable, "-m", "risk.kernel_aot_build"],
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "CC": "/nonexistent/cc"},
        capture_output=True, text=True, timeout=900, cwd=ROOT,
    )  # fmt: skip
    assert run.returncode == 1
    assert run.stderr.startswith("Error: the ahead-of-time kernel cannot be built: ")
    assert "Traceback" not in run.stderr
    key = kernel_aot.build_key()
    assert (tmp_path / "aot" / f"{key}.failed").is_file()
    assert not kernel_aot.module_path(tmp_path).exists()
    assert not list((tmp_path / "aot").glob(".build-*"))  # the work folder is gone
    assert not (tmp_path / "aot" / f"{key}.lock").exists()


def test_an_unknown_kernel_setting_is_a_one_line_error(tmp_path, monkeypatch):
    run = subprocess.run(
        [sys.executable, "-m", "replay", "demo", "-o", str(tmp_path / "demo"), "--no-progress"],
        env={**os.environ, "RISKREPLAY_KERNEL": "fast"},
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert run.returncode == 1
    last = run.stderr.strip().splitlines()[-1]
    assert last.startswith("Error: RISKREPLAY_KERNEL='fast' is not one of auto, jit"), run.stderr
    assert "Traceback" not in run.stderr
    assert not (tmp_path / "demo").exists()  # nothing half-written
    monkeypatch.setenv("RISKREPLAY_KERNEL", "fast")
    with pytest.raises(kernel.KernelSettingError):
        kernel.kernel_mode()
