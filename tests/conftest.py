"""Shared fixtures: tiny hand-built frames and the location of ../shared/data."""

from __future__ import annotations

import pathlib

import pytest

from risk import kernel

ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def shared_data() -> pathlib.Path:
    """The real data samples beside the project; skips the test when they are absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(
            f"real data samples not found at {SHARED_DATA} (clone ../shared beside the project)"
        )
    return SHARED_DATA


def pytest_configure(config: pytest.Config) -> None:
    """Compile the risk kernels once, in the controller, before pytest-xdist starts its
    workers: they then load the cached kernels instead of each compiling them."""
    if not hasattr(config, "workerinput"):
        kernel.warm_up()
