"""The corridor stage (risk.kernel_corridor): a slow numpy oracle, hand-made frames, and
the issue's highway frame through the default filter."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk import kernel
from risk.cascade import (
    CascadeConfig,
    CorridorSettings,
    corridor_mask,
    corridor_vector,
    run_cascade,
)
from risk.filtering import filter_frame
from risk.frame import Frame
from risk.kernel_corridor import BEHIND, CROSS_STEP_S, CROSSING, LEADER


# ---------------------------------------------------------------------- the oracle
def _line(points: np.ndarray, x0: float, y0: float, heading: float) -> np.ndarray:
    if points.shape[0] < 2:
        return np.array([[x0, y0], [x0 + math.cos(heading), y0 + math.sin(heading)]])
    return points


def _project(line: np.ndarray, q: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Arc, signed lateral offset and unit direction of the nearest point (ends open)."""
    best = (math.inf, 0.0, math.inf, np.array([1.0, 0.0]))
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))])
    n = line.shape[0]
    for k in range(n - 1):
        d = line[k + 1] - line[k]
        seg = float(np.hypot(*d))
        if seg == 0:
            continue
        t = float(np.dot(q - line[k], d)) / seg**2
        if k > 0:
            t = max(t, 0.0)
        if k < n - 2:
            t = min(t, 1.0)
        dist = float(np.hypot(*(q - (line[k] + t * d))))
        if dist < best[0]:
            side = float(d[0] * (q[1] - line[k][1]) - d[1] * (q[0] - line[k][0]))
            best = (dist, cum[k] + t * seg, dist if side >= 0 else -dist, d / seg)
    return best[1], best[2], best[3]


def _point_at(line: np.ndarray, arc: float) -> np.ndarray:
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))])
    k = min(max(int(np.searchsorted(cum, arc, side="left")) - 1, 0), line.shape[0] - 2)
    span = cum[k + 1] - cum[k]
    f = (arc - cum[k]) / span if span > 0 else 0.0
    return line[k] + f * (line[k + 1] - line[k])


def corridor_oracle(frame: Frame, c: CorridorSettings) -> np.ndarray:
    """The corridor stage, one agent at a time, straight from its definition."""
    out = np.zeros(frame.n_agents, np.int8)
    e = frame.ego

    def path(i: int) -> np.ndarray:
        rows = np.flatnonzero(frame.path_agent == i)
        pts = frame.paths[rows[0], : frame.path_points[rows[0]]] if rows.size else np.zeros((0, 2))
        return _line(pts, *frame.xy[i], frame.heading[i])

    ego_line = path(e)
    s_ego = _project(ego_line, frame.xy[e])[0]
    v = max(float(frame.speed[e]), 0.0)
    leaders = []
    for i in np.flatnonzero(frame.others):
        half = (frame.width[e] + frame.width[i]) / 2 + c.lateral_margin_m
        reach = (frame.length[e] + frame.length[i]) / 2
        s, lat, u = _project(ego_line, frame.xy[i])
        if abs(lat) <= half:
            along = frame.speed[i] * (
                math.cos(frame.heading[i]) * u[0] + math.sin(frame.heading[i]) * u[1]
            )
            if s > s_ego:
                if s - s_ego - reach <= c.interaction_range_m(v, v - along):
                    leaders.append((s, i))
            elif s_ego - s - reach > max(along - v, 0.0) * c.horizon_s + c.margin_m:
                out[i] = BEHIND
            continue
        if not c.crossing or frame.speed[i] <= 0:
            continue
        line = path(i)
        for k in range(1, int(c.horizon_s / CROSS_STEP_S + 1e-9) + 1):
            t = k * CROSS_STEP_S
            s, lat, _ = _project(ego_line, _point_at(line, frame.speed[i] * t))
            if abs(lat) > half:
                continue
            ahead = s - s_ego
            if ahead > 0 and ahead - reach <= c.interaction_range_m(v, v):
                passed = (ahead + reach) / v if v > 0 else math.inf
                if t <= passed + c.crossing_slack_s:
                    out[i] = CROSSING
            break
    for _, i in sorted(leaders)[: c.leaders]:
        out[i] = LEADER
    return out


def _kernel_codes(frame: Frame, c: CorridorSettings) -> np.ndarray:
    fa = kernel.frame_arrays(frame)
    return kernel.corridor_keep(
        *fa[:5], fa[6], fa[7], fa[8], fa[9], int(frame.ego), corridor_vector(c)
    )


# ---------------------------------------------------------------------- frames
def highway(extra: list[tuple[float, float, float, float]]) -> Frame:
    """The ego at x = 0 driving +x at 30 m/s in the lane y = 0; ``extra``: (x, y, heading,
    speed) of the others, each on a straight path along its heading (12 s of it)."""
    agents = [(0.0, 0.0, 0.0, 30.0), *extra]
    xy = np.array([[x, y] for x, y, _, _ in agents])
    heading = np.array([h for _, _, h, _ in agents])
    speed = np.array([v for *_, v in agents])
    paths = [
        np.array([[x, y], [x + max(v * 12, 50) * math.cos(h), y + max(v * 12, 50) * math.sin(h)]])
        for x, y, h, v in agents
    ]
    length = np.full(len(agents), 4.5)
    width = np.full(len(agents), 1.8)
    return Frame.from_arrays(xy, heading, speed, length, width, paths, ego=0)


def test_leaders_by_hand():
    c = CorridorSettings(leaders=1, crossing=False)
    # a car 60 m ahead in the lane, one 90 m ahead, one in the next lane, one behind
    frame = highway([(60, 0, 0, 25), (90, 0.3, 0, 25), (60, 3.5, 0, 25), (-20, 0, 0, 30)])
    codes = _kernel_codes(frame, c)
    assert codes.tolist() == [0, LEADER, 0, 0, 0]  # (the follower 20 m behind: too close)
    c2 = CorridorSettings(leaders=2, crossing=False)
    assert _kernel_codes(frame, c2).tolist() == [0, LEADER, LEADER, 0, 0]


def test_range_grows_with_speed_and_closing():
    c = CorridorSettings()
    assert c.interaction_range_m(30, 12) > 150  # the IDM follower closing on a truck
    closing = CorridorSettings(brake_mps2=4.0)  # where IDM's dynamic gap is the larger
    assert closing.interaction_range_m(30, 20) > closing.interaction_range_m(30, 0)
    assert c.interaction_range_m(30, 0) > c.interaction_range_m(10, 0)
    # the truck 150 m ahead, 12 m/s slower, is in range; the same truck at 700 m is not
    assert _kernel_codes(highway([(150, 0, 0, 18)]), c)[1] == LEADER
    assert _kernel_codes(highway([(700, 0, 0, 40)]), c)[1] == 0


def test_crossing_by_hand():
    c = CorridorSettings(leaders=0)
    # crossing 60 m ahead, coming from 20 m to the side at 10 m/s: there in 2 s, the ego
    # at 30 m/s passes in 2.1 s -> kept; a slow one there in 20 s -> not kept
    fast = (60, -20, math.pi / 2, 10)
    slow = (60, -20, math.pi / 2, 1)
    codes = _kernel_codes(highway([fast, slow]), c)
    assert codes.tolist() == [0, CROSSING, 0]
    assert _kernel_codes(highway([fast]), CorridorSettings(crossing=False))[1] == 0


def _random_frame(rng: np.random.Generator, n: int) -> Frame:
    xy = rng.uniform(-150, 250, (n, 2)) * np.array([1.0, 0.15])
    heading = rng.uniform(-math.pi, math.pi, n)
    heading[rng.random(n) < 0.6] = 0.0
    speed = rng.uniform(0, 35, n)
    speed[rng.random(n) < 0.15] = 0.0
    paths = []
    for i in range(n):
        k = int(rng.integers(1, 6))
        steps = rng.normal(0, 0.2, k).cumsum() + heading[i]
        seg = rng.uniform(5, 40, k)
        pts = np.vstack(
            [xy[i], xy[i] + np.cumsum(np.c_[np.cos(steps), np.sin(steps)] * seg[:, None], axis=0)]
        )
        paths.append(pts if rng.random() > 0.1 else pts[:1])
    return Frame.from_arrays(
        xy, heading, speed, rng.uniform(3, 12, n), rng.uniform(1.6, 2.6, n), paths, ego=0
    )


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 25), leaders=st.integers(0, 3))
def test_kernel_matches_the_oracle(seed, n, leaders):
    frame = _random_frame(np.random.default_rng(seed), n)
    c = CorridorSettings(leaders=leaders)
    assert _kernel_codes(frame, c).tolist() == corridor_oracle(frame, c).tolist()


# ---------------------------------------------------------------------- in the cascade
def test_protected_agents_skip_the_stages_in_both_cascades():
    config = CascadeConfig.named("survival")
    with_corridor = CascadeConfig(
        stages=config.stages, tiers=config.tiers, corridor=CorridorSettings()
    )
    frame = highway([(150, 0, 0, 18), (-80, 0, 0, 30), (700, 0, 0, 40)])
    fused = run_cascade(frame, with_corridor)
    assert fused.protected is not None and fused.protected.tolist() == [False, True, False, False]
    assert fused.kept[:, 1].all() and fused.dropped_at[1] == -1
    assert np.isfinite(fused.survival[1]) and fused.tier[1] >= -1

    def staged_evaluate(frame, models, params=None):
        from risk.registry import evaluate

        return evaluate(frame, models=models, params=params)

    staged = run_cascade(frame, with_corridor, evaluate=staged_evaluate)
    assert staged.kept.tolist() == fused.kept.tolist()
    assert staged.protected is not None and staged.protected.tolist() == fused.protected.tolist()
    mask, elapsed = corridor_mask(frame, with_corridor.corridor)
    assert mask is not None and elapsed >= 0 and not mask.flags.writeable
    # the follower 80 m behind is dropped by the corridor stage ahead of stage 0, in both
    assert fused.behind is not None and fused.behind.tolist() == [False, False, True, False]
    assert staged.behind is not None and staged.behind.tolist() == fused.behind.tolist()
    assert fused.dropped_at[2] == staged.dropped_at[2] == 0 and not fused.kept[:, 2].any()
    assert fused.baseline.tolist() == staged.baseline.tolist()
    assert fused.false_negatives.tolist() == staged.false_negatives.tolist()
    answer = filter_frame(frame, with_corridor)
    assert answer.dropped[2] == "corridor" and 1 in answer.kept_ids.tolist()


def test_the_issue_highway_frame_with_the_default_filter():
    """Issue 37: the default filter keeps a truck 150 m ahead in the ego's lane, 12 m/s
    slower, and drops a car 80 m behind and one 700 m ahead pulling away."""
    truck, behind, far = 1, 2, 3
    frame = highway([(150, 0, 0, 18), (-80, 0, 0, 30), (700, 0, 0, 40)])
    frame_truck_length = frame.length.copy()
    assert frame_truck_length.shape == (4,)
    answer = filter_frame(frame)
    kept = set(answer.kept_ids.tolist())
    assert truck in kept
    assert behind not in kept and far not in kept


def test_corridor_toml_round_trip(tmp_path):
    config = CascadeConfig(
        stages=CascadeConfig.named("survival").stages,
        tiers=CascadeConfig.named("survival").tiers,
        corridor=CorridorSettings(leaders=1, margin_m=5.0),
        guarantee={"miss_rate": 0.05, "confidence": 0.9, "units": 60, "unit": "scene"},
    )
    path = tmp_path / "c.toml"
    path.write_text(config.to_toml_string())
    back = CascadeConfig.from_toml(path)
    assert back.corridor == config.corridor and back.guarantee == config.guarantee
    bad = tmp_path / "bad.toml"
    bad.write_text(config.to_toml_string().replace("leaders = 1", "leaders = -1"))
    with pytest.raises(Exception, match=r"corridor\.leaders"):
        CascadeConfig.from_toml(bad)


def test_a_follower_that_cannot_close_the_gap_is_dropped():
    c = CorridorSettings()
    # 80 m behind at the ego's speed: dropped; 80 m behind 15 m/s faster: it closes 120 m
    # within the 8 s horizon, so the other stages judge it; 20 m behind: too close
    codes = _kernel_codes(highway([(-80, 0, 0, 30), (-80, 0.2, 0, 45), (-20, 0, 0, 30)]), c)
    assert codes.tolist() == [0, BEHIND, 0, 0]


@functools.cache
def _gaps_and_offsets():
    """A compiled caller of the corridor's inner functions (which Python cannot call):
    ``(gap, |lat|)`` for each query point."""
    import numba

    from risk.kernel_corridor import _corridor_project, _line_bounds, _line_gap

    @numba.njit
    def run(xs, ys, cum, q):
        bounds = _line_bounds(xs, ys)
        out = np.empty((q.shape[0], 2))
        for j in range(q.shape[0]):
            out[j, 0] = _line_gap(bounds, q[j, 0], q[j, 1])
            out[j, 1] = abs(_corridor_project(xs, ys, cum, q[j, 0], q[j, 1])[1])
        return out

    return run


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 8))
def test_line_gap_is_a_lower_bound_of_the_lateral_offset(seed, n):
    """The corridor's O(1) skip test never exceeds the distance it stands in for (so an
    agent it calls outside is outside), and is 1-Lipschitz like it."""
    rng = np.random.default_rng(seed)
    xs, ys = rng.uniform(-50, 50, n), rng.uniform(-50, 50, n)
    if rng.random() < 0.3:  # a zero-length first or last segment: no ray at that end
        k = 0 if rng.random() < 0.5 else n - 2
        xs[k + 1], ys[k + 1] = xs[k], ys[k]
    cum = np.r_[0.0, np.cumsum(np.hypot(np.diff(xs), np.diff(ys)))]
    q = rng.uniform(-200, 200, (50, 2))
    gaps, lats = _gaps_and_offsets()(xs, ys, cum, q).T
    assert (gaps <= lats + 1e-9).all()
    assert (gaps > 0).any()  # the bound is not trivially zero
    step = np.hypot(*(q[1:] - q[:-1]).T)
    assert (np.abs(np.diff(gaps)) <= step + 1e-9).all()
