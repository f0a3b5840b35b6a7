"""The closed loop's shortcuts give the rows a plain run gives.

- The filters of one ego stepped together (``drive_all``: runs share a timeline while
  they move alike, and part with a copy) against each filter's run on its own, from its
  own preparation: identical rows, timing columns aside.
- The reactive agents' rails searched with a kept index (``Rails.poses``) against
  :func:`risk.geometry.interpolate_components`: the same values, bit for bit.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from replay.analysis.planner_eval.closed_loop import (
    ClosedLoopSettings,
    _prepare,
    _scene,
    drive,
    drive_all,
    run_ego,
)
from replay.analysis.planner_eval.open_loop import PlanSettings
from replay.core.egos import load_scene
from replay.planning import reactive
from replay.planning.registry import make_planner
from replay.planning.tracking import make_tracker
from risk import geometry
from risk.cascade import CascadeConfig
from risk.filtering import KeepAll, parse_filter
from tests.test_closed_loop import EGO, _follower_scene

TIMING = ("plan_ms_median", "plan_ms_p95", "filter_ms_median")


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> pathlib.Path:
    from converters.scene.writer import write_scene

    folder = tmp_path_factory.mktemp("identity") / "hand-made"
    folder.mkdir()
    return write_scene(folder / "follower.mcap", _follower_scene(duration_s=6.0))


def _without_timing(row: dict) -> dict:
    return {k: v for k, v in row.items() if k not in TIMING}


def _same(a: dict, b: dict) -> bool:
    if a.keys() != b.keys():
        return False
    for k in a:
        x, y = a[k], b[k]
        both_nan = isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)
        if not (x == y or both_nan):
            return False
    return True


@pytest.mark.parametrize(("agents", "tracker"), [("reactive", "lqr"), ("log", "perfect")])
def test_filters_stepped_together_match_their_runs_alone(scene_file, agents, tracker):
    settings = ClosedLoopSettings(plan=PlanSettings(filters=()), agents=agents, tracker=tracker)
    # all agents; a twin that keeps them too (never parts); a radius of 1 m that drops
    # the standing car ahead (parts at once: the ego no longer stops for it)
    filters = [
        KeepAll(name="none"),
        KeepAll(name="twin"),
        parse_filter("radius:1", CascadeConfig.default()),
    ]
    planner = make_planner("idm")
    track = make_tracker(tracker)
    together = drive_all(_prepare(load_scene(scene_file), EGO, settings.plan), planner,
                         filters, track, settings)  # fmt: skip
    alone = [
        drive(_prepare(load_scene(scene_file), EGO, settings.plan), planner, flt, track, settings)
        for flt in filters
    ]
    for a, b in zip(together, alone, strict=True):
        assert _same(_without_timing(a), _without_timing(b)), (a, b)
    # the runs did part: without the standing car the ego drives on
    assert together[2]["progress_m"] > together[0]["progress_m"] + 1.0
    assert _same(
        {**_without_timing(together[0]), "filter": ""},
        {**_without_timing(together[1]), "filter": ""},
    )


def test_run_ego_uses_the_scene_cache_and_gives_the_same_rows(scene_file):
    settings = ClosedLoopSettings(plan=PlanSettings(filters=("radius:1",)), tracker="perfect")
    _scene.cache_clear()
    first = run_ego(scene_file, EGO, settings)
    again = run_ego(scene_file, EGO, settings)  # the scene's shared data from the cache
    assert _scene.cache_info().hits >= 1
    assert [_without_timing(r) for r in first] == [_without_timing(r) for r in again]


def _random_rails(seed: int) -> reactive.Rails:
    rng = np.random.default_rng(seed)
    k, p = 7, 40
    steps = rng.uniform(0.0, 3.0, (k, p, 2))
    steps[rng.random((k, p)) < 0.3] = 0.0  # standing: repeated points, runs of equal arcs
    xy = np.cumsum(steps, axis=1) + rng.uniform(-50, 50, (k, 1, 2))
    heading = rng.uniform(-np.pi, np.pi, (k, p))
    return reactive.Rails.from_positions(xy, heading, extend_m=20.0)


@pytest.mark.parametrize("seed", range(5))
def test_rail_poses_match_the_geometry_interpolation_bit_for_bit(seed):
    rails = _random_rails(seed)
    rng = np.random.default_rng(100 + seed)
    lengths = rails.arc_m[:, -1:]
    queries = rng.uniform(-0.1, 1.1, (rails.n, 30))  # a few beyond either end
    arc = queries * lengths
    arc[:, :8] = rails.arc_m[:, rng.integers(0, rails.arc_m.shape[1], 8)]  # on breakpoints
    arc[:, 8] = np.nextafter(arc[:, 0], -np.inf)  # a hair before one
    for rows in (None, np.array([5, 1, 1, 3]), np.zeros(0, np.int64)):
        which = np.arange(rails.n) if rows is None else rows
        xy, heading = rails.poses(arc[which], rows)
        sub = rails.rows(which)
        x, y, _ = geometry.interpolate_components(
            np.ascontiguousarray(sub.xy[..., 0]), np.ascontiguousarray(sub.xy[..., 1]),
            sub.arc_m, arc[which],
        )  # fmt: skip
        h, _, _ = geometry.interpolate_components(
            sub.heading_rad, sub.heading_rad, sub.arc_m, arc[which]
        )
        np.testing.assert_array_equal(xy[..., 0], x)
        np.testing.assert_array_equal(xy[..., 1], y)
        np.testing.assert_array_equal(heading, h)
