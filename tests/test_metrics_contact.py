"""The at-fault rules of replay/analysis/planner_eval/metrics.py where they met coarse
histories and tracks that begin inside the ego (issue 35's 21 PDM runs):

- nuPlan judges every 0.1 s; a history sampled at 2 Hz (SinD) first sees a side contact
  0.3 s later, deep in, where the ego's front edge already touches the other box: the
  contact is classified at its first 0.1 s sub-step, with both boxes interpolated;
- a track whose first overlap is at its own first step (it begins inside the ego's box)
  is counted, never at fault, as one that overlaps at the run's first step.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from replay.analysis.planner_eval import metrics

#: A car cutting in from the right: 14 m/s forward and 4 m/s sideways, 1.5 m behind the
#: ego's centre and 3 m to its right at t = 0; the ego drives at 10 m/s along +x. Its
#: side touches the ego's right side at t = 0.155 s (first seen every 0.1 s at 0.2 s,
#: where its front lies behind the ego's front edge: lateral); at 0.5 s it reaches
#: across the ego's front edge.
CUT_IN_HEADING = math.atan2(4.0, 14.0)


def _histories(times: np.ndarray) -> tuple[metrics.EgoHistory, metrics.OthersHistory]:
    n = times.size
    ego = metrics.EgoHistory(
        times_s=times, xy=np.stack([10.0 * times, np.zeros(n)], 1), heading_rad=np.zeros(n),
        speed_mps=np.full(n, 10.0), length_m=4.5, width_m=1.8,
    )  # fmt: skip
    xy = np.stack([-1.5 + 14.0 * times, -3.0 + 4.0 * times], 1)[:, None, :]
    others = metrics.OthersHistory(
        ids=np.array([5]), kinds=np.array([0], np.int8), xy=xy,
        heading_rad=np.full((n, 1), CUT_IN_HEADING), speed_mps=np.full((n, 1), math.hypot(14, 4)),
        length_m=np.full((n, 1), 4.5), width_m=np.full((n, 1), 1.8), valid=np.ones((n, 1), bool),
    )  # fmt: skip
    return ego, others


def test_a_side_contact_seen_late_by_a_coarse_history_is_still_lateral():
    fine_ego, fine = _histories(np.round(np.arange(0.0, 0.51, 0.1), 9))
    coarse_ego, coarse = _histories(np.array([0.0, 0.5]))
    at_fine = metrics.classify_collisions(fine_ego, fine, np.ones(6, bool))
    at_coarse = metrics.classify_collisions(coarse_ego, coarse, np.ones(2, bool))
    assert at_fine.first_step.tolist() == [2]  # t = 0.2 s
    lateral = int(metrics.CollisionType.ACTIVE_LATERAL)
    assert at_fine.kind.tolist() == [lateral] and at_coarse.kind.tolist() == [lateral]
    assert at_fine.at_fault.tolist() == [False] == at_coarse.at_fault.tolist()  # in lane
    # at 0.5 s itself (where the old rule classified it) the ego's front edge touches it
    late_ego, late = _histories(np.array([0.5]))
    at_late = metrics.classify_collisions(late_ego, late, np.ones(1, bool))
    assert at_late.kind.tolist() == [int(metrics.CollisionType.ACTIVE_FRONT)]
    # out of its lane, the same side contact is the ego's fault (nuPlan's lane change)
    out = metrics.classify_collisions(coarse_ego, coarse, np.zeros(2, bool))
    assert out.kind.tolist() == [lateral] and out.at_fault.tolist() == [True]


def test_sub_steps_do_not_change_a_history_at_nuplans_rate():
    """At 0.1 s steps the contact is classified at its first overlapping step, as before."""
    ego, others = _histories(np.round(np.arange(0.0, 0.51, 0.1), 9))
    contact = metrics._first_contact(ego, others, np.array([2]), np.array([0]))
    np.testing.assert_allclose(contact["ego_xy"], ego.xy[[2]])
    np.testing.assert_allclose(contact["xy"], others.xy[2, [0]])
    assert contact["step"].tolist() == [2]


@pytest.mark.parametrize("present_before", [True, False])
def test_a_track_that_begins_inside_the_ego_is_never_at_fault(present_before):
    """The ego at 5 m/s, a slower car (3 m/s) 4 m ahead: a front collision at step 1,
    at fault when the car was there (apart) the step before, not when it begins there."""
    ego = metrics.EgoHistory(
        times_s=np.array([0.0, 0.1]), xy=np.array([[0.0, 0.0], [0.5, 0.0]]),
        heading_rad=np.zeros(2), speed_mps=np.full(2, 5.0), length_m=4.5, width_m=1.8,
    )  # fmt: skip
    track = metrics.OthersHistory(
        ids=np.array([9]), kinds=np.array([0], np.int8),
        xy=np.array([[[40.0, 0.0]], [[4.5, 0.0]]]), heading_rad=np.zeros((2, 1)),
        speed_mps=np.full((2, 1), 3.0), length_m=np.full((2, 1), 4.5),
        width_m=np.full((2, 1), 1.8), valid=np.array([[present_before], [True]]),
    )  # fmt: skip
    out = metrics.classify_collisions(ego, track, np.ones(2, bool))
    assert out.first_step.tolist() == [1] and out.n == 1
    assert out.kind.tolist() == [int(metrics.CollisionType.ACTIVE_FRONT)]
    assert out.at_fault.tolist() == [present_before]
