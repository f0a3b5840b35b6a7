"""Shared by the job-engine tests of ``replay plan`` and ``replay calibrate``: three small
road scenes in two datasets and a broken one, one local Ray instance per module, and the
comparison of outputs with their wall-clock figures left out."""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import pathlib
from typing import Any

import pytest
from planner_scenes import OTHERS, write_road_scene

HAS_RAY = importlib.util.find_spec("ray") is not None
NO_RAY = "ray is not installed (pip install 'riskreplay[ray]')"


def road_corpus(root: pathlib.Path, *, broken: bool = True) -> list[pathlib.Path]:
    """Three road scenes (tests/planner_scenes.py) in two datasets, and with ``broken``
    a file that is no MCAP scene (it fails on whichever worker reads it)."""
    (root / "setA").mkdir(parents=True)
    (root / "setB").mkdir()
    scenes = [
        write_road_scene(root / "setA" / "S_SiteA-1_1.mcap", OTHERS),
        write_road_scene(root / "setA" / "S_SiteA-1_2.mcap", OTHERS[:3]),
        write_road_scene(root / "setB" / "S_SiteB-2_1.mcap", OTHERS),
    ]
    if broken:
        (root / "setB" / "broken.mcap").write_bytes(b"not an mcap file")
        scenes.append(root / "setB" / "broken.mcap")
    return scenes


@pytest.fixture(scope="module")
def ray_instance():
    """One local Ray instance (two CPUs) for the module's commands: ``--engine ray``
    uses an instance already running in the process as it is (starting one per command
    costs seconds)."""
    if not HAS_RAY:
        pytest.skip(NO_RAY)
    import ray

    os.environ.setdefault("RAY_worker_niceness", "0")
    ray.init(num_cpus=2, include_dashboard=False, logging_level=logging.WARNING,
             log_to_driver=False)  # fmt: skip
    yield ray
    ray.shutdown()


def timing_key(key: str) -> bool:
    """Keys and columns that hold wall-clock figures (plan_ms, filter_ms_median,
    time_s, median_time_ratio, ...)."""
    words = key.split("_")
    return "ms" in words or "time" in words or key == "time_s"


def untimed(value: Any) -> Any:
    """``value`` (parsed JSON) without its wall-clock figures."""
    if isinstance(value, dict):
        return {k: untimed(v) for k, v in value.items() if not timing_key(k)}
    if isinstance(value, list):
        return [untimed(v) for v in value]
    return value


def summary(out: pathlib.Path) -> Any:
    return untimed(json.loads((out / "summary.json").read_text()))
