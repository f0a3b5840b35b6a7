"""Hindsight truth (risk.hindsight): hand-computed scenes, properties, a slow oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk import hindsight
from risk.errors import RiskError
from risk.hindsight import (
    LABEL_NEGATIVE,
    LABEL_POSITIVE,
    LABEL_UNKNOWN,
    HindsightSettings,
    Tracks,
    box_corners,
    box_gap,
    boxes_overlap,
    forward_window_min,
    forward_window_sum,
    hindsight_truth,
    tracks_from_states,
)


# ---------------------------------------------------------------------- slow oracle
def _corners(x, y, h, length, width):
    c, s = math.cos(h), math.sin(h)
    out = []
    for sl, sw in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        ex, ey = sl * length / 2, sw * width / 2
        out.append((x + ex * c - ey * s, y + ex * s + ey * c))
    return out


def _point_segment(p, a, b):
    dx, dy = b[0] - a[0], b[1] - a[1]
    dd = dx * dx + dy * dy
    u = 0.0 if dd == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / dd))
    return math.hypot(p[0] - a[0] - u * dx, p[1] - a[1] - u * dy)


def _cross(o, a, b):
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(p1, p2, q1, q2):
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    return d1 * d2 < 0 and d3 * d4 < 0


def _inside(p, poly):
    signs = [_cross(poly[k], poly[(k + 1) % 4], p) for k in range(4)]
    return all(s >= 0 for s in signs) or all(s <= 0 for s in signs)


def oracle_gap(a, b):
    """Plain loops: 0 if an edge pair crosses or a corner lies inside the other box,
    else the least corner-to-edge distance both ways."""
    pa, pb = _corners(*a), _corners(*b)
    for i in range(4):
        for j in range(4):
            if _segments_cross(pa[i], pa[(i + 1) % 4], pb[j], pb[(j + 1) % 4]):
                return 0.0
    if any(_inside(p, pb) for p in pa) or any(_inside(p, pa) for p in pb):
        return 0.0
    best = math.inf
    for p, poly in [(p, pb) for p in pa] + [(p, pa) for p in pb]:
        for k in range(4):
            best = min(best, _point_segment(p, poly[k], poly[(k + 1) % 4]))
    return best


coord = st.floats(-30, 30, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)
size = st.floats(0.2, 8.0, allow_nan=False)
box = st.tuples(coord, coord, angle, size, size)


@settings(max_examples=400, deadline=None)
@given(box, box)
def test_box_gap_matches_the_slow_oracle(a, b):
    got = float(box_gap(*a, *b))
    want = oracle_gap(a, b)
    assert got == pytest.approx(want, abs=1e-7)


@settings(max_examples=200, deadline=None)
@given(box, box)
def test_box_gap_is_symmetric_and_non_negative(a, b):
    ab, ba = float(box_gap(*a, *b)), float(box_gap(*b, *a))
    assert ab >= 0
    assert ab == pytest.approx(ba, abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(box, box, coord, coord, angle)
def test_box_gap_is_invariant_under_rigid_motion(a, b, tx, ty, rot):
    def move(bx):
        x, y, h, length, width = bx
        c, s = math.cos(rot), math.sin(rot)
        return (c * x - s * y + tx, s * x + c * y + ty, h + rot, length, width)

    assert float(box_gap(*move(a), *move(b))) == pytest.approx(float(box_gap(*a, *b)), abs=1e-7)


@settings(max_examples=200, deadline=None)
@given(box, st.floats(-0.49, 0.49), st.floats(-0.49, 0.49), angle)
def test_overlapping_boxes_have_gap_zero(a, fx, fy, h):
    # A box whose centre lies inside the other always overlaps it.
    x, y, ha, length, width = a
    c, s = math.cos(ha), math.sin(ha)
    bx = x + fx * length * c - fy * width * s
    by = y + fx * length * s + fy * width * c
    assert float(box_gap(*a, bx, by, h, 1.0, 1.0)) == 0.0
    assert bool(boxes_overlap(*a, bx, by, h, 1.0, 1.0))


def test_box_gap_hand_computed():
    assert box_gap(0, 0, 0, 4, 2, 10, 0, 0, 4, 2) == pytest.approx(6.0)  # end to end
    assert box_gap(0, 0, 0, 4, 2, 0, 5, math.pi / 2, 4, 2) == pytest.approx(2.0)
    # corner to corner: offsets 3 and 2 beyond the boxes' half sizes
    assert box_gap(0, 0, 0, 2, 2, 5, 4, 0, 2, 2) == pytest.approx(math.hypot(3, 2))
    assert box_gap(0, 0, 0, 4, 2, 4, 0, 0, 4, 2) == 0.0  # touching end to end
    corners = box_corners(0.0, 0.0, 0.0, 4.0, 2.0)
    assert corners.tolist() == [[2, 1], [-2, 1], [-2, -1], [2, -1]]


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.floats(-100, 100, allow_nan=False), min_size=1, max_size=30),
    st.integers(1, 12),
)
def test_window_min_and_sum_match_naive(values, length):
    a = np.array(values)
    want = [min(values[f : f + length]) for f in range(len(values))]
    assert forward_window_min(a, length).tolist() == want
    ints = np.rint(a).astype(np.int64)
    want_sum = [int(ints[f : f + length].sum()) for f in range(len(values))]
    assert forward_window_sum(ints, length).tolist() == want_sum


# ---------------------------------------------------------------------- tiny scenes
DT = 0.25  # exact in binary: every position below is exact


def _tracks(states: dict[int, list[tuple[int, float, float, float]]], n_frames: int) -> Tracks:
    """Agent id -> [(frame, x, y, heading)], every box 4 m x 2 m."""
    rows = [(f, a, x, y, h) for a, s in states.items() for f, x, y, h in s]
    f, a, x, y, h = (np.array(c) for c in zip(*rows, strict=True))
    return tracks_from_states(
        f, a, np.zeros(f.size, dtype=np.int8), np.column_stack([x, y]), h,
        np.full(f.size, 4.0), np.full(f.size, 2.0), t0_s=0.0, dt_s=DT, n_frames=n_frames,
    )  # fmt: skip


def _crossing(n_frames: int = 41) -> Tracks:
    # Ego east along y = 0 at 8 m/s (2 m per frame); agent north along x = 21 at 8 m/s,
    # starting 31 m south of the ego's lane.
    return _tracks(
        {
            1: [(k, 2.0 * k, 0.0, 0.0) for k in range(n_frames)],
            2: [(k, 21.0, 2.0 * k - 31.0, math.pi / 2) for k in range(n_frames)],
        },
        n_frames,
    )


HORIZON = HindsightSettings(horizon_s=5.0, gap_m=0.5, pet_s=1.0)  # 20 frames


def test_crossing_gap_and_pet_by_hand():
    # Boxes overlap in x when |2i - 21| <= 3 (ego frames i = 9..12) and in y when
    # |2j - 31| <= 3 (agent frames j = 14..17): the ego leaves the shared place at frame
    # 12 (t = 3.0 s), the agent arrives at frame 14 (t = 3.5 s): PET = 0.5 s.
    # At equal times the clearance is hypot(max(0, 18 - 2k, 2k - 24), max(0, 28 - 2k,
    # 2k - 34)): least at k = 13, 2 * sqrt(2) m.
    truth = hindsight_truth(_crossing(), 0, settings=HORIZON)
    agent = 1
    assert truth.horizon_steps == 20
    assert truth.pet_s[0, 0, agent] == pytest.approx(0.5)
    assert truth.gap_m[0, 0, agent] == pytest.approx(2 * math.sqrt(2))
    assert truth.label[0, 0, agent] == LABEL_POSITIVE  # PET 0.5 <= 1 s
    # Frame 12 still holds the pair (ego 12, agent 14); from frame 13 on no overlap is
    # left in the future: the ego has passed.
    assert truth.pet_s[12, 0, agent] == pytest.approx(0.5)
    assert np.isnan(truth.pet_s[13, 0, agent])
    assert truth.gap_m[13, 0, agent] == pytest.approx(2 * math.sqrt(2))
    assert truth.gap_m[14, 0, agent] == pytest.approx(4.0)
    assert truth.label[14, 0, agent] == LABEL_NEGATIVE
    # With a stricter PET threshold the crossing is no interaction (gap 2.83 m > 0.5 m).
    strict = hindsight_truth(_crossing(), 0, settings=HindsightSettings(pet_s=0.25))
    assert strict.label[0, 0, agent] == LABEL_NEGATIVE


def test_crossing_is_symmetric_in_ego_and_agent():
    t = hindsight_truth(_crossing(), [0, 1], settings=HORIZON)
    np.testing.assert_allclose(t.gap_m[:, 0, 1], t.gap_m[:, 1, 0], equal_nan=True)
    np.testing.assert_allclose(t.pet_s[:, 0, 1], t.pet_s[:, 1, 0], equal_nan=True)
    np.testing.assert_array_equal(t.label[:, 0, 1], t.label[:, 1, 0])
    assert (t.label[:, 0, 0] == LABEL_UNKNOWN).all()  # the ego itself: not applicable


def test_parallel_agent_never_comes_close():
    n = 41
    tracks = _tracks(
        {
            1: [(k, 2.0 * k, 0.0, 0.0) for k in range(n)],
            2: [(k, 2.0 * k, 5.0, 0.0) for k in range(n)],  # next lane, same speed
        },
        n,
    )
    t = hindsight_truth(tracks, 0, settings=HORIZON)
    assert np.allclose(t.gap_m[:, 0, 1], 3.0)  # 5 m between centres - 2 x 1 m half width
    assert np.isnan(t.pet_s[:, 0, 1]).all()  # the strips y in [-1, 1] and [4, 6] never meet
    # Frames 0..20 have their whole 5 s window recorded: negatives. 21..40: censored.
    assert (t.label[:21, 0, 1] == LABEL_NEGATIVE).all()
    assert (t.label[21:, 0, 1] == LABEL_UNKNOWN).all()
    assert t.censored[21:, 0, 1].all() and not t.censored[:21, 0, 1].any()
    assert t.observed[21, 0, 1] == 20 and t.observed[20, 0, 1] == 21


def test_censored_end_keeps_positives_seen_before_it():
    # The scene ends 2 s after the crossing starts: frame 0's window (0..20) is cut at
    # frame 15, yet the crossing (PET 0.5 s, frames 12 and 14) is inside the recorded part.
    t = hindsight_truth(_crossing(n_frames=16), 0, settings=HORIZON)
    assert t.censored[0, 0, 1]
    assert t.label[0, 0, 1] == LABEL_POSITIVE
    assert t.label[13, 0, 1] == LABEL_UNKNOWN  # no close approach seen, window cut: unknown


def test_agent_track_ending_censors_the_window():
    n = 41
    tracks = _tracks(
        {
            1: [(k, 2.0 * k, 0.0, 0.0) for k in range(n)],
            2: [(k, 2.0 * k, 5.0, 0.0) for k in range(10)],  # leaves the recorded area
        },
        n,
    )
    t = hindsight_truth(tracks, 0, settings=HORIZON)
    assert (t.label[:10, 0, 1] == LABEL_UNKNOWN).all()
    relaxed = hindsight_truth(tracks, 0, settings=HindsightSettings(coverage=10 / 21))
    assert relaxed.label[0, 0, 1] == LABEL_NEGATIVE  # 10 of 21 steps recorded suffice
    assert relaxed.label[1, 0, 1] == LABEL_UNKNOWN


def test_collision_has_zero_gap_and_pet():
    n = 21
    tracks = _tracks(
        {
            1: [(k, 2.0 * k, 0.0, 0.0) for k in range(n)],
            2: [(k, 20.0, 2.0 * k - 20.0, math.pi / 2) for k in range(n)],
        },
        n,
    )
    t = hindsight_truth(tracks, 0, settings=HORIZON)
    assert t.gap_m[0, 0, 1] == 0.0 and t.pet_s[0, 0, 1] == 0.0


@settings(max_examples=30, deadline=None)
@given(coord, coord, angle)
def test_truth_is_invariant_under_rigid_motion(tx, ty, rot):
    base = _crossing()
    c, s = math.cos(rot), math.sin(rot)
    xy = base.xy @ np.array([[c, s], [-s, c]]) + [tx, ty]
    moved = Tracks(base.ids, base.kinds, xy, base.heading + rot, base.length, base.width,
                   base.valid, base.t0_s, base.dt_s)  # fmt: skip
    a = hindsight_truth(base, [0, 1], settings=HORIZON)
    b = hindsight_truth(moved, [0, 1], settings=HORIZON)
    np.testing.assert_allclose(a.gap_m, b.gap_m, atol=1e-7, equal_nan=True)
    np.testing.assert_allclose(a.pet_s, b.pet_s, equal_nan=True)


def test_blocks_of_egos_match_one_ego_at_a_time(monkeypatch):
    rng = np.random.default_rng(3)
    n_t, n = 30, 6
    xy = np.cumsum(rng.normal(0, 1.5, (n_t, n, 2)), axis=0) + rng.uniform(-15, 15, (1, n, 2))
    tracks = Tracks(
        np.arange(n) * 10, np.zeros(n, np.int8), xy, rng.uniform(-3, 3, (n_t, n)),
        np.full((n_t, n), 4.0), np.full((n_t, n), 2.0), rng.random((n_t, n)) > 0.1, 0.0, 0.1,
    )  # fmt: skip
    together = hindsight_truth(tracks, np.arange(n), settings=HindsightSettings(horizon_s=1.0))
    import risk.hindsight as hs

    monkeypatch.setattr(hs, "BLOCK_ELEMENTS", 1)  # one ego per block
    for e in range(n):
        alone = hindsight_truth(tracks, e, settings=HindsightSettings(horizon_s=1.0))
        np.testing.assert_allclose(alone.gap_m[:, 0], together.gap_m[:, e], equal_nan=True)
        np.testing.assert_allclose(alone.pet_s[:, 0], together.pet_s[:, e], equal_nan=True)
        np.testing.assert_array_equal(alone.label[:, 0], together.label[:, e])
    # And the gap against a brute-force loop over frames and windows.
    e, a, f = 0, 3, 5
    want = [
        oracle_gap(
            (*xy[k, e], tracks.heading[k, e], 4.0, 2.0), (*xy[k, a], tracks.heading[k, a], 4.0, 2.0)
        )
        for k in range(f, f + 11)
        if tracks.valid[k, e] and tracks.valid[k, a]
    ]
    if tracks.valid[f, e] and tracks.valid[f, a]:
        assert together.gap_m[f, e, a] == pytest.approx(min(want), abs=1e-7)


def test_bad_settings_are_refused():
    with pytest.raises(RiskError, match="coverage"):
        HindsightSettings(coverage=0.0)
    with pytest.raises(RiskError, match="gap_m"):
        HindsightSettings(gap_m=-1.0)
    with pytest.raises(RiskError, match="out of range"):
        hindsight_truth(_crossing(), 5)


def _slow_pet(tracks: Tracks, e: int, a: int, f: int, h: int) -> float:
    """Plain loops: the least |i - j| dt over window frames whose boxes overlap."""
    best = math.inf
    for i in range(f, min(f + h, tracks.n_frames - 1) + 1):
        for j in range(f, min(f + h, tracks.n_frames - 1) + 1):
            if not (tracks.valid[i, e] and tracks.valid[j, a]):
                continue
            bi = (*tracks.xy[i, e], tracks.heading[i, e], tracks.length[i, e], tracks.width[i, e])
            bj = (*tracks.xy[j, a], tracks.heading[j, a], tracks.length[j, a], tracks.width[j, a])
            if oracle_gap(bi, bj) <= 1e-9:
                best = min(best, abs(i - j) * tracks.dt_s)
    return best


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000))
def test_pet_matches_slow_loops_on_random_tracks(seed):
    rng = np.random.default_rng(seed)
    n_t, n = 14, 4
    xy = np.cumsum(rng.normal(0, 1.2, (n_t, n, 2)), axis=0) + rng.uniform(-6, 6, (1, n, 2))
    tracks = Tracks(
        np.arange(n), np.zeros(n, np.int8), xy, rng.uniform(-3, 3, (n_t, n)),
        rng.uniform(1, 5, (n_t, n)), rng.uniform(0.5, 2, (n_t, n)), rng.random((n_t, n)) > 0.15,
        0.0, 0.5,
    )  # fmt: skip
    t = hindsight_truth(tracks, np.arange(n), settings=HindsightSettings(horizon_s=2.5))
    for e in range(n):
        for a in range(n):
            for f in range(n_t):
                if e == a or not (tracks.valid[f, e] and tracks.valid[f, a]):
                    continue
                want = _slow_pet(tracks, e, a, f, 5)
                got = t.pet_s[f, e, a]
                assert (np.isnan(got) and want == math.inf) or got == pytest.approx(want)


def test_rows_of_the_same_tracks_share_one_truth(monkeypatch):
    """A replay's recording and table label their rows from the same tracks: the truth is
    computed once per egos and settings, and the rows get the same labels as alone."""
    tracks = _crossing()
    t_s = np.arange(tracks.n_frames) * DT
    ego, agent = np.full(t_s.size, 1), np.full(t_s.size, 2)
    alone = hindsight.truth_for_rows(_crossing(), t_s, ego, agent, settings=HORIZON)
    calls = []
    real = hindsight.hindsight_truth
    monkeypatch.setattr(
        hindsight, "hindsight_truth", lambda *a, **k: calls.append(k) or real(*a, **k)
    )
    first = hindsight.truth_for_rows(tracks, t_s, ego, agent, settings=HORIZON)
    again = hindsight.truth_for_rows(tracks, t_s[::2], ego[::2], agent[::2], settings=HORIZON)
    wider = HindsightSettings(horizon_s=5.0, gap_m=20.0, pet_s=1.0)
    other = hindsight.truth_for_rows(tracks, t_s, ego, agent, settings=wider)
    assert len(calls) == 2
    for a, b in zip(alone, first, strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a[::2], b)
    assert not np.array_equal(first[2], other[2])  # (a wider gap: more positives)


def test_tracks_refuse_repeated_agent_ids():
    shape = (2, 3)
    with pytest.raises(RiskError, match="ids must be unique"):
        Tracks(
            ids=np.array([3, 1, 3]), kinds=np.zeros(3, np.int8), xy=np.zeros((*shape, 2)),
            heading=np.zeros(shape), length=np.ones(shape), width=np.ones(shape),
            valid=np.ones(shape, bool), t0_s=0.0, dt_s=0.1,
        )  # fmt: skip


def test_truth_for_rows_in_blocks_of_egos_equals_one_block(monkeypatch):
    """Issue 31: rows of many egos are labelled in blocks of egos (bounded memory); the
    labels, gaps and PETs are those of one call over all egos."""
    from risk import hindsight as H

    rng = np.random.default_rng(5)
    t, n = 30, 9
    xy = np.cumsum(rng.normal(0, 0.8, (t, n, 2)), axis=0) + rng.uniform(0, 12, (1, n, 2))
    valid = rng.random((t, n)) > 0.1
    tracks = H.Tracks(
        ids=np.arange(n) * 10, kinds=np.zeros(n, np.int8), xy=xy,
        heading=rng.uniform(-3, 3, (t, n)), length=np.full((t, n), 4.0),
        width=np.full((t, n), 1.8), valid=valid, t0_s=0.0, dt_s=0.1,
    )  # fmt: skip
    rows = 400
    t_s = rng.integers(0, t, rows) * 0.1
    ego = rng.integers(0, n, rows) * 10
    agent = rng.integers(0, n, rows) * 10
    settings = H.HindsightSettings(horizon_s=1.0, gap_m=1.0, pet_s=1.0)
    whole = H.truth_for_rows(tracks, t_s, ego, agent, settings=settings)
    monkeypatch.setattr(H, "TRUTH_BLOCK_ELEMENTS", 2 * t * n)  # two egos per block
    blocks = H.truth_for_rows(tracks, t_s, ego, agent, settings=settings)
    for w, b in zip(whole, blocks, strict=True):
        np.testing.assert_array_equal(w, b)
    assert (whole[2] == H.LABEL_POSITIVE).any() and (whole[2] == H.LABEL_NEGATIVE).any()
