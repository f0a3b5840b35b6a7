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
    CORRIDOR,
    REACHABILITY,
    CascadeFilter,
    FilterSpecError,
    KeepAll,
    ModelFilter,
    NearestFilter,
    RadiusFilter,
    cascade_answer,
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


def _dropped_oracle(frame: Frame, result) -> dict[int, str]:
    """The drop reasons one agent at a time: the bound first, then the corridor, else the
    stage that dropped it (the slow, obvious form of cascade_answer's)."""
    out = {}
    for i in np.flatnonzero(result.dropped_at >= 0):
        if result.unreachable is not None and result.unreachable[i]:
            out[int(frame.ids[i])] = REACHABILITY
        elif result.behind is not None and result.behind[i]:
            out[int(frame.ids[i])] = CORRIDOR
        else:
            out[int(frame.ids[i])] = result.stage_names[int(result.dropped_at[i])]
    return out


def _highway(rng: np.random.Generator, n: int) -> Frame:
    """Vehicles on three lanes along +x, ahead and behind the ego, some far and fast:
    the bound, the corridor (followers behind) and the stage each drop some."""
    x = np.concatenate([[0.0], rng.uniform(-400.0, 1500.0, n - 1)])
    y = np.concatenate([[0.0], rng.choice([-3.5, 0.0, 3.5, 40.0], n - 1)])
    xy = np.stack([x, y], axis=1)
    return Frame.from_arrays(
        xy=xy, heading=np.zeros(n), speed=rng.uniform(5.0, 35.0, n), length=np.full(n, 4.5),
        width=np.full(n, 1.8), paths=[np.array([p, p + np.array([400.0, 0.0])]) for p in xy],
        ego=0, ids=np.arange(500, 500 + n),
    )  # fmt: skip


@pytest.mark.parametrize("seed", range(6))
def test_cascade_filter_without_the_baseline_answers_as_with_it(seed: int) -> None:
    """CascadeFilter skips survival on all agents (not part of the answer): the same
    kept ids in the same order, tiers and drop reasons as run_cascade with the baseline,
    and drop reasons equal to the one-at-a-time oracle."""
    frame = _highway(np.random.default_rng(seed), 60)
    config = CascadeConfig.default()
    answer = CascadeFilter(config).apply(frame)
    full = run_cascade(frame, config)  # with the baseline
    reference = cascade_answer(frame, full, config)
    assert answer.kept_ids.tolist() == reference.kept_ids.tolist()
    assert answer.tiers == reference.tiers
    assert answer.dropped == reference.dropped == _dropped_oracle(frame, full)
    reasons = set(answer.dropped.values())
    assert reasons <= {REACHABILITY, CORRIDOR, *config.stage_names}
    assert {REACHABILITY, CORRIDOR} <= reasons and reasons & set(config.stage_names)
    result = answer.cascade
    assert result is not None and full.baseline_computed and not result.baseline_computed
    assert np.isnan(result.survival_all).all() and not result.baseline.any()
    assert not result.false_negatives.any()
    with_baseline = CascadeFilter(config, baseline=True).apply(frame).cascade
    assert with_baseline is not None and with_baseline.baseline_computed
    np.testing.assert_array_equal(with_baseline.survival_all, full.survival_all)


@pytest.mark.parametrize("seed", range(4))
def test_a_cascade_without_tiers_keeps_the_same_agents_without_survival(seed: int) -> None:
    """tiers=False (replay plan's planners read only the kept agents): the same kept and
    dropped agents, no tiers, no survival risk; the fused kernel, the pass per stage and
    the staged cascade agree on it."""
    import dataclasses

    from risk.registry import evaluate as risk_evaluate

    frame = _highway(np.random.default_rng(10 + seed), 50)
    config = CascadeConfig.default()
    tiered = CascadeFilter(config).apply(frame)
    plain = CascadeFilter(config, tiers=False).apply(frame)
    assert sorted(plain.kept_ids.tolist()) == sorted(tiered.kept_ids.tolist())
    assert plain.kept_ids.tolist() == sorted(plain.kept_ids.tolist())  # the frame's order
    assert plain.dropped == tiered.dropped and plain.tiers == {}
    assert plain.cascade is not None and np.isnan(plain.cascade.survival).all()
    assert (
        tiered.cascade is not None
        and not np.isnan(tiered.cascade.survival[tiered.cascade.kept[-1]]).any()
    )
    untiered = dataclasses.replace(config, tiers=())
    staged = run_cascade(frame, untiered, evaluate=lambda *a, **k: risk_evaluate(*a, **k))
    np.testing.assert_array_equal(staged.kept, plain.cascade.kept)
    assert np.isnan(staged.survival).all() and (staged.tier == -1).all()


def test_an_applied_cascade_filter_pickles_without_its_prepared_config() -> None:
    """Filters go to worker processes: the parsed settings are not carried along."""
    import pickle

    config = CascadeConfig.default()
    applied = CascadeFilter(config)
    first = applied.apply(_highway(np.random.default_rng(1), 20))
    copy = pickle.loads(pickle.dumps(applied))
    assert "_prepared" not in vars(copy) and copy.config == config
    again = copy.apply(_highway(np.random.default_rng(1), 20))
    assert again.kept_ids.tolist() == first.kept_ids.tolist()


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
