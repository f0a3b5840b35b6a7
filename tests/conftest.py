"""Shared fixtures: tiny hand-built frames and the location of ../shared/data."""

from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
from exactness import numpy_exp_off_by

from risk import kernel

ROOT = pathlib.Path(__file__).resolve().parents[1]
# ../shared/data beside the project; RISKREPLAY_SHARED_DATA names it when the checkout
# lives elsewhere (a git worktree, CI).
SHARED_DATA = pathlib.Path(
    os.environ.get("RISKREPLAY_SHARED_DATA") or ROOT.parent / "shared" / "data"
)


@pytest.fixture
def shared_data() -> pathlib.Path:
    """The real data samples beside the project; skips the test when they are absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(
            f"real data samples not found at {SHARED_DATA} (clone ../shared beside the project)"
        )
    return SHARED_DATA


#: ``RISKREPLAY_TEST_EXP_ULPS=k``: for the whole session, the numpy models' ``exp`` moves
#: its results by up to ``k`` floats at random (tests/exactness.py): the ``exp`` of another
#: CPU's numpy, on any machine. .ci/run's second pass of the exactness tests sets it, so a
#: test that wants the kernel and numpy bit for bit fails there, not only on AVX-512.
EXP_ULPS_ENV = "RISKREPLAY_TEST_EXP_ULPS"


def pytest_configure(config: pytest.Config) -> None:
    """Compile the risk kernels once, in the controller, before pytest-xdist starts its
    workers: they then load the cached kernels instead of each compiling them. Move the
    numpy models' exp when ``RISKREPLAY_TEST_EXP_ULPS`` asks (in every process)."""
    ulps = os.environ.get(EXP_ULPS_ENV, "").strip()
    if ulps:
        numpy_exp_off_by(int(ulps), np.random.default_rng(0)).start()
    if not hasattr(config, "workerinput"):
        kernel.warm_up()
