"""Compiling the just-in-time kernels from cold: on two or more cores half of the inner
functions (and, in the whole warm-up, the cascade) compile in a second process while this
one compiles the other half (risk.kernel._start_beside); on a warm cache nothing is
started."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from risk import kernel

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_a_warm_cache_starts_no_second_process():
    from risk import kernel_numba

    kernel.warm_up(kernel_numba)  # (the conftest has compiled them; this loads them)
    assert not kernel._cache_is_cold(kernel_numba.cascade_agents)
    for cascade in (True, False):
        assert kernel._start_beside(kernel_numba, cascade=cascade) is None


def test_the_ahead_of_time_module_is_never_compiled_beside():
    fake = type(sys)("riskreplay_kernel_aot")
    for cascade in (True, False):
        assert kernel._start_beside(fake, cascade=cascade) is None


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="compiles beside only on 2+ cores")
@pytest.mark.skipif(not kernel.HAVE_CYCLE_COUNTER, reason="no one-pass cascade on this CPU")
def test_a_cold_cache_starts_the_compile_beside(tmp_path):
    """In a new process on an empty cache folder the cache reads as cold and the helper
    process starts (it is stopped at once: the whole compile takes about 30 s)."""
    code = textwrap.dedent(
        """
        from risk import kernel, kernel_numba
        assert kernel._cache_is_cold(kernel_numba.cascade_agents)
        assert kernel._cache_is_cold(kernel_numba.evaluate_agents)
        for cascade in (True, False):
            beside = kernel._start_beside(kernel_numba, cascade=cascade)
            assert beside is not None
            beside.kill()
            assert beside.wait() != 0
        print("ok")
        """
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "RISKREPLAY_KERNEL": "jit"}
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok"


def test_the_cache_folder_probe(tmp_path):
    from risk.kernel_shared import cache_problem

    assert cache_problem(str(tmp_path / "new" / "cache")) is None
    assert list((tmp_path / "new" / "cache").iterdir()) == []  # the probe is removed
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    assert cache_problem(str(blocker / "cache")) == "Not a directory"


def test_an_unwritable_cache_is_named_in_the_notice_and_compiles_nothing_beside(
    monkeypatch, caplog
):
    """numba caches nothing there, silently: the notice says every run will compile, and
    no second process compiles what could not be loaded from the cache."""
    from risk import kernel_jit, kernel_numba

    # (kernel_jit holds the notice; kernel_numba, which gathers the kernel, names the same)
    monkeypatch.setattr(kernel_jit, "CACHE_PROBLEM", "Permission denied")
    monkeypatch.setattr(kernel_numba, "CACHE_PROBLEM", "Permission denied")
    monkeypatch.setattr(kernel_numba._CompileNotice, "said", set())
    monkeypatch.setattr(kernel, "_cache_is_cold", lambda dispatcher: True)
    with caplog.at_level("WARNING", logger="risk"):
        kernel_numba._CompileNotice().on_start(None)
        kernel_numba._CompileNotice().on_start(None)  # once per process
    assert len(caplog.records) == 1
    message = caplog.records[0].getMessage()
    assert "in every run" in message and "Permission denied" in message
    assert kernel_numba.CACHE_DIR in message and "NUMBA_CACHE_DIR" in message
    for cascade in (True, False):
        assert kernel._start_beside(kernel_numba, cascade=cascade) is None


def test_the_jit_cache_has_a_folder_per_argument_layout():
    """numba's cache checks a function's own source file only, not the layout constants it
    reads from risk.kernel_shared (generated from the registry): a folder per layout keeps
    a registry with another model, or another order, from loading stale code."""
    from risk import kernel_jit, kernel_numba, kernel_shared

    assert kernel_jit.JIT_CACHE_DIR.startswith(kernel.CACHE_DIR)
    assert kernel_jit.JIT_CACHE_DIR.endswith(f"jit-{kernel_shared.LAYOUT_KEY}")
    assert kernel_numba.evaluate_agents._cache._cache_path.startswith(kernel_jit.JIT_CACHE_DIR)
    slots, floats, ints = kernel_shared.SLOTS, kernel_shared.FLOAT_AT, kernel_shared.INT_AT
    assert kernel_shared.layout_key(slots, floats, ints) == kernel_shared.LAYOUT_KEY
    assert kernel_shared.layout_key(slots[::-1], floats, ints) != kernel_shared.LAYOUT_KEY
    (a, i), (b, j) = list(floats.items())[:2]
    swapped = {**floats, a: j, b: i}
    assert kernel_shared.layout_key(slots, swapped, ints) != kernel_shared.LAYOUT_KEY
    one_more = {**floats, ("new_model", "epsilon"): len(floats)}
    assert (
        kernel_shared.layout_key((*slots, "new_model"), one_more, ints) != kernel_shared.LAYOUT_KEY
    )
