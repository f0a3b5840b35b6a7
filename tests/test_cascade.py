"""The filter cascade: stage logic on sub-frames, false negatives, tiers, the TOML config."""

from __future__ import annotations

import numpy as np
import pytest
from exactness import (
    FLOOR,
    assert_exact,
    assert_within_ulps,
    cascade_ties,
    kernel_ulps,
    numpy_exp_off_by,
)
from frames import scattered_frame
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from risk.cascade import (
    CascadeConfig,
    CascadeConfigError,
    Stage,
    Tier,
    assign_tiers,
    run_cascade,
)
from risk.frame import Frame


def line_frame(n: int, *, valid: list[bool] | None = None, ego: int = 0) -> Frame:
    """``n`` agents on the x axis, ids 10, 11, ..., each with a short straight path."""
    xy = np.c_[np.arange(n) * 10.0, np.zeros(n)]
    paths = [np.array([p, p + np.array([5.0, 0.0])]) for p in xy]
    return Frame.from_arrays(
        xy, np.zeros(n), np.ones(n), np.full(n, 4.0), np.full(n, 2.0), paths, ego,
        ids=np.arange(10, 10 + n), valid=valid,
    )  # fmt: skip


class TableEvaluator:
    """A stand-in for ``risk.evaluate``: fixed risks per model and agent id, NaN for the
    ego and invalid agents; records which agent ids each call saw."""

    def __init__(self, table: dict[str, dict[int, float]]):
        self.table = table
        self.calls: list[tuple[tuple[str, ...], tuple[int, ...]]] = []

    def __call__(self, frame, models=None, params=None, *, prediction=None):
        self.calls.append((tuple(models), tuple(int(i) for i in frame.ids)))
        out = {}
        for m in models:
            r = np.array([self.table[m].get(int(i), np.nan) for i in frame.ids])
            r[frame.ego] = np.nan
            r[~frame.valid] = np.nan
            out[m] = r
        return out


TIERS = (
    Tier("behavior", 1e-25),
    Tier("interactive", 0.1, max_agents=2),
    Tier("cooperative", 0.5, max_agents=1),
)
CONFIG = CascadeConfig(
    stages=(Stage("path_distance", 0.2), Stage("trajectory_distance", 0.3), Stage("gaussian", 1.0)),
    tiers=TIERS,
)


def hand_case() -> tuple[Frame, TableEvaluator]:
    # ego 10; others 11..16; agent 16 invalid.
    frame = line_frame(7, valid=[True] * 6 + [False])
    table = {
        #                 11    12    13    14    15
        "path_distance": {11: 0.9, 12: 0.1, 13: 0.5, 14: 0.2, 15: 0.8},
        "trajectory_distance": {11: 0.9, 12: 0.9, 13: 0.2, 14: 0.3, 15: 0.7},
        "gaussian": {11: 3.0, 12: 9.0, 13: 9.0, 14: 0.5, 15: 1.0},
        # 12 is baseline-important but dropped by stage 0, 14 is dropped by stage 2.
        "survival": {11: 0.6, 12: 0.01, 13: 0.0, 14: 1e-3, 15: 0.2},
    }
    return frame, TableEvaluator(table)


def test_hand_computed_cascade():
    frame, ev = hand_case()
    res = run_cascade(frame, CONFIG, evaluate=ev)
    # Stage 0 keeps risk >= 0.2: 11, 13, 14, 15 (12 has 0.1).
    # Stage 1 keeps >= 0.3 of those: 11, 14, 15 (13 has 0.2).
    # Stage 2 keeps >= 1.0 of those: 11, 15 (14 has 0.5).
    np.testing.assert_array_equal(
        res.kept,
        [
            [0, 1, 0, 1, 1, 1, 0],
            [0, 1, 0, 0, 1, 1, 0],
            [0, 1, 0, 0, 0, 1, 0],
        ],
    )
    np.testing.assert_array_equal(res.dropped_at, [-1, -1, 0, 1, 2, -1, -1])
    np.testing.assert_array_equal(res.others, [0, 1, 1, 1, 1, 1, 0])
    # Baseline: survival >= 1e-25 -> 11, 12, 14, 15 (13 has exactly 0).
    np.testing.assert_array_equal(res.baseline, [0, 1, 1, 0, 1, 1, 0])
    # FN up to stage s: {12}, {12}, {12, 14}.
    np.testing.assert_array_equal(res.false_negatives, [1, 1, 2])
    # Survivors 11 (0.6) and 15 (0.2): both behavior, both interactive (>= 0.1, cap 2),
    # only 11 cooperative (>= 0.5).
    np.testing.assert_array_equal(res.tier, [-1, 2, -1, -1, -1, 1, -1])
    np.testing.assert_array_equal(np.isnan(res.survival), [1, 0, 1, 1, 1, 0, 1])
    assert res.survival[1] == 0.6 and res.survival[5] == 0.2
    np.testing.assert_array_equal(res.survival_all[1:6], [0.6, 0.01, 0.0, 1e-3, 0.2])
    assert res.stage_names == ("path_distance", "trajectory_distance", "gaussian")
    np.testing.assert_array_equal(res.n_kept, [4, 3, 2])
    np.testing.assert_array_equal(res.tier_counts(3), [2, 2, 1])


def test_each_stage_sees_only_the_survivors_of_the_previous_one():
    frame, ev = hand_case()
    run_cascade(frame, CONFIG, evaluate=ev)
    # The ego comes first in every sub-frame; the invalid agent 16 is never evaluated
    # by a stage.
    assert ev.calls == [
        (("survival",), (10, 11, 12, 13, 14, 15, 16)),  # the baseline, on all agents
        (("path_distance",), (10, 11, 12, 13, 14, 15)),
        (("trajectory_distance",), (10, 11, 13, 14, 15)),
        (("gaussian",), (10, 11, 14, 15)),
        (("survival",), (10, 11, 15)),  # sorting the survivors
    ]


def test_times_are_measured_and_non_negative():
    frame, ev = hand_case()
    res = run_cascade(frame, CONFIG, evaluate=ev)
    assert res.stage_time_s.shape == (3,)
    assert np.all(res.stage_time_s > 0)
    assert res.sort_time_s > 0 and res.survival_all_time_s > 0


def test_a_stage_with_nobody_left_is_not_run():
    frame, ev = hand_case()
    config = CascadeConfig(
        stages=(Stage("path_distance", 5.0), Stage("gaussian", 0.0)), tiers=TIERS
    )
    res = run_cascade(frame, config, evaluate=ev)
    assert not res.kept.any()
    assert res.stage_time_s[1] == 0.0 and res.sort_time_s == 0.0
    assert [c[0] for c in ev.calls] == [("survival",), ("path_distance",)]
    np.testing.assert_array_equal(res.false_negatives, [4, 4])
    assert (res.tier == -1).all() and np.isnan(res.survival).all()


def test_ego_alone():
    frame = line_frame(1)
    ev = TableEvaluator({m: {} for m in ("survival", "path_distance", "gaussian")})
    config = CascadeConfig(stages=(Stage("path_distance", 0.0),), tiers=TIERS)
    res = run_cascade(frame, config, evaluate=ev)
    assert res.kept.shape == (1, 1) and not res.kept.any()
    np.testing.assert_array_equal(res.false_negatives, [0])


def test_ego_in_the_middle_keeps_indices_of_the_full_frame():
    frame = line_frame(4, ego=2)  # ids 10, 11, 12 (ego), 13
    ev = TableEvaluator(
        {"path_distance": {10: 0.5, 11: 0.0, 13: 0.7}, "survival": {10: 0.3, 11: 0.0, 13: 0.9}}
    )
    config = CascadeConfig(stages=(Stage("path_distance", 0.1),), tiers=TIERS)
    res = run_cascade(frame, config, evaluate=ev)
    np.testing.assert_array_equal(res.kept[0], [1, 0, 0, 1])
    np.testing.assert_array_equal(res.survival[[0, 3]], [0.3, 0.9])
    np.testing.assert_array_equal(res.tier, [1, -1, -1, 2])


# ---------------------------------------------------------------------- tiers
def test_assign_tiers_hand_computed():
    r = np.array([0.05, 0.9, 0.3, 0.0, 0.6, 0.3])
    # behavior: >= 1e-25 -> all but index 3; interactive (>= 0.1, top 2): 1 and 4;
    # cooperative (>= 0.5, top 1): 1.
    np.testing.assert_array_equal(assign_tiers(r, TIERS), [0, 2, 0, -1, 1, 0])


def test_assign_tiers_ties_prefer_the_lower_index():
    tiers = (Tier("a", 0.0, max_agents=2),)
    np.testing.assert_array_equal(
        assign_tiers(np.array([0.5, 0.7, 0.5, 0.5]), tiers), [0, 0, -1, -1]
    )


tier_strategy = st.lists(
    st.tuples(st.floats(0, 1, allow_nan=False), st.one_of(st.none(), st.integers(1, 6))),
    min_size=1,
    max_size=4,
).map(lambda ts: tuple(Tier(f"t{k}", m, c) for k, (m, c) in enumerate(ts)))


@settings(max_examples=60, deadline=None)
@given(
    r=hnp.arrays(np.float64, st.integers(0, 12), elements=st.floats(0, 1, allow_nan=False)),
    tiers=tier_strategy,
)
def test_tiers_are_nested_capped_and_ranked(r, tiers):
    tier = assign_tiers(r, tiers)
    for k, t in enumerate(tiers):
        members = tier >= k
        assert np.all(r[members] >= t.min_survival_risk)
        if t.max_agents is not None:
            assert members.sum() <= t.max_agents
        if k > 0:
            assert np.all(members <= (tier >= k - 1))  # nested
        # Ranked: nobody outside tier k is riskier than a member while in tier k - 1.
        if members.any():
            prev = tier >= k - 1 if k > 0 else np.ones_like(members)
            outside = prev & ~members
            if outside.any():
                assert r[outside].max() <= r[members].min()


# ---------------------------------------------------------------------- configuration
def test_from_dict_rejects_nonsense_naming_the_key():
    good = CONFIG.to_dict()
    with pytest.raises(CascadeConfigError, match=r"^x\.toml: stages\[1\]\.threshold: must be"):
        CascadeConfig.from_dict(
            {**good, "stages": [good["stages"][0], {"model": "gaussian", "threshold": -1}]},
            source="x.toml",
        )
    with pytest.raises(CascadeConfigError, match=r"^tiers\[0\]\.colour: unknown key"):
        CascadeConfig.from_dict({**good, "tiers": [{**good["tiers"][0], "colour": "red"}]})
    with pytest.raises(CascadeConfigError, match=r"^stages\[0\]\.threshold: missing key"):
        CascadeConfig.from_dict({**good, "stages": [{"model": "gaussian"}]})
    with pytest.raises(CascadeConfigError, match=r"^stages\[0\]\.model: unknown model 'gauss'"):
        CascadeConfig.from_dict({**good, "stages": [{"model": "gauss", "threshold": 1.0}]})
    with pytest.raises(CascadeConfigError, match=r"^stagez: unknown key"):
        CascadeConfig.from_dict({**good, "stagez": []})
    with pytest.raises(CascadeConfigError, match=r"^tiers: missing key"):
        CascadeConfig.from_dict({k: v for k, v in good.items() if k != "tiers"})
    with pytest.raises(CascadeConfigError, match=r"^tiers\[2\]\.max_agents: expected an integer"):
        tiers = [*good["tiers"][:2], {**good["tiers"][2], "max_agents": 0}]
        CascadeConfig.from_dict({**good, "tiers": tiers})
    with pytest.raises(CascadeConfigError, match=r"^baseline_threshold: expected a number"):
        CascadeConfig.from_dict({**good, "baseline_threshold": "small"})


def test_toml_round_trip(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(CONFIG.to_toml_string())
    back = CascadeConfig.from_toml(path)
    assert back == CONFIG
    assert list(tmp_path.iterdir()) == [path]  # no temp file left behind


def test_from_toml_reports_bad_toml_with_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("stages = [\n")
    with pytest.raises(CascadeConfigError, match=r"bad\.toml: toml: not valid TOML"):
        CascadeConfig.from_toml(bad)


def test_default_config_loads_and_is_the_paper_cascade():
    config = CascadeConfig.named("survival")
    assert config.stage_names == ("path_distance", "trajectory_distance", "gaussian")
    assert [t.name for t in config.tiers] == ["behavior", "interactive", "cooperative"]
    assert config.baseline_threshold == 1e-25
    assert "replay calibrate" in config.provenance
    assert all(s.threshold > 0 for s in config.stages)


# ---------------------------------------------------------------------- with the real models
@pytest.mark.exactness
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sub_frame_risks_equal_whole_frame_risks(seed):
    """Every model is a function of the ego and one agent, so a stage on a sub-frame must
    decide exactly as the same threshold on the whole frame (what calibration assumes)."""
    import risk

    frame = scattered_frame(seed)
    whole = risk.evaluate(
        frame, models=["path_distance", "trajectory_distance", "gaussian", "survival"]
    )
    others = frame.others
    # Thresholds at the median of each model's risk, so that every stage drops agents.
    stages = tuple(
        Stage(m, float(np.median(whole[m][others])))
        for m in ("path_distance", "trajectory_distance", "gaussian")
    )
    config = CascadeConfig(stages=stages, tiers=TIERS)
    res = run_cascade(frame, config)
    reaching = others.copy()
    for s, stage in enumerate(stages):
        expected = reaching & (np.nan_to_num(whole[stage.model], nan=-1) >= stage.threshold)
        np.testing.assert_array_equal(res.kept[s], expected)
        reaching = expected
    assert res.kept[0].sum() < others.sum()  # the thresholds did bite
    np.testing.assert_allclose(res.survival_all, whole["survival"], rtol=1e-12)
    survivors = res.kept[-1]
    np.testing.assert_allclose(res.survival[survivors], whole["survival"][survivors], rtol=1e-12)
    assert np.isnan(res.survival[~survivors]).all()
    np.testing.assert_array_equal(
        res.baseline, others & (np.nan_to_num(whole["survival"], nan=-1) >= 1e-25)
    )


def test_prediction_settings_reach_every_evaluation():
    import risk

    frame = scattered_frame(4)
    short = risk.PredictionSettings(horizon_s=3.0)
    config = CascadeConfig(stages=(Stage("gaussian", 0.0),), tiers=TIERS)
    res = run_cascade(frame, config, prediction=short)
    expected = risk.evaluate(frame, models=["survival"], prediction=short)["survival"]
    default = risk.evaluate(frame, models=["survival"])["survival"]
    np.testing.assert_allclose(res.survival_all, expected, rtol=1e-12)
    assert not np.allclose(res.survival_all[frame.others], default[frame.others])
    kept = res.kept[0]
    np.testing.assert_allclose(res.survival[kept], expected[kept], rtol=1e-12)


# ---------------------------------------------------------------------- fused cascade
def spread_frame(rng: np.random.Generator, n: int, spread: float, *, forks: bool = False) -> Frame:
    """Agents of every kind scattered up to ``spread`` m from the ego, random headings,
    speeds and straight or bent paths (some long, some a single point); ``forks``: the
    ego and about a third of the agents have two or three candidate paths."""
    xy = rng.uniform(-spread, spread, (n, 2))
    xy[0] = 0.0
    heading = rng.uniform(-np.pi, np.pi, n)
    paths: list[np.ndarray | list[np.ndarray]] = []
    for i in range(n):
        n_paths = int(rng.integers(2, 4)) if forks and (i == 0 or rng.random() < 0.35) else 1
        candidates = []
        for _ in range(n_paths):
            pts = [xy[i]]
            h = heading[i]
            for _ in range(int(rng.integers(0, 4))):
                h += rng.normal(0, 0.5)
                pts.append(pts[-1] + rng.uniform(1, 60) * np.array([np.cos(h), np.sin(h)]))
            candidates.append(np.array(pts))
        paths.append(candidates if forks else candidates[0])
    speed = rng.uniform(0, 30, n) * (rng.random(n) > 0.2)
    kinds = rng.integers(0, 4, n)
    valid = rng.random(n) > 0.05
    valid[0] = True
    return Frame.from_arrays(
        xy, heading, speed, rng.uniform(0.3, 6, n), rng.uniform(0.3, 2.5, n), paths, 0,
        kinds=kinds, valid=valid,
    )  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from([1e-25, 1e-12, 1e-4]),
    st.sampled_from([None, 0.0]),
    st.sampled_from([20.0, 150.0, 600.0]),
)
def test_reachability_bound_never_drops_an_important_agent(seed, threshold, vmax, spread):
    """Property: every agent that survival analysis rates important (R_S >= threshold) is
    reachable, also with the maximum speeds set to 0 (the bound then rests on the agents'
    own speeds alone, its tightest form)."""
    from risk import PredictionSettings, evaluate
    from risk.cascade import reachable_mask

    rng = np.random.default_rng(seed)
    frame = spread_frame(rng, 40, spread)
    pred = PredictionSettings(horizon_s=float(rng.choice([2.0, 6.0])), dt_s=0.25)
    speeds = (
        None if vmax is None else dict.fromkeys(("vehicle", "pedestrian", "cyclist", "other"), vmax)
    )
    reach = reachable_mask(frame, threshold, prediction=pred, max_speed_mps=speeds)
    surv = evaluate(frame, ["survival"], prediction=pred)["survival"]
    important = frame.others & (np.nan_to_num(surv, nan=-1.0) >= threshold)
    assert not (important & ~reach).any()
    assert not reach[~frame.others].any()


def test_reachability_bound_drops_far_agents():
    from risk import PredictionSettings
    from risk.cascade import reachable_mask

    frame = spread_frame(np.random.default_rng(1), 60, 20.0)
    far = Frame.from_arrays(
        np.array([[0.0, 0.0], [5000.0, 0.0], [40.0, 0.0]]), np.zeros(3), np.array([10.0, 0, 0]),
        np.full(3, 4.0), np.full(3, 2.0),
        [np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([[5000.0, 0.0]]), np.array([[40.0, 0.0]])],
        0,
    )  # fmt: skip
    np.testing.assert_array_equal(reachable_mask(far), [False, False, True])
    # Close agents are never dropped.
    assert reachable_mask(frame, prediction=PredictionSettings(2.0, 0.5))[frame.others].all()


@pytest.mark.exactness
@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([30.0, 400.0]), st.booleans())
def test_fused_cascade_matches_the_staged_oracle(seed, spread, forks):
    """Same kept sets, drops, tiers and survival (bit for bit: the kernel on both sides,
    the same compiled code) as the staged cascade on sub-frames, except the agents the reachability bound drops first (none of them
    important); also with several candidate paths per agent and for the ego (the
    Gaussian stage hands the pair it computed last to survival)."""
    from risk import PredictionSettings, evaluate

    rng = np.random.default_rng(seed)
    frame = spread_frame(rng, 50, spread, forks=forks)
    pred = PredictionSettings(horizon_s=4.0, dt_s=0.25)
    config = CascadeConfig(
        stages=(
            Stage("path_distance", float(rng.choice([0.0, 0.02, 0.3, 1.0]))),
            Stage("trajectory_distance", float(rng.choice([0.01, 0.1]))),
            Stage("gaussian", float(rng.choice([0.0, 1e-30, 1e-3]))),
        ),
        tiers=TIERS,
    )
    staged = run_cascade(frame, config, prediction=pred, evaluate=lambda *a, **k: evaluate(*a, **k))
    plain = run_cascade(frame, config, prediction=pred, reachability=False)
    fused = run_cascade(frame, config, prediction=pred)
    for name in ("kept", "dropped_at", "tier", "baseline", "false_negatives", "survival_all"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(staged, name), err_msg=name)
    np.testing.assert_array_equal(plain.survival, staged.survival)
    assert not (fused.unreachable & fused.baseline).any()
    np.testing.assert_array_equal(fused.kept, staged.kept & ~fused.unreachable)
    np.testing.assert_array_equal(fused.false_negatives, staged.false_negatives)
    assert (fused.dropped_at[fused.unreachable] == 0).all()


@pytest.mark.exactness
@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_fused_cascade_with_other_stage_models_matches_the_staged_oracle(seed):
    """Stages outside the one-pass kernel (here the current distance and the circles, in
    another order) run one kernel call per stage; same decisions as on sub-frames."""
    from risk import PredictionSettings, evaluate

    rng = np.random.default_rng(seed)
    frame = spread_frame(rng, 40, 60.0)
    pred = PredictionSettings(horizon_s=3.0, dt_s=0.25)
    config = CascadeConfig(
        stages=(
            Stage("gaussian", float(rng.choice([0.0, 1e-30]))),
            Stage("current_distance", float(rng.choice([0.02, 0.1]))),
            Stage("circles", 0.05),
        ),
        tiers=TIERS,
    )
    staged = run_cascade(frame, config, prediction=pred, evaluate=lambda *a, **k: evaluate(*a, **k))
    plain = run_cascade(frame, config, prediction=pred, reachability=False)
    for name in ("kept", "dropped_at", "tier", "false_negatives", "survival"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(staged, name), err_msg=name)


@pytest.mark.exactness
@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([30.0, 400.0]), st.sampled_from([0, 1]))
def test_fused_cascade_on_the_kernel_decides_as_the_staged_one_on_numpy(seed, spread, exp_ulps):
    """Across code paths: the fused cascade (the compiled kernel) against the staged
    cascade on the numpy modules, with numpy's own exp or one moved by up to a float
    (another CPU's, simulated). Survival within the contract's ulps; every decision (kept
    by each stage, dropped where, tier, baseline, false negatives) the same, except for
    the agents that cascade_ties finds within the tolerance of a threshold or of another
    agent's rank. The thresholds are risks of agents of the frame, as calibration picks
    them, so such ties are there on purpose: they are found, left out by name and
    counted, and stay few."""
    from risk import PredictionSettings, evaluate
    from risk.registry import evaluate_numpy

    rng = np.random.default_rng(seed)
    frame = spread_frame(rng, 50, spread, forks=bool(rng.random() < 0.5))
    pred = PredictionSettings(horizon_s=4.0, dt_s=0.25)
    fast = evaluate(frame, prediction=pred)
    others = np.flatnonzero(frame.others)

    def observed(model: str) -> float:
        """A risk of an agent of the frame, as calibration picks them; not 1 (touching
        paths), and not 0 or below the contract's floor of 1e-300 (no overlap at any step,
        or a subnormal that another code path may round to 0), which many agents share."""
        values = fast[model][others]
        values = values[(values >= FLOOR) & (values < 1)]
        return float(rng.choice(values)) if values.size else 0.1

    config = CascadeConfig(
        stages=(
            Stage("path_distance", observed("path_distance")),
            Stage("trajectory_distance", float(rng.choice([0.01, 0.1]))),
            Stage("gaussian", observed("gaussian")),
        ),
        tiers=(
            Tier("behavior", observed("survival")),
            Tier("interactive", float(rng.choice([1e-12, 1e-6])), max_agents=3),
        ),
    )
    fused = run_cascade(frame, config, prediction=pred, reachability=False)
    with numpy_exp_off_by(exp_ulps, rng):
        staged = run_cascade(frame, config, prediction=pred, evaluate=evaluate_numpy)

    def tol(model: str) -> float:
        return kernel_ulps(model, pred.horizon_s)

    tol_s = tol("survival")
    assert_within_ulps(fused.survival_all, staged.survival_all, tol_s, "survival_all")
    both = fused.kept[-1] & staged.kept[-1]
    assert_within_ulps(fused.survival[both], staged.survival[both], tol_s, "survival")

    ties = cascade_ties(fast, config, tol)
    n_ties = int(ties[others].sum())
    # Thresholds on observed risks: at least the agents that gave them are found.
    on_a_threshold = np.zeros(frame.n_agents, dtype=bool)
    for stage in (config.stages[0], config.stages[2]):
        on_a_threshold |= fast[stage.model] == stage.threshold
    assert not (on_a_threshold & ~ties).any()
    assert n_ties <= max(4, others.size // 10), f"{n_ties} of {others.size} agents tie"
    clear = frame.others & ~ties
    for name in ("dropped_at", "baseline"):
        assert_exact(getattr(fused, name)[clear], getattr(staged, name)[clear], name)
    assert_exact(fused.kept[:, clear], staged.kept[:, clear], "kept")
    # A tied agent that survives on one side only and reaches the capped tier's threshold
    # changes the ranking of everyone in that tier: then the tiers are not compared.
    contending = fast["survival"] >= config.tiers[1].min_survival_risk
    if not (ties & contending & (fused.kept[-1] | staged.kept[-1])).any():
        assert_exact(fused.tier[clear], staged.tier[clear], "tier")
    fn_apart = np.abs(fused.false_negatives - staged.false_negatives)
    assert (fn_apart <= n_ties).all(), (fused.false_negatives, staged.false_negatives, n_ties)


def test_one_pass_stage_times_share_the_measured_call():
    """The one-pass cascade reports each part's time as a share of the call: every share
    is >= 0, a stage that judged nobody costs 0, and the parts add up to no more than the
    whole run."""
    import time

    frame = spread_frame(np.random.default_rng(2), 60, 50.0)
    config = CascadeConfig(
        stages=(
            Stage("path_distance", 0.02),
            Stage("trajectory_distance", 2.0),  # drops everyone (risk <= 1)
            Stage("gaussian", 1e-30),
        ),
        tiers=TIERS,
    )
    start = time.perf_counter()
    res = run_cascade(frame, config)
    whole = time.perf_counter() - start
    assert res.kept[1].sum() == 0 and res.kept[0].sum() > 0
    assert (res.stage_time_s >= 0).all() and res.reach_time_s >= 0 and res.sort_time_s >= 0
    assert res.stage_time_s[0] > 0 and res.stage_time_s[1] > 0
    assert res.stage_time_s[2] == 0.0  # nobody reached the Gaussian stage
    parts = res.reach_time_s + res.stage_time_s.sum() + res.sort_time_s
    assert parts + res.survival_all_time_s <= whole


def test_the_fused_result_has_every_field_as_the_constructor_sets_them():
    """``CascadeResult._make`` (the fused cascade's fast constructor) sets every field."""
    import dataclasses

    from risk.cascade import CascadeResult

    res = run_cascade(spread_frame(np.random.default_rng(5), 30, 40.0), CONFIG)
    values = {f.name: getattr(res, f.name) for f in dataclasses.fields(CascadeResult)}
    assert vars(res) == values
    assert vars(CascadeResult(**values)) == vars(res)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.sort_time_s = 0.0  # type: ignore[misc]


def test_engine_style_partial_uses_the_fused_cascade():
    import functools

    from risk import PredictionSettings, evaluate

    frame = spread_frame(np.random.default_rng(4), 30, 3000.0)
    pred = PredictionSettings(horizon_s=2.0, dt_s=0.5)
    res = run_cascade(frame, CONFIG, evaluate=functools.partial(evaluate, prediction=pred))
    assert res.unreachable is not None and res.unreachable.any()


@settings(max_examples=200, deadline=None)
@given(
    st.floats(1e-9, 1.0),
    st.floats(1e-3, 50.0),
    st.lists(st.floats(0.0, 1e4), min_size=1, max_size=20),
)
def test_keep_bounds_never_change_a_decision(threshold, eps, distances):
    """d^2 <= stop2 certainly keeps and d^2 > cut2 certainly drops, in floating point."""
    from risk.cascade import keep_bounds

    stop2, cut2 = keep_bounds(threshold, eps)
    assert stop2 <= cut2
    d_cut = eps / threshold - eps
    for d in [*distances, d_cut, np.nextafter(d_cut, 0), np.nextafter(d_cut, np.inf)]:
        risk = eps / (eps + d)
        if d * d <= stop2:
            assert risk >= threshold
        if d * d > cut2:
            assert risk < threshold


@pytest.mark.exactness
def test_without_a_cycle_counter_the_cascade_times_each_stage(monkeypatch):
    """Where the one-pass kernel may not read the cycle counter (non-x86), the fused
    cascade runs one kernel call per stage: the same decisions, tiers and survival."""
    from risk import kernel

    frame = spread_frame(np.random.default_rng(9), 50, 40.0)
    one_pass = run_cascade(frame, CONFIG)
    monkeypatch.setattr(kernel, "HAVE_CYCLE_COUNTER", False)
    per_stage = run_cascade(frame, CONFIG)
    for name in ("kept", "dropped_at", "tier", "unreachable", "false_negatives", "survival"):
        np.testing.assert_array_equal(
            getattr(one_pass, name), getattr(per_stage, name), err_msg=name
        )


def test_the_default_is_the_planner_calibrated_cascade_with_its_guarantee():
    config = CascadeConfig.default()
    assert config == CascadeConfig.named("planner")
    assert config.corridor is not None and config.stages
    g = config.guarantee
    assert {"miss_rate", "confidence", "unit", "units", "statement"} <= set(g)
    assert "--reference planner" in config.provenance


def test_without_tiers_no_path_computes_survival_and_all_keep_the_same(monkeypatch):
    """A cascade without tiers skips survival of the survivors in the one-pass kernel and
    in the pass per stage (CPUs without a cycle counter) alike: the same decisions as
    with tiers, survival NaN, no tier."""
    import dataclasses

    from risk import kernel

    frame = spread_frame(np.random.default_rng(9), 50, 10.0)
    config = dataclasses.replace(CONFIG, stages=CONFIG.stages[:2])  # (some survive both)
    tiered = run_cascade(frame, config)
    assert tiered.kept[-1].sum() > 5 and (tiered.tier >= 0).any()
    one_pass = run_cascade(frame, dataclasses.replace(config, tiers=()))
    monkeypatch.setattr(kernel, "HAVE_CYCLE_COUNTER", False)
    per_stage = run_cascade(frame, dataclasses.replace(config, tiers=()))
    for result in (one_pass, per_stage):
        for name in ("kept", "dropped_at", "unreachable", "false_negatives"):
            np.testing.assert_array_equal(getattr(result, name), getattr(tiered, name), name)
        assert np.isnan(result.survival).all() and (result.tier == -1).all()
    assert not np.isnan(tiered.survival[tiered.kept[-1]]).any()
