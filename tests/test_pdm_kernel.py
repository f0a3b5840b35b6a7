"""``pdm``'s compiled loops (replay/planning/pdm_kernel.py) against their numpy forms, the
oracles: ``PdmPlanner(compiled=False)``, :func:`replay.planning.lqr.simulate` and the numpy
``_Centreline.project``. Kernel by kernel on random inputs, then whole plans (the same
chosen proposal, emergency brake and leader, trajectories and scores within 1e-9) on
hand-made requests, hypothesis-generated ones (agents around a curved reference) and real
MONA frames from ../shared/data.

numpy's SIMD ``sin``/``cos``/``pow`` and BLAS may round the last bit another way than the
compiled loops, so floats are compared within 1e-9 (they agree to about 1e-13), decisions
exactly.
"""

from __future__ import annotations

import dataclasses
import math
import sys

import numpy as np
import planner_scenes as ps
import pytest
from conftest import ROOT, SHARED_DATA
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_lqr_fused import random_case
from test_pdm import hand_request, road_request

from replay.planning import AgentForecasts, EgoState, PlanRequest, lqr, pdm_kernel
from replay.planning.pdm import (
    PdmPlanner,
    PdmSettings,
    _candidates,
    _Centreline,
    _centres,
    _idm_rollout,
    contacts,
)
from risk import Kind

#: .ci/run runs these again under numpy's baseline dispatch and a generic numba CPU.
pytestmark = pytest.mark.exactness

ATOL = 1e-9
FAST, SLOW = PdmPlanner(), PdmPlanner(compiled=False)


# ---------------------------------------------------------------------- kernel by kernel
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("batch", [1, 17])
def test_compiled_simulation_matches_numpy(seed, batch):
    """Random references (curves, braking to rest, limits; tests/test_lqr_fused.py), past
    the reference's end and with a steering weight."""
    initial, reference, wheelbase = random_case(seed, batch, 50)
    for n_steps, tracker in ((50, lqr.TrackerSettings()), (80, lqr.TrackerSettings(q_steer=2.0))):
        fast = pdm_kernel.simulate(initial, reference, n_steps, wheelbase, tracker)
        slow = lqr.simulate(initial, reference, n_steps, wheelbase, tracker)
        assert fast.shape == slow.shape
        np.testing.assert_allclose(fast, slow, rtol=0.0, atol=ATOL)


def test_compiled_simulation_reaches_the_branches():
    """The case above exercises rest, clipped acceleration and clipped steering."""
    initial, reference, wheelbase = random_case(3, 40, 50)
    sim = pdm_kernel.simulate(initial, reference, 50, wheelbase, lqr.TrackerSettings())
    assert (sim[..., lqr.StateIndex.SPEED] == 0.0).any()
    assert (sim[..., lqr.StateIndex.ACCEL] == -8.0).any()
    assert (np.abs(sim[..., lqr.StateIndex.STEER]) == np.pi / 3).any()


def _curve(kappa: float, length_m: float = 200.0, step_m: float = 2.0) -> np.ndarray:
    s = np.arange(0.0, length_m + step_m / 2, step_m)
    if abs(kappa) < 1e-9:
        return np.stack([s, np.zeros_like(s)], axis=1)
    return np.stack([np.sin(kappa * s) / kappa, (1.0 - np.cos(kappa * s)) / kappa], axis=1)


@pytest.mark.parametrize("kappa", [0.0, 0.02, -0.05])
def test_compiled_projection_matches_numpy(kappa):
    """Points near and far, beyond both ends, on vertices and on the line itself."""
    rng = np.random.default_rng(7)
    reference = _curve(kappa)
    fast = _Centreline.of(reference, compiled=True)
    slow = _Centreline.of(reference, compiled=False)
    points = np.concatenate(
        [
            rng.uniform(-300.0, 500.0, (400, 2)),
            reference + rng.normal(0.0, 2.0, reference.shape),
            reference[::7],
            0.5 * (reference[1:] + reference[:-1]),
        ]
    ).reshape(2, -1, 2)
    for a, b in zip(fast.project(points), slow.project(points), strict=True):
        assert a.shape == b.shape == points.shape[:-1]
        np.testing.assert_array_equal(a, b)


def _random_leaders(rng: np.random.Generator, n_s: int, n_p: int, n_l: int):
    corridor = rng.random((n_s, n_p, n_l)) < 0.4
    corridor[rng.random(n_s) < 0.3] = False  # search steps without any leader
    arc = rng.uniform(-10.0, 80.0, (n_s, n_l)) + np.arange(n_s)[:, None] * 0.5
    back = arc - rng.uniform(1.0, 5.0, (n_s, n_l))
    back[:, : n_l // 2] = back[:, :1]  # ties: the first row wins
    speed = rng.choice([0.0, 3.0, 12.0], (n_s, n_l))
    return corridor, arc, back, speed


@pytest.mark.parametrize("seed", range(6))
def test_compiled_idm_matches_numpy(seed):
    """Leaders held between searches, searches without leaders, ties, stops within a step
    (hard braking from speed behind a close leader)."""
    rng = np.random.default_rng(seed)
    n_t, n_p, n_l = 51, 17, int(rng.integers(1, 9))
    every = int(rng.integers(1, 4))
    n_s = len(range(0, n_t - 1, every))
    target = rng.uniform(0.1, 25.0, n_p)
    v0 = float(rng.uniform(0.0, 20.0))
    p = PdmSettings(leader_update_steps=every)
    for leaders in (None, _random_leaders(rng, n_s, n_p, n_l)):
        fast = pdm_kernel.idm_rollout(n_t, 5.0, v0, target, leaders, p, 0.1)
        slow = _idm_rollout(n_t, 5.0, v0, target, leaders, p, 0.1)
        for a, b in zip(fast, slow, strict=True):
            assert a.shape == b.shape and a.dtype == b.dtype
            # (a leader within the least gap asks for millions of m/s^2: relative)
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=ATOL)
        np.testing.assert_array_equal(fast[4], slow[4])  # the held leader's rows


def _crowd(seed: int):
    """Proposals and agents crowded into 16 m: many candidate pairs, many contacts, and
    boxes that touch exactly (axis-aligned, bumper to bumper)."""
    rng = np.random.default_rng(seed)
    n_p, n_t, n_k = 5, 12, 7
    times = np.arange(n_t) * 0.1
    xy = rng.uniform(-8, 8, (n_k, n_t, 2))
    heading = rng.uniform(-np.pi, np.pi, (n_k, n_t))
    xy[0], heading[0] = [4.5, 0.0], 0.0  # touches an ego standing at the origin
    agents = AgentForecasts(
        ids=np.arange(n_k), kinds=np.zeros(n_k), length_m=np.r_[4.5, rng.uniform(0.3, 12, n_k - 1)],
        width_m=np.r_[1.8, rng.uniform(0.3, 3, n_k - 1)], times_s=times, xy=xy, heading_rad=heading,
    )  # fmt: skip
    req = PlanRequest(
        ego=EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=5.0),
        reference=np.array([[0.0, 0.0], [50.0, 0.0]]),
        target_speed_mps=5.0,
        agents=agents,
        horizon_s=1.1,
    )
    sim = np.zeros((n_p, n_t, lqr.N_STATE))
    sim[..., lqr.StateIndex.REAR_X] = rng.uniform(-6, 6, (n_p, n_t))
    sim[..., lqr.StateIndex.REAR_Y] = rng.uniform(-6, 6, (n_p, n_t))
    sim[..., lqr.StateIndex.HEADING] = rng.uniform(-np.pi, np.pi, (n_p, n_t))
    sim[..., lqr.StateIndex.SPEED] = rng.uniform(0, 15, (n_p, n_t))
    sim[0, :, : lqr.StateIndex.SPEED + 1] = 0.0  # standing at the origin, heading 0
    wheelbase = float(lqr.wheelbase_m(req.ego.length_m))
    sim[0, :, lqr.StateIndex.REAR_X] = -wheelbase / 2.0
    return req, sim, _centres(sim, wheelbase), rng


@pytest.mark.parametrize("seed", range(6))
def test_compiled_candidates_and_contacts_match_numpy(seed):
    req, sim, sim_xy, rng = _crowd(seed)
    look = np.array([0, 3, 6, 9])
    last = rng.integers(0, sim.shape[1], req.agents.n)
    ignore = rng.random(req.agents.n) < 0.2
    fast = _candidates(req, req.agents, sim, sim_xy, look, last, compiled=True)
    slow = _candidates(req, req.agents, sim, sim_xy, look, last)
    np.testing.assert_array_equal(fast, slow)
    assert slow.any() and not slow.all()
    for ignored in (None, ignore):
        a = contacts(req, req.agents, sim, sim_xy, look, ignored, last_step=last, compiled=True)
        b = contacts(req, req.agents, sim, sim_xy, look, ignored, last_step=last)
        for name in ("proposal", "step", "lookahead", "agent", "agent_step"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=ATOL)
        np.testing.assert_allclose(a.y, b.y, rtol=0, atol=ATOL)
    # bumper to bumper (0 m apart) is a contact at every step
    touching = contacts(req, req.agents, sim, sim_xy, look[:1], compiled=True)
    assert ((touching.proposal == 0) & (touching.agent == 0)).sum() == sim.shape[1]


# ---------------------------------------------------------------------- whole plans
def assert_same_plans(request: PlanRequest) -> None:
    """The compiled planner plans what the numpy one does: the same decisions, the same
    agents read, trajectories, proposals and scores within ATOL."""
    fast, slow = FAST.plan(request), SLOW.plan(request)
    assert fast.ok == slow.ok and fast.reason == slow.reason
    np.testing.assert_array_equal(FAST.may_matter(request), SLOW.may_matter(request))
    if not fast.ok:
        return
    for key in ("offset_m", "target_fraction", "emergency_brake", "brake_proposal", "proposals"):
        assert fast.extras[key] == slow.extras[key], key
    assert fast.extras["score"] == pytest.approx(slow.extras["score"], abs=ATOL)
    assert (fast.blocking_id, fast.lane, fast.stops) == (slow.blocking_id, slow.lane, slow.stops)
    for name in ("xy", "heading_rad", "speed_mps"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name), rtol=0, atol=ATOL)
    # the stages: proposals, their simulation, the leaders and every score
    line_f, scored_f, prop_f, _, cand_f = FAST._relevant(request)
    line_s, scored_s, prop_s, _, cand_s = SLOW._relevant(request)
    np.testing.assert_array_equal(scored_f.owner, scored_s.owner)
    np.testing.assert_array_equal(prop_f.leader, prop_s.leader)
    np.testing.assert_allclose(prop_f.states, prop_s.states, rtol=0, atol=ATOL)
    np.testing.assert_allclose(prop_f.simulated, prop_s.simulated, rtol=0, atol=ATOL)
    if cand_f is not None:
        np.testing.assert_array_equal(cand_f, cand_s)
    sim = prop_s.simulated  # both scorers on the same simulation
    xy = _centres(sim, prop_s.wheelbase_m)
    score_f = FAST._score(request, line_f, scored_s, sim, xy, cand_s)
    score_s = SLOW._score(request, line_s, scored_s, sim, xy, cand_s)
    for name in ("multi", "weighted", "progress_m", "total", "collision_step"):
        np.testing.assert_allclose(
            getattr(score_f, name), getattr(score_s, name), rtol=0, atol=ATOL, err_msg=name
        )
    np.testing.assert_array_equal(score_f.collision_row, score_s.collision_row)


def _brake_request() -> PlanRequest:
    """4 m/s, 1.5 m behind a standing car: the emergency brake (at 2 m, tests/test_pdm.py,
    the 8 m/s^2 braking proposal stops short of it instead)."""
    ego = EgoState(xy=np.array([40.0 - 4.5 - 1.5, 0.0]), heading_rad=0.0, speed_mps=4.0)
    base = road_request(agents=[ps.STOPPED], target_speed_mps=4.0)
    return dataclasses.replace(base, ego=ego, reference=np.array([[ego.xy[0], 0.0], [200, 0]]))


#: A standing car ahead (road), close behind it at low speed (an emergency brake), no
#: agents, one car close ahead, one head-on, and a mix (a pedestrian crossing,
#: neighbours, a fast follower, a static object in the lane).
HAND_MADE = {
    "road": road_request(),
    "brake": _brake_request(),
    "empty": hand_request(),
    "close": hand_request([(12.0, 0.0, 0.0, 0.0, Kind.VEHICLE)]),
    "head-on": hand_request([(25.0, 0.0, math.pi, 8.0, Kind.VEHICLE)], lanes_left=1),
    "mixed": hand_request(
        [
            (30.0, -12.0, math.pi / 2, 5.0, Kind.PEDESTRIAN),
            (20.0, 3.5, 0.0, 4.0, Kind.VEHICLE),
            (-15.0, 0.0, 0.0, 14.0, Kind.VEHICLE),
            (40.0, 0.5, 0.0, 0.0, Kind.OTHER),
        ],
        lanes_left=1,
    ),
}


@pytest.mark.parametrize("name", HAND_MADE)
def test_compiled_plans_match_numpy_on_hand_made_requests(name):
    assert_same_plans(HAND_MADE[name])


def test_the_hand_made_requests_brake_and_follow():
    """The cases above reach the emergency brake and a reported leader."""
    plans = {name: FAST.plan(request) for name, request in HAND_MADE.items()}
    assert plans["brake"].extras["emergency_brake"] == 1.0
    assert plans["road"].blocking_id == 1


@st.composite
def curved_requests(draw) -> PlanRequest:
    """A circular-arc reference (either side, or straight), the ego near its start, and up
    to 8 agents around it: along the path at an offset (leaders, followers, oncoming) or
    on straight lines across it, at rest or moving."""
    kappa = draw(st.sampled_from([0.0, 0.01, -0.01, 0.03, -0.04]))
    reference = _curve(kappa, 160.0)
    line = _Centreline.of(reference, compiled=False)
    times = np.arange(51) * 0.1
    d0 = draw(st.floats(-1.5, 1.5))
    (xy0,), (h0,) = line.pose(np.array([0.0]), np.array([d0]))
    ego = EgoState(
        xy=xy0,
        heading_rad=float(h0) + draw(st.floats(-0.2, 0.2)),
        speed_mps=draw(st.floats(0.0, 20.0)),
        accel_mps2=draw(st.floats(-3.0, 2.0)),
    )
    n = draw(st.integers(0, 8))
    xy = np.zeros((n, times.size, 2))
    heading = np.zeros((n, times.size))
    kinds, lengths, widths = [], [], []
    for k in range(n):
        s = draw(st.floats(-30.0, 110.0))
        lateral = draw(st.sampled_from([0.0, 0.5, -0.8, 3.5, -3.5])) + draw(st.floats(-0.3, 0.3))
        speed = draw(st.sampled_from([0.0, 2.0, 8.0, 15.0]))
        if draw(st.booleans()):  # along the path, either way
            sign = draw(st.sampled_from([1.0, -1.0]))
            p, h = line.pose(s + sign * speed * times, np.full(times.size, lateral))
            xy[k], heading[k] = p, h + (0.0 if sign > 0 else math.pi)
        else:  # a straight line at any heading
            (start,), _ = line.pose(np.array([s]), np.array([lateral]))
            angle = draw(st.floats(-math.pi, math.pi))
            xy[k] = start + speed * times[:, None] * np.array([math.cos(angle), math.sin(angle)])
            heading[k] = angle
        kinds.append(draw(st.sampled_from([Kind.VEHICLE, Kind.PEDESTRIAN, Kind.OTHER])))
        lengths.append(draw(st.floats(0.5, 12.0)))
        widths.append(draw(st.floats(0.5, 2.6)))
    agents = AgentForecasts(
        ids=np.arange(n) + 1,
        kinds=kinds,
        length_m=lengths,
        width_m=widths,
        times_s=times,
        xy=xy,
        heading_rad=heading,
    )
    return PlanRequest(
        ego=ego,
        reference=reference,
        target_speed_mps=draw(st.floats(0.0, 25.0)),
        agents=agents,
        lanes_left=draw(st.integers(0, 1)),
        lanes_right=draw(st.integers(0, 1)),
    )


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(request_=curved_requests())
def test_compiled_plans_match_numpy_on_random_requests(request_):
    assert_same_plans(request_)


@pytest.fixture(scope="module")
def mona_requests(tmp_path_factory) -> list[PlanRequest]:
    """12 requests of two real MONA scenes (35-40 agents a frame), built as
    benchmarks/bench_pdm.py builds them (its own function)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data samples not found at {SHARED_DATA} (clone ../shared beside it)")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_pdm

    found = bench_pdm.requests(tmp_path_factory.mktemp("mona"), 12)
    if not found:
        pytest.skip(f"the MONA scenes of benchmarks/bench_pdm.py are not in {bench_pdm.RECORDED}")
    return [request for _, request in found]


def test_compiled_plans_match_numpy_on_real_frames(mona_requests):
    assert mona_requests
    for request in mona_requests:
        assert_same_plans(request)


def test_warm_up_compiles_every_kernel_with_the_types_of_real_requests():
    """What the warm-up compiles (or loads) is what later plans use: no second compile in
    a worker. The numpy planner has nothing to warm up."""
    kernels = ("_idm_loop", "_tracking_loop", "_project", "_candidate_pairs", "_box_contacts")
    PdmPlanner().warm_up()
    warmed = {name: list(getattr(pdm_kernel, name).signatures) for name in kernels}
    assert all(len(signatures) >= 1 for signatures in warmed.values())
    for request in HAND_MADE.values():
        FAST.plan(request)
    assert {name: list(getattr(pdm_kernel, name).signatures) for name in kernels} == warmed
    PdmPlanner(compiled=False).warm_up()
