"""Compiling the just-in-time kernels from cold: on two or more cores the cascade's
kernels compile in a second process while this one compiles ``evaluate_agents``
(risk.kernel._compile_cascade_beside); on a warm cache nothing is started."""

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
    assert kernel._compile_cascade_beside(kernel_numba) is None


def test_the_ahead_of_time_module_is_never_compiled_beside():
    fake = type(sys)("riskreplay_kernel_aot")
    assert kernel._compile_cascade_beside(fake) is None


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="compiles beside only on 2+ cores")
@pytest.mark.skipif(not kernel.HAVE_CYCLE_COUNTER, reason="no one-pass cascade on this CPU")
def test_a_cold_cache_starts_the_cascade_compile_beside(tmp_path):
    """In a new process on an empty cache folder the cache reads as cold and the helper
    process starts (it is stopped at once: the whole compile takes about 30 s)."""
    code = textwrap.dedent(
        """
        from risk import kernel, kernel_numba
        assert kernel._cache_is_cold(kernel_numba.cascade_agents)
        assert kernel._cache_is_cold(kernel_numba.evaluate_agents)
        beside = kernel._compile_cascade_beside(kernel_numba)
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
