"""Path geometry: arc lengths, extension, lookup, cutting, projection, exact distances."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk import geometry as g


def pad(rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Polylines -> padded (M, P, 2) (last point repeated) and point counts."""
    p = max(len(r) for r in rows)
    out = np.empty((len(rows), p, 2))
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
        out[i, len(r) :] = r[-1]
    return out, np.array([len(r) for r in rows])


# ---------------------------------------------------------------------- arc lengths
def test_cumulative_lengths_and_padding():
    paths, _ = pad([np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 10.0]]), np.array([[1.0, 1.0]])])
    cum = g.cumulative_lengths(paths)
    np.testing.assert_allclose(cum[0], [0.0, 5.0, 11.0])
    np.testing.assert_allclose(cum[1], [0.0, 0.0, 0.0])


def test_segment_directions_fill_degenerate_and_fallback():
    paths, _ = pad(
        [
            np.array([[0.0, 0.0], [0.0, 0.0], [2.0, 0.0], [2.0, 0.0], [2.0, 3.0]]),
            np.array([[5.0, 5.0]]),
        ]
    )
    d = g.segment_directions(paths, np.array([0.3, math.pi / 2]))
    # leading repeat: no segment before it -> fallback heading 0.3 rad
    np.testing.assert_allclose(d[0, 0], [math.cos(0.3), math.sin(0.3)])
    np.testing.assert_allclose(d[0, 1], [1.0, 0.0])
    np.testing.assert_allclose(d[0, 2], [1.0, 0.0])  # repeat takes the previous direction
    np.testing.assert_allclose(d[0, 3], [0.0, 1.0])
    np.testing.assert_allclose(d[1], [[0.0, 1.0]] * 4, atol=1e-15)  # single point: heading


# ---------------------------------------------------------------------- extension
def test_extend_short_path_along_last_segment():
    paths, n = pad([np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 4.0]])])
    ext, n_ext = g.extend_paths(paths, n, np.array([0.0]), np.array([15.0]))
    assert n_ext[0] == 4
    # 5 m given, 10 m more along (0.6, 0.8) from the last real point.
    np.testing.assert_allclose(ext[0, 3], [3.0 + 6.0, 4.0 + 8.0])
    assert g.cumulative_lengths(ext)[0, -1] == pytest.approx(15.0)


def test_extend_single_point_along_heading_and_long_path_unchanged():
    paths, n = pad([np.array([[1.0, 2.0]]), np.array([[0.0, 0.0], [100.0, 0.0]])])
    ext, n_ext = g.extend_paths(paths, n, np.array([math.pi / 2, 0.0]), np.array([7.0, 50.0]))
    np.testing.assert_allclose(ext[0, n_ext[0] - 1], [1.0, 9.0], atol=1e-12)
    # long enough: the extra point repeats the end (zero-length segment)
    np.testing.assert_allclose(ext[1, :3], [[0.0, 0.0], [100.0, 0.0], [100.0, 0.0]])


# ---------------------------------------------------------------------- lookup
def test_interpolate_points_segments_and_clipping():
    paths, _ = pad([np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])])
    cum = g.cumulative_lengths(paths)
    pts, seg = g.interpolate(paths, cum, np.array([[0.0, 4.0, 10.0, 15.0, 20.0, 99.0, -3.0]]))
    np.testing.assert_allclose(
        pts[0], [[0, 0], [4, 0], [10, 0], [10, 5], [10, 10], [10, 10], [0, 0]], atol=1e-12
    )
    # at a vertex the segment starting there is used; at the end the last segment
    assert list(seg[0]) == [0, 0, 1, 1, 1, 1, 0]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.lists(st.floats(0, 5), min_size=1, max_size=12), min_size=1, max_size=6),
    st.integers(0, 2**31 - 1),
)
def test_locate_matches_per_row_searchsorted(steps, seed):
    """The all-rows search with offsets equals an exact per-row search, ties included."""
    rng = np.random.default_rng(seed)
    p = max(len(s) for s in steps) + 1
    cum = np.zeros((len(steps), p))
    for i, s in enumerate(steps):
        c = np.r_[0.0, np.cumsum(np.round(s, 1))]  # rounding creates exact ties
        cum[i, : len(c)] = c
        cum[i, len(c) :] = c[-1]
    # queries: breakpoints themselves (ties) and random values
    q = np.concatenate([cum, rng.uniform(0, 1, cum.shape) * cum[:, -1:]], axis=1)
    got = g.locate(cum, q)
    want = np.stack([np.searchsorted(cum[i], q[i], side="right") - 1 for i in range(len(cum))])
    np.testing.assert_array_equal(got, want)


def test_cut_paths():
    paths, _ = pad([np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])] * 3)
    cum = g.cumulative_lengths(paths)
    cut, n = g.cut_paths(paths, cum, np.array([15.0, 0.0, 50.0]))
    np.testing.assert_allclose(cut[0], [[0, 0], [10, 0], [10, 5]])
    np.testing.assert_allclose(cut[1], [[0, 0]] * 3)  # standing agent: a single point
    np.testing.assert_allclose(cut[2], paths[2])  # beyond the end: whole path
    assert g.cumulative_lengths(cut)[0, -1] == pytest.approx(15.0)
    assert list(n) == [3, 2, 3]


def test_project_points():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    cum = g.cumulative_lengths(path[None])[0]
    d, arc = g.project_points(np.array([[4.0, 2.0], [12.0, 7.0], [-3.0, -4.0]]), path, cum)
    np.testing.assert_allclose(d, [2.0, 2.0, 5.0])
    np.testing.assert_allclose(arc, [4.0, 17.0, 0.0])


# ---------------------------------------------------------------------- segment distances
@pytest.mark.parametrize(
    ("p1", "q1", "p2", "q2", "want"),
    [
        ((0, 0), (2, 2), (0, 2), (2, 0), 0.0),  # proper crossing
        ((0, 0), (2, 0), (1, 0), (1, 5), 0.0),  # T: endpoint on the other segment
        ((0, 0), (2, 0), (2, 0), (3, 1), 0.0),  # shared endpoint
        ((0, 0), (2, 0), (1, 0), (5, 0), 0.0),  # collinear overlap
        ((0, 0), (2, 0), (3, 0), (5, 0), 1.0),  # collinear, disjoint
        ((0, 0), (4, 0), (1, 3), (3, 3), 3.0),  # parallel
        ((0, 0), (4, 0), (6, 1), (6, 5), math.hypot(2, 1)),  # end to end
        ((1, 1), (1, 1), (0, 0), (4, 0), 1.0),  # a point against a segment
        ((1, 1), (1, 1), (4, 5), (4, 5), 5.0),  # two points
    ],
)
def test_segment_distances(p1, q1, p2, q2, want):
    a = [np.array(v, dtype=float) for v in (p1, q1, p2, q2)]
    assert float(g.segment_distances(*a)) == pytest.approx(want, abs=1e-15)
    assert float(g.segment_distances(a[2], a[3], a[0], a[1])) == pytest.approx(want, abs=1e-15)


def brute_polyline_distance(a: np.ndarray, b: np.ndarray) -> float:
    sa = [(a[i], a[i + 1]) for i in range(len(a) - 1)] or [(a[0], a[0])]
    sb = [(b[i], b[i + 1]) for i in range(len(b) - 1)] or [(b[0], b[0])]
    return min(float(g.segment_distances(p, q, r, s)) for p, q in sa for r, s in sb)


polylines = st.integers(1, 25).flatmap(
    lambda n: st.lists(
        st.tuples(st.floats(-40, 40), st.floats(-40, 40)), min_size=n, max_size=n
    ).map(lambda pts: np.array(pts, dtype=float))
)


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(polylines, st.lists(polylines, min_size=1, max_size=5))
def test_polyline_distances_equal_brute_force(a, bs):
    """The pruned chunk search never loses the minimum (random, self-crossing polylines)."""
    b, n = pad(bs)
    got = g.polyline_distances(g.chunk_polylines(a[None]), g.chunk_polylines(b, None, n, k=4))
    want = [brute_polyline_distance(a, x) for x in bs]
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_crossing_paths_give_exactly_zero_and_chunk_sizes_agree():
    s = np.linspace(0, 150, 101)
    ego = np.column_stack([s, np.zeros_like(s)])
    crossing = np.column_stack([np.full_like(s, 73.3), s - 75.1])
    parallel = np.column_stack([s, np.full_like(s, 3.5)])
    b, n = pad([crossing, parallel])
    for k in (2, 8, 16):
        d = g.polyline_distances(
            g.chunk_polylines(ego[None], k=k), g.chunk_polylines(b, None, n, k)
        )
        assert d[0] == 0.0
        assert d[1] == pytest.approx(3.5, abs=1e-12)


def test_inactive_padding_chunks_do_not_change_the_result():
    short = np.array([[5.0, 5.0]])
    long = np.column_stack([np.linspace(0, 60, 41), np.zeros(41)])
    b, n = pad([short, long])
    a = np.array([[0.0, 8.0], [60.0, 8.0]])
    d = g.polyline_distances(g.chunk_polylines(a[None]), g.chunk_polylines(b, None, n))
    np.testing.assert_allclose(d, [3.0, 8.0])


# ---------------------------------------------------------------------- first crossing
def test_first_intersections_crossing_and_merge():
    ego = np.array([[0.0, 0.0], [100.0, 0.0]])
    b, n = pad(
        [
            np.array([[40.0, -20.0], [40.0, 20.0]]),  # crosses at ego arc 40, own arc 20
            np.array([[10.0, -5.0], [10.0, 5.0], [30.0, 5.0], [30.0, -5.0]]),  # crosses twice
            np.array([[-10.0, -10.0], [20.0, 0.0], [60.0, 0.0]]),  # merges, then overlaps
            np.array([[0.0, 5.0], [100.0, 5.0]]),  # never meets
        ]
    )
    arc_b, arc_a = g.first_intersections(
        g.chunk_polylines(ego[None]), g.chunk_polylines(b, None, n)
    )
    np.testing.assert_allclose(arc_b[:3], [20.0, 5.0, math.hypot(30, 10)])
    np.testing.assert_allclose(arc_a[:3], [40.0, 10.0, 20.0])
    assert np.isnan(arc_b[3]) and np.isnan(arc_a[3])
    rows = np.array([True, False, True, True])
    arc_b, _ = g.first_intersections(
        g.chunk_polylines(ego[None]), g.chunk_polylines(b, None, n), rows=rows
    )
    assert np.isnan(arc_b[1])  # masked out
