"""One conformance suite run over every model in the registry."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from exactness import assert_exact, assert_within_ulps, kernel_ulps

from risk import (
    BASELINE_MODEL,
    BASELINE_THRESHOLD,
    MODELS,
    Frame,
    FrameContext,
    ModelSpec,
    PredictionSettings,
    RiskError,
    UnknownModelError,
    baseline_mask,
    evaluate,
)

ORDER = [
    "current_distance",
    "path_distance",
    "trajectory_distance",
    "closest_encounter",
    "headway",
    "headway_2d",
    "circles",
    "gaussian",
    "survival",
]


def scene(n: int = 12, seed: int = 3) -> Frame:
    """A crossing-rich frame: lanes east/west and north/south, a pedestrian, a standing
    car, an invalid track, and one agent with two path candidates; the ego is agent 2."""
    rng = np.random.default_rng(seed)
    xy, heading, paths, kinds = [], [], [], []
    for i in range(n):
        if i % 2:
            x0, y0, h = rng.uniform(-60, 60), rng.choice([-1.75, 1.75]), rng.choice([0.0, math.pi])
        else:
            x0, y0, h = (
                rng.choice([-1.75, 1.75]),
                rng.uniform(-60, 60),
                rng.choice([-1, 1]) * math.pi / 2,
            )
        u = np.array([math.cos(h), math.sin(h)])
        start = np.array([x0, y0])
        path = start + np.linspace(0, 80, 41)[:, None] * u
        if i == 5:  # a fork: straight on, or turn left
            left = np.array([-u[1], u[0]])
            path = [path, np.vstack([start, start + 10 * u, start + 10 * u + 40 * left])]
        xy.append(start)
        heading.append(h)
        paths.append(path)
        kinds.append("pedestrian" if i == 7 else "vehicle")
    speed = rng.uniform(0, 15, n)
    speed[9] = 0.0
    valid = np.ones(n, dtype=bool)
    valid[4] = False
    return Frame.from_arrays(
        np.array(xy),
        np.array(heading),
        speed,
        np.full(n, 4.5),
        np.full(n, 1.9),
        paths,
        ego=2,
        kinds=kinds,
        valid=valid,
        ids=np.arange(100, 100 + n),
    )


FRAME = scene()
PRED = PredictionSettings(horizon_s=8.0, dt_s=0.2)


def test_registry_order_and_metadata():
    assert list(MODELS) == ORDER
    for name, spec in MODELS.items():
        assert isinstance(spec, ModelSpec)
        assert spec.name == name
        assert spec.family in ("distance", "time", "stochastic")
        assert spec.paper_ref.startswith("eq.") and "Sec." in spec.paper_ref
        assert spec.complexity.startswith("O(")
        assert dataclasses.is_dataclass(spec.params_type)
        params = spec.default_params()
        with pytest.raises(dataclasses.FrozenInstanceError):
            params.__setattr__("x", 1)  # frozen
        for p in spec.describe_params():
            assert p["name"] and "value" in p
    assert BASELINE_MODEL == "survival" and BASELINE_THRESHOLD == 1e-25


def test_the_registry_drives_colours_titles_and_ranges():
    """Plot colours, report titles and table ranges come from ModelSpec, not from lists
    of names in replay/ (so a new model needs no edit there)."""
    import matplotlib.colors

    from replay.analysis.evaluation.report import TITLES
    from replay.analysis.stats.plots import MODEL_COLORS
    from replay.core.tablecheck import RANGES

    colors = [spec.color for spec in MODELS.values()]
    assert len(set(colors)) == len(colors)  # one colour per model in the ROC plot
    assert all(matplotlib.colors.is_color_like(c) for c in colors)
    assert all(spec.label.strip() for spec in MODELS.values())
    for name, spec in MODELS.items():
        lo, hi = spec.risk_range
        assert 0.0 <= lo < hi
        assert MODEL_COLORS[name] == spec.color and TITLES[name] == spec.label
        assert RANGES[name] == spec.risk_range
    # densities (1/m^2): the Gaussian overlap, and survival analysis built on it
    unbounded = {"gaussian", "survival"}
    assert all(MODELS[n].risk_range == (0.0, math.inf) for n in unbounded)
    assert {spec.risk_range for n, spec in MODELS.items() if n not in unbounded} == {(0.0, 1.0)}


@pytest.mark.parametrize("name", ORDER)
def test_shape_dtype_and_nan_only_for_ego_and_invalid(name):
    r = evaluate(FRAME, [name], prediction=PRED)[name]
    assert r.shape == (FRAME.n_agents,)
    assert r.dtype == np.float64
    assert np.array_equal(np.isnan(r), ~FRAME.others)
    assert np.all(np.isfinite(r[FRAME.others]))


@pytest.mark.exactness
@pytest.mark.parametrize("name", ORDER)
def test_deterministic_and_the_same_alone_or_together(name):
    """Twice, alone or with the others: the same compiled code, so bit for bit."""
    alone = evaluate(FRAME, [name], prediction=PRED)[name]
    again = evaluate(FRAME, [name], prediction=PRED)[name]
    together = evaluate(FRAME, prediction=PRED)[name]
    assert_exact(alone, again, "twice")
    assert_exact(alone, together, "alone vs together")


@pytest.mark.exactness
@pytest.mark.parametrize("name", ORDER)
def test_the_spec_callable_gives_what_evaluate_gives(name):
    """The spec callable (the numpy code) against evaluate (the compiled kernel): within
    the exactness contract's ulps (tests/exactness.py), not bit for bit, since numpy's
    exp is its own SIMD code on some CPUs."""
    kernel = evaluate(FRAME, [name], prediction=PRED)[name]
    direct = MODELS[name].fn(FrameContext(FRAME, PRED), MODELS[name].default_params())
    assert_within_ulps(kernel, direct, kernel_ulps(name, PRED.horizon_s), name)


@pytest.mark.parametrize("name", ORDER)
def test_agent_order_does_not_matter(name):
    perm = np.random.default_rng(0).permutation(FRAME.n_agents)
    shuffled = FRAME.select(perm)
    a = evaluate(FRAME, [name], prediction=PRED)[name]
    b = evaluate(shuffled, [name], prediction=PRED)[name]
    np.testing.assert_allclose(b, a[perm], rtol=1e-12, atol=0)


@pytest.mark.parametrize("name", ORDER)
def test_an_agent_risk_does_not_depend_on_who_else_is_present(name):
    full = evaluate(FRAME, [name], prediction=PRED)[name]
    pair = evaluate(FRAME.select([FRAME.ego, 6]), [name], prediction=PRED)[name]
    assert pair[1] == pytest.approx(full[6], rel=1e-12)


@pytest.mark.parametrize("name", ORDER)
def test_inputs_are_not_modified(name):
    before = {
        k: np.array(v, copy=True) for k, v in FRAME._fields().items() if isinstance(v, np.ndarray)
    }
    params = MODELS[name].default_params()
    params_before = dataclasses.asdict(params)
    evaluate(FRAME, [name], {name: params}, prediction=PRED)
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(FRAME, k), v, err_msg=k)
    assert dataclasses.asdict(params) == params_before


@pytest.mark.parametrize("name", ORDER)
def test_frame_with_only_the_ego(name):
    alone = FRAME.select([FRAME.ego])
    r = evaluate(alone, [name], prediction=PRED)[name]
    assert r.shape == (1,) and np.isnan(r[0])


def test_models_argument_forms_and_errors():
    assert list(evaluate(FRAME, prediction=PRED)) == ORDER
    assert list(evaluate(FRAME, "gaussian", prediction=PRED)) == ["gaussian"]
    assert list(evaluate(FRAME, ["survival", "headway", "survival"], prediction=PRED)) == [
        "survival",
        "headway",
    ]
    with pytest.raises(UnknownModelError, match="valid models: current_distance"):
        evaluate(FRAME, ["ttc"])
    with pytest.raises(UnknownModelError):
        evaluate(FRAME, None, {"ttc": object()})
    with pytest.raises(RiskError, match="SurvivalParams"):
        evaluate(FRAME, ["survival"], {"survival": MODELS["gaussian"].default_params()})
    with pytest.raises(RiskError, match="PredictionSettings"):
        evaluate(FRAME, ["survival"], prediction={"horizon_s": 3})


def test_parameters_are_validated():
    with pytest.raises(RiskError, match="epsilon_m"):
        MODELS["path_distance"].params_type(epsilon_m=0.0)
    with pytest.raises(RiskError, match="n_circles"):
        MODELS["circles"].params_type(n_circles=0)
    with pytest.raises(RiskError, match="escape_time_s"):
        MODELS["survival"].params_type(escape_time_s=-1.0)
    with pytest.raises(RiskError, match="encounter_time_max_s"):
        MODELS["closest_encounter"].params_type(encounter_time_max_s=0.0)


def test_baseline_mask():
    np.testing.assert_array_equal(
        baseline_mask(np.array([np.nan, 0.0, 1e-26, 1e-25, 0.3])), [False, False, False, True, True]
    )
