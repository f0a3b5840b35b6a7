"""The filter's answer by agent id (risk.filtering): hand-made frames with known answers,
the cascade's answer against run_cascade itself, and properties of the simple cuts."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk import CascadeConfig, Frame, filter_frame, parse_filter
from risk.cascade import run_cascade
from risk.filtering import (
    REACHABILITY,
    FilterSpecError,
    KeepAll,
    ModelFilter,
    NearestFilter,
    RadiusFilter,
)


def _frame(xy: list[tuple[float, float]], *, ids: list[int] | None = None, ego: int = 0) -> Frame:
    """Agents on parallel straight paths along +x at 5 m/s."""
    pts = np.asarray(xy, dtype=float)
    n = len(pts)
    return Frame.from_arrays(
        xy=pts,
        heading=np.zeros(n),
        speed=np.full(n, 5.0),
        length=np.full(n, 4.0),
        width=np.full(n, 2.0),
        paths=[np.array([p, p + np.array([80.0, 0.0])]) for p in pts],
        ego=ego,
        ids=ids,
    )


def test_nearest_keeps_the_k_nearest_by_id_in_distance_order() -> None:
    frame = _frame([(0, 0), (30, 0), (10, 0), (0, -20), (100, 0)], ids=[5, 6, 7, 8, 9])
    answer = NearestFilter(2).apply(frame)
    assert answer.kept_ids.tolist() == [7, 8]  # 10 m, then 20 m
    assert answer.dropped == {6: "nearest:2", 9: "nearest:2"}
    assert answer.n_others == 4 and answer.ego_id == 5
    assert NearestFilter(10).apply(frame).kept_ids.tolist() == [7, 8, 6, 9]
    assert NearestFilter(0).apply(frame).kept_ids.size == 0


def test_radius_is_inclusive_and_ignores_invalid_agents() -> None:
    pts = np.array([(0, 0), (30, 0), (10, 0), (0, -20), (5, 5)], dtype=float)
    frame = Frame.from_arrays(
        xy=pts, heading=np.zeros(5), speed=np.full(5, 5.0), length=np.full(5, 4.0),
        width=np.full(5, 2.0), paths=[np.array([p, p + np.array([80.0, 0.0])]) for p in pts], ego=0,
        valid=[True, True, True, True, False],
    )  # fmt: skip
    answer = RadiusFilter(20.0).apply(frame)
    assert answer.kept_ids.tolist() == [2, 3]  # 10 m and exactly 20 m; agent 4 invalid
    assert set(answer.dropped) == {1}
    assert answer.n_others == 3


def test_keep_all_keeps_every_valid_other() -> None:
    frame = _frame([(0, 0), (30, 0), (10, 0)])
    answer = KeepAll().apply(frame)
    assert sorted(answer.kept_ids.tolist()) == [1, 2] and answer.dropped == {}


def test_model_filter_keeps_what_reaches_the_threshold() -> None:
    # current distance: R = 1 / (1 + d), d the centre distance; 1 / (1 + 10) ~ 0.0909
    frame = _frame([(0, 0), (30, 0), (10, 0), (0, -20)])
    answer = ModelFilter("current_distance", 1.0 / 21.0).apply(frame)  # d <= 20 m
    assert answer.kept_ids.tolist() == [2, 3]  # riskiest first
    assert answer.dropped == {1: "current_distance"}


def test_cascade_answer_matches_run_cascade() -> None:
    rng = np.random.default_rng(4)
    n = 40
    xy = rng.uniform(-120, 120, size=(n, 2))
    xy[0] = 0.0
    heading = rng.uniform(-np.pi, np.pi, n)
    direction = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    frame = Frame.from_arrays(
        xy=xy, heading=heading, speed=rng.uniform(0, 15, n), length=np.full(n, 4.5),
        width=np.full(n, 1.8), paths=[np.array([p, p + 120 * d]) for p, d in zip(xy, direction, strict=False)],
        ego=0, ids=np.arange(100, 100 + n),
    )  # fmt: skip
    config = CascadeConfig.default()
    answer = filter_frame(frame, config)
    result = run_cascade(frame, config)
    kept = set(frame.ids[result.kept[-1]].tolist())
    assert set(answer.kept_ids.tolist()) == kept
    others = set(frame.ids[frame.others].tolist())
    assert set(answer.dropped) == others - kept
    assert set(answer.dropped.values()) <= {REACHABILITY, *config.stage_names}
    # most important first: survival risk non-increasing along kept_ids
    index = {int(i): k for k, i in enumerate(frame.ids)}
    surv = np.array([result.survival[index[int(i)]] for i in answer.kept_ids])
    assert np.all(np.diff(surv) <= 0)
    # tiers are nested and named as in the config
    names = [t.name for t in config.tiers]
    assert list(answer.tiers) == names
    for outer, inner in itertools.pairwise(names):
        assert set(answer.tiers[inner]) <= set(answer.tiers[outer])
    assert answer.cascade is not None
    assert np.array_equal(answer.cascade.kept, result.kept) and answer.time_ms >= 0
    text = repr(answer)
    assert "cascade" in text and len(text.splitlines()) == 1


@pytest.mark.parametrize(
    ("spec", "name"),
    [("none", "none"), ("cascade", "cascade"), ("nearest:32", "nearest:32"),
     ("radius:50", "radius:50"), ("model:gaussian:1e-20", "model:gaussian"),
     ("model:survival:1e-25", "model:survival"), ("cascade:survival", "cascade:survival"),
     ("cascade:planner", "cascade:planner")],
)  # fmt: skip
def test_parse_filter_forms(spec: str, name: str) -> None:
    assert parse_filter(spec).name == name


def test_model_filter_takes_the_cascade_stage_threshold() -> None:
    config = CascadeConfig.default()
    stage = config.stages[0]  # whichever model the shipped cascade's first stage uses
    flt = parse_filter(f"model:{stage.model}", config)
    assert isinstance(flt, ModelFilter)
    assert flt.threshold == stage.threshold


@pytest.mark.parametrize(
    "spec", ["nearest", "nearest:x", "nearest:-1", "radius:far", "radius:-3", "radius:inf",
             "model:wobble", "model:headway", "model:gaussian:nan", "closest:3", ""],
)  # fmt: skip
def test_bad_specs_name_the_valid_forms(spec: str) -> None:
    with pytest.raises(FilterSpecError) as info:
        parse_filter(spec)
    message = str(info.value)
    assert "nearest:K" in message and "radius:R" in message and "\n" not in message


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-200, 200), st.floats(-200, 200)), min_size=2, max_size=30),
    st.integers(0, 40),
)
def test_nearest_property_kept_never_farther_than_dropped(pts, k) -> None:
    frame = _frame([(0.0, 0.0), *pts[1:]], ids=list(range(len(pts))))
    answer = NearestFilter(k).apply(frame)
    assert answer.n_kept == min(k, len(pts) - 1)
    d = np.hypot(*frame.xy.T)
    kept = d[answer.kept_ids]
    dropped = d[list(answer.dropped)]
    if kept.size and dropped.size:
        assert kept.max() <= dropped.min()
    assert np.all(np.diff(kept) >= 0)
