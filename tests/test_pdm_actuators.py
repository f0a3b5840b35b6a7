"""PDM's simulation starts from the vehicle's own actuators (issue 35's closed loop).

The closed loop's request carries the tracked ego's acceleration and steering angle
(:func:`replay.analysis.planner_eval.closed_loop._with_actuators`). Before, PDM simulated
every proposal from acceleration 0 and the steering of the path's curvature while the LQR
vehicle carried its own, so it scored motions the vehicle could not drive: in 4 of the 11
runs of the 400-ego study where PDM collided at fault (INTERACTION egos 16 and 68, inD
ego 10103, AV2 ego 105) the ego hit cars that PDM's scorer saw it miss.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from test_pdm import hand_request

from replay.analysis.planner_eval.closed_loop import _with_actuators
from replay.planning import EgoState, Plan, PlanRequest
from replay.planning.lqr import LqrTracker, StateIndex, centre_xy
from replay.planning.pdm import PdmPlanner
from replay.planning.tracking import PerfectTracker, VehicleState


def test_pdm_simulates_its_proposals_from_the_vehicles_steering_angle():
    """The ego on a straight road with its wheels turned 0.2 rad: the tracked vehicle
    (LqrTracker, the closed loop's) first swerves left before it straightens. PDM's
    simulation of the proposal it hands the tracker matches where the vehicle goes when
    the request carries the steering angle; assuming the path's curvature (0), it
    misplaces the ego by 2 m after 1 s."""
    state = VehicleState(xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0, steer_rad=0.2)
    base = hand_request()
    tracker = LqrTracker()

    def mismatch(steer: float | None) -> float:
        ego = EgoState(xy=state.xy, heading_rad=0.0, speed_mps=10.0, steer_rad=steer)
        request = dataclasses.replace(base, ego=ego)
        planner = PdmPlanner()
        plan = planner.plan(request)
        _, _, proposals, _, _ = planner._relevant(request)
        chosen = int(
            np.flatnonzero(
                (proposals.offset_m == plan.extras["offset_m"])
                & (proposals.fraction == plan.extras["target_fraction"])
            )[0]
        )
        sim = proposals.simulated[chosen]
        predicted = centre_xy(
            sim[:, [StateIndex.REAR_X, StateIndex.REAR_Y]],
            sim[:, StateIndex.HEADING],
            proposals.wheelbase_m,
        )
        worst = 0.0
        for k in (2, 5, 10):
            moved = tracker.follow(state, plan, k * 0.1)
            worst = max(worst, float(np.hypot(*(moved.xy - predicted[k]))))
        return worst

    assert mismatch(0.2) < 0.01
    assert mismatch(None) > 1.0


def test_the_closed_loop_request_carries_the_tracked_actuators():
    request = hand_request()
    state = VehicleState(
        xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0, accel_mps2=-2.5, steer_rad=0.1
    )
    lqr = _with_actuators(request, state, LqrTracker())
    assert lqr.ego.accel_mps2 == -2.5 and lqr.ego.steer_rad == 0.1
    # a perfect tracker has no steering state: the planner assumes the path's curvature
    perfect = _with_actuators(request, state, PerfectTracker())
    assert perfect.ego.accel_mps2 == -2.5 and perfect.ego.steer_rad is None
    assert request.ego.steer_rad is None and request.ego.accel_mps2 == 0.0  # untouched


def test_the_closed_loop_hands_pdm_the_vehicles_actuators_every_step(tmp_path):
    """The follower scene (the ego at 10 m/s, a car standing 40 m ahead) under PDM and the
    LQR tracker: after the first step every request carries the tracked vehicle's
    acceleration and steering angle, and the ego brakes (acceleration below 0 reaches the
    planner)."""
    from converters.scene.writer import write_scene
    from replay.analysis.planner_eval import closed_loop
    from replay.analysis.planner_eval.open_loop import ALL_AGENTS, PlanSettings
    from replay.core.egos import load_scene
    from risk.filtering import KeepAll
    from tests.test_closed_loop import EGO, _follower_scene

    seen: list[EgoState] = []

    class Spy(PdmPlanner):
        def plan(self, request: PlanRequest) -> Plan:
            seen.append(request.ego)
            return super().plan(request)

    plan_settings = PlanSettings(planner="pdm", filters=())
    (tmp_path / "hand-made").mkdir()
    path = write_scene(tmp_path / "hand-made" / "follower.mcap", _follower_scene(6.0))
    run = closed_loop._prepare(closed_loop._SceneRuns(load_scene(str(path))), EGO, plan_settings)
    settings = closed_loop.ClosedLoopSettings(plan=plan_settings, tracker="lqr")
    (row,) = closed_loop.drive_all(run, Spy(), [KeepAll(name=ALL_AGENTS)], LqrTracker(), settings)
    assert row["at_fault_collisions"] == 0
    assert all(ego.steer_rad is not None for ego in seen)
    assert seen[0].accel_mps2 == 0.0 and min(ego.accel_mps2 for ego in seen[1:]) < -1.0
