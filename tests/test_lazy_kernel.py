"""The compiled kernel loads on first use (risk/lazy.py): importing the models, the
engine or the output writers does not import numba (about 0.5 s per process)."""

from __future__ import annotations

import subprocess
import sys

from test_kernel import TWO_AGENTS

import risk
from risk import MODELS, kernel


def test_kernel_slots_follow_the_registry():
    assert tuple(MODELS) == kernel.SLOTS


def test_from_risk_import_kernel_is_the_one_kernel_module():
    assert risk.kernel is kernel is sys.modules["risk.kernel"]


def test_importing_does_not_load_numba_and_the_first_call_does():
    code = (
        "import sys; import risk, risk.cascade, replay.engine, replay.pool, "
        "recordings.writer, replay.table_file, replay.commands.run; "
        "print('numba' in sys.modules); "
        "import numpy as np; from risk import Frame, evaluate; "
        + TWO_AGENTS
        + "r = evaluate(f)['survival'][1]; print('numba' in sys.modules, r > 0)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "True", "True"]
