"""``lqr.simulate`` (the per-step work of ``lqr_commands`` and ``bicycle_step`` fused into
one loop over time) against the loop that calls the two functions step by step, kept here
as the oracle: the same states bit for bit, on random batches (curves, braking to rest,
steering and acceleration at their limits, standing references) and on PDM's proposals
on the hand-made two-lane road.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_pdm import road_request

from replay.planning import lqr
from replay.planning.pdm import PdmPlanner


def stepwise(initial, reference, n_steps, wheelbase, settings):
    """The former ``lqr.simulate``: lqr_commands then bicycle_step at every step."""
    problem = lqr.TrackingProblem.of(reference, wheelbase, settings)
    out = np.empty((n_steps + 1, initial.shape[0], lqr.N_STATE))
    out[0] = initial
    for k in range(n_steps):
        accel, steer_rate = lqr.lqr_commands(out[k], problem, k)
        out[k + 1] = lqr.bicycle_step(
            out[k], accel, steer_rate, settings.dt_s, problem.wheelbase, settings
        )
    return np.ascontiguousarray(np.moveaxis(out, 0, 1))


def random_case(seed: int, batch: int, steps: int):
    """A batch of references: arcs of random curvature, speeds that rise, fall to 0 or
    stand, and initial states off them (lateral, heading, speed, steering)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps + 12) * 0.1
    v0 = rng.uniform(0.0, 30.0, batch)
    decel = rng.choice([-2.0, 0.0, 3.0, 9.0], batch)
    speed = np.maximum(v0[:, None] - decel[:, None] * t[None, :], 0.0)
    speed[rng.random(batch) < 0.15] = 0.0  # standing references
    kappa = rng.uniform(-0.08, 0.08, batch)
    arc = np.concatenate([np.zeros((batch, 1)), np.cumsum(speed[:, :-1] * 0.1, axis=1)], axis=1)
    heading = kappa[:, None] * arc + rng.uniform(-np.pi, np.pi, batch)[:, None]
    step_xy = np.stack([np.cos(heading), np.sin(heading)], axis=-1) * (speed * 0.1)[..., None]
    xy = np.concatenate([np.zeros((batch, 1, 2)), np.cumsum(step_xy[:, :-1], axis=1)], axis=1)
    wheelbase = rng.uniform(1.0, 8.0, batch)
    reference = lqr.reference_from_centres(xy, heading, speed, wheelbase)
    initial = np.zeros((batch, lqr.N_STATE))
    initial[:, :2] = reference.rear_xy[:, 0] + rng.normal(0.0, 1.0, (batch, 2))
    initial[:, lqr.StateIndex.HEADING] = heading[:, 0] + rng.normal(0.0, 0.3, batch)
    initial[:, lqr.StateIndex.SPEED] = np.maximum(v0 + rng.normal(0.0, 2.0, batch), 0.0)
    initial[:, lqr.StateIndex.ACCEL] = rng.uniform(-8.0, 4.0, batch)
    initial[:, lqr.StateIndex.STEER] = rng.uniform(-1.0, 1.0, batch)
    return initial, reference, wheelbase


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("batch", [1, 17, 40])
def test_fused_simulation_is_the_stepwise_one_bit_for_bit(seed, batch):
    initial, reference, wheelbase = random_case(seed, batch, 50)
    settings = lqr.TrackerSettings()
    fused = lqr.simulate(initial, reference, 50, wheelbase, settings)
    np.testing.assert_array_equal(fused, stepwise(initial, reference, 50, wheelbase, settings))
    # beyond the reference's end (its last row is held) and with a steering weight
    weighted = lqr.TrackerSettings(q_steer=2.0)
    long = lqr.simulate(initial, reference, 80, wheelbase, weighted)
    np.testing.assert_array_equal(long, stepwise(initial, reference, 80, wheelbase, weighted))


def test_the_case_reaches_the_limits_and_stops():
    """The random cases exercise the branches: a state at rest, clipped commands."""
    initial, reference, wheelbase = random_case(3, 40, 50)
    sim = lqr.simulate(initial, reference, 50, wheelbase, lqr.TrackerSettings())
    assert (sim[..., lqr.StateIndex.SPEED] == 0.0).any()
    assert (sim[..., lqr.StateIndex.ACCEL] == -8.0).any()
    assert (np.abs(sim[..., lqr.StateIndex.STEER]) == np.pi / 3).any()


def test_pdm_proposals_on_the_road_are_simulated_as_before():
    # pdm's numpy form (its compiled twin: tests/test_pdm_kernel.py)
    planner = PdmPlanner(compiled=False)
    req = road_request()
    _, _, proposals, _, _ = planner._relevant(req)
    ego = req.ego
    n_p = proposals.states.shape[0]
    wheelbase = np.full(n_p, float(lqr.wheelbase_m(ego.length_m)))
    simulated, _ = planner._simulate(req, proposals.states, req.dt_s)
    xy = proposals.states[..., :2]
    reference = lqr.reference_from_centres(
        xy, proposals.states[..., 2], proposals.states[..., 3], wheelbase
    )
    oracle = stepwise(
        simulated[:, 0], reference, simulated.shape[1] - 1, wheelbase, planner.tracker
    )
    np.testing.assert_array_equal(simulated, oracle)
