"""The ego view of a recording with plans (``replay run --planner``): a second 2D view
whose origin is the ego's pose, so that a 5 s plan is readable without zooming."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from test_recordings import make_results, read_rrd

from recordings import SceneRecorder
from recordings import layout as L
from replay.planning.types import Plan


@pytest.mark.parametrize("heading", [0.0, 0.7, math.pi / 2, -2.5, math.pi])
def test_ego_frame_puts_ahead_up_and_left_to_the_left(heading):
    m = L.ego_frame_matrices(np.array([heading]))[0]
    forward = np.array([math.cos(heading), math.sin(heading), 0.0])
    left = np.array([-math.sin(heading), math.cos(heading), 0.0])
    # view coordinates: u to the right, v down (rerun's 2D view)
    np.testing.assert_allclose(m @ [0.0, -1.0, 0.0], forward, atol=1e-12)  # up = ahead
    np.testing.assert_allclose(m @ [-1.0, 0.0, 0.0], left, atol=1e-12)  # left = left
    np.testing.assert_allclose(m @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0])


def test_ego_view_bounds_follow_the_plans_reach():
    (x0, x1), (y0, y1) = L.ego_view_bounds(50.0, aspect=0.75)
    assert (y0, y1) == (-60.0, L.EGO_VIEW_BEHIND_M)  # 10 m beyond the plans, 15 m behind
    assert x1 - x0 == pytest.approx(0.75 * 75.0) and x0 == -x1
    assert L.ego_view_bounds(5.0)[1][0] == -L.EGO_VIEW_AHEAD_M  # never smaller
    assert L.ego_view_bounds(400.0)[1][0] == -L.EGO_VIEW_MAX_AHEAD_M  # nor larger


def _plan(xy: np.ndarray) -> Plan:
    n = len(xy)
    return Plan(
        ok=True,
        times_s=np.arange(n) * 0.1,
        xy=xy,
        heading_rad=np.zeros(n),
        speed_mps=np.ones(n),
        plan_ms=1.0,
    )


def _record(tmp_path, with_plans: bool) -> dict:
    info, results = make_results()
    if with_plans:
        results = [
            dataclasses.replace(
                r,
                extras={
                    "plan_all": _plan(r.frame.xy[r.frame.ego] + np.outer(np.arange(6.0), [5, 0])),
                    "plan_filtered": _plan(r.frame.xy[r.frame.ego] + [[0, 0], [5, 1]]),
                },
            )
            for r in results
        ]
    out = tmp_path / "scene.rrd"
    rec = SceneRecorder(out)
    rec.begin(info)
    for r in results:
        rec.add(r)
    rec.close()
    return {"ents": read_rrd(out), "results": results}


def test_recording_with_plans_logs_the_ego_pose_per_frame(tmp_path):
    got = _record(tmp_path, with_plans=True)
    ent = got["ents"][L.EGO_FRAME]
    assert len(ent.rows) == len(got["results"])
    for (_, row), r in zip(ent.rows, got["results"], strict=True):
        ego = r.frame.ego
        np.testing.assert_allclose(row["translation"][0][:2], r.frame.xy[ego])
        want = L.ego_frame_matrices(np.array([r.frame.heading[ego]]))[0]
        # rerun stores the 3x3 column-major
        np.testing.assert_allclose(np.reshape(row["mat3x3"][0], (3, 3)).T, want, atol=1e-6)
    assert L.PLAN_ALL in got["ents"]


def test_recording_without_plans_has_no_ego_frame(tmp_path):
    assert L.EGO_FRAME not in _record(tmp_path, with_plans=False)["ents"]
