"""The compiled kernel loads on first use (risk/lazy.py): importing the models, the
engine or the output writers loads neither numba (about 0.5 s per process) nor the
ahead-of-time module."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from test_kernel import TWO_AGENTS

import risk
from risk import MODELS, kernel


def test_kernel_slots_follow_the_registry():
    assert tuple(MODELS) == kernel.SLOTS


def test_from_risk_import_kernel_is_the_one_kernel_module():
    assert risk.kernel is kernel is sys.modules["risk.kernel"]


@pytest.mark.parametrize("mode", ["jit", "auto"])
def test_importing_does_not_load_the_kernel_and_the_first_call_does(mode):
    """Importing loads neither numba nor the ahead-of-time module; the first model call
    loads the kernel: numba with RISKREPLAY_KERNEL=jit, either form by default."""
    loaded = "[m for m in ('numba', 'riskreplay_kernel_aot') if m in sys.modules]"
    code = (
        "import sys; import risk, risk.cascade, replay.core.engine, replay.core.pool, "
        "recordings.writer, replay.core.table_file, replay.cli.commands.run; "
        f"print({loaded} == []); "
        "import numpy as np; from risk import Frame, evaluate, kernel; "
        + TWO_AGENTS
        + f"r = evaluate(f)['survival'][1]; print(kernel.IMPLEMENTATION, {loaded}, r > 0)"
    )
    run = subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, "RISKREPLAY_KERNEL": mode},
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    first, second = run.stdout.splitlines()
    assert first == "True"
    implementation, rest = second.split(" ", 1)
    expected = {"jit": "['numba'] True", "aot": "['riskreplay_kernel_aot'] True"}
    assert rest == expected[implementation]
    if mode == "jit":
        assert implementation == "jit"
