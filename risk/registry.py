"""The registry of the nine risk models and :func:`evaluate`, the one entry point.

Code that uses models (replay, cascade, calibration, ROC, recordings) iterates over
:data:`MODELS` and never special-cases a model by name.

Paper references count equations and sections as the paper source
(``../shared/paper/*.tex``) compiles: the TPR/FPR pair is eq. 1-2 and the models are in
Sec. III. (The model spec, ``../shared/docs/risk-models.md``, numbers some of them
differently.)
"""

from __future__ import annotations

import functools
import math
import types
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np

from risk import distance, stochastic, temporal
from risk.errors import RiskError, UnknownModelError
from risk.frame import Frame
from risk.lazy import lazy_module
from risk.prediction import FrameContext, PredictionSettings

Family = Literal["distance", "time", "stochastic"]
ModelFn = Callable[[FrameContext, Any], np.ndarray]


@dataclass(frozen=True, kw_only=True)
class ModelSpec:
    """One risk model: how to call it and how to describe it.

    ``fn(ctx, params)`` is the vectorised numpy implementation: it returns ``(N,)``
    float64 risks, higher = riskier, NaN for the ego and invalid agents; ``params`` is an
    instance of ``params_type`` (a frozen dataclass). :func:`evaluate` runs the compiled
    kernel (:mod:`risk.kernel`) instead; ``fn`` stays as the oracle it is tested against
    (:func:`evaluate_numpy`). Build specs with keywords only.
    """

    name: str
    title: str
    family: Family
    paper_ref: str
    complexity: str
    params_type: type
    fn: ModelFn
    #: the model's name inside a sentence of a report ("... ranks above {label}")
    label: str
    #: its colour in every plot (a matplotlib colour name; the paper's, Sec. V)
    color: str
    unit: str = ""  # unit of the risk value ("" = dimensionless)
    #: the closed range of its risk values (tables read back are checked against it)
    risk_range: tuple[float, float] = (0.0, 1.0)

    def default_params(self) -> Any:
        """The spec's defaults."""
        return self.params_type()

    def describe_params(self, params: Any | None = None) -> list[dict[str, Any]]:
        """Name, value, unit and help of every parameter (defaults when ``params`` is None)."""
        p = self.default_params() if params is None else params
        return [
            {
                "name": f.name,
                "value": getattr(p, f.name),
                "unit": f.metadata.get("unit", ""),
                "help": f.metadata.get("help", ""),
            }
            for f in fields(self.params_type)
        ]


MODELS: dict[str, ModelSpec] = {
    spec.name: spec
    for spec in (
        ModelSpec(
            name="current_distance",
            title="Current distance",
            family="distance",
            paper_ref="eq. 3-4, Sec. III-A",
            complexity="O(1)",
            params_type=distance.CurrentDistanceParams,
            fn=distance.current_distance,
            label="current distance",
            color="tab:blue",
        ),
        ModelSpec(
            name="path_distance",
            title="Path distance",
            family="distance",
            paper_ref="eq. 5, Sec. III-A",
            complexity="O(p^2)",
            params_type=distance.PathDistanceParams,
            fn=distance.path_distance,
            label="path distance",
            color="tab:orange",
        ),
        ModelSpec(
            name="trajectory_distance",
            title="Trajectory distance (dynamic horizon)",
            family="distance",
            paper_ref="eq. 12, Sec. III-D",
            complexity="O(p^2)",
            params_type=distance.TrajectoryDistanceParams,
            fn=distance.trajectory_distance,
            label="trajectory distance",
            color="tab:green",
        ),
        ModelSpec(
            name="closest_encounter",
            title="Closest encounter",
            family="time",
            paper_ref="eq. 6-7, Sec. III-B",
            complexity="O(n)",
            params_type=temporal.ClosestEncounterParams,
            fn=temporal.closest_encounter,
            label="closest encounter",
            color="tab:red",
        ),
        ModelSpec(
            name="headway",
            title="Closest encounter + headway",
            family="time",
            paper_ref="eq. 7-8, Sec. III-B",
            complexity="O(n + p)",
            params_type=temporal.HeadwayParams,
            fn=temporal.headway,
            label="closest encounter + headway",
            color="tab:purple",
        ),
        ModelSpec(
            name="headway_2d",
            title="Closest encounter + 2D headway",
            family="time",
            paper_ref="eq. 8, Sec. III-B",
            complexity="O(n + p^2)",
            params_type=temporal.Headway2DParams,
            fn=temporal.headway_2d,
            label="closest encounter + 2D headway",
            color="tab:brown",
        ),
        ModelSpec(
            name="circles",
            title="Circle approximation",
            family="stochastic",
            paper_ref="eq. 9, Sec. III-C",
            complexity="O(k n)",
            params_type=stochastic.CirclesParams,
            fn=stochastic.circles,
            label="circles",
            color="tab:pink",
        ),
        ModelSpec(
            name="gaussian",
            title="2D Gaussians",
            family="stochastic",
            paper_ref="eq. 10, Sec. III-C",
            complexity="O(n)",
            params_type=stochastic.GaussianParams,
            fn=stochastic.gaussian,
            label="2D Gaussians",
            color="tab:gray",
            risk_range=(0.0, math.inf),
            unit="1/m^2",
        ),
        ModelSpec(
            name="survival",
            title="Survival analysis",
            family="stochastic",
            paper_ref="eq. 11, Sec. III-C",
            complexity="O(n)",
            params_type=stochastic.SurvivalParams,
            fn=stochastic.survival,
            label="survival analysis",
            color="tab:olive",
        ),
    )
}

#: The model whose thresholded set is the ground truth of the ROC curves (paper Sec. IV-B).
BASELINE_MODEL = "survival"
#: An agent is important when its survival risk is at least this (paper Sec. IV-B). The
#: default of every ``threshold`` argument; pass another value to study its influence.
BASELINE_THRESHOLD = 1e-25

#: The compiled kernel, loaded when a model first runs (risk/kernel.py); that
#: ``kernel.SLOTS`` lists MODELS in this order is tested (tests/test_kernel.py).
kernel = lazy_module("risk.kernel")


def baseline_mask(risks: np.ndarray, threshold: float = BASELINE_THRESHOLD) -> np.ndarray:
    """Important agents ``(N,)`` bool: ``risk >= threshold``; False for NaN."""
    r = np.asarray(risks, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return r >= threshold


def resolve_models(models: Iterable[str] | str | None) -> list[str]:
    """Model names in request order without repeats (all nine when None).

    Raises UnknownModelError for a name that is not in :data:`MODELS`.
    """
    if models is None:
        return list(MODELS)
    if isinstance(models, str):
        models = [models]
    names: list[str] = []
    for name in models:
        if name not in MODELS:
            raise UnknownModelError(str(name), list(MODELS))
        if name not in names:
            names.append(name)
    return names


_DEFAULTS: dict[str, Any] = {name: spec.default_params() for name, spec in MODELS.items()}


def resolve_params(params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Parameter objects for every model: the given ones, defaults for the rest."""
    if not params:
        return dict(_DEFAULTS)
    given = dict(params)
    for name, value in given.items():
        if name not in MODELS:
            raise UnknownModelError(str(name), list(MODELS))
        expected = MODELS[name].params_type
        if not isinstance(value, expected):
            raise RiskError(
                f"parameters for {name!r} must be a {expected.__name__}, got {type(value).__name__}"
            )
    return {name: given.get(name, default) for name, default in _DEFAULTS.items()}


def resolve_prediction(prediction: PredictionSettings | None) -> PredictionSettings:
    """``prediction`` checked, or the defaults when None."""
    if prediction is None:
        return _DEFAULT_PREDICTION
    if not isinstance(prediction, PredictionSettings):
        raise RiskError(f"prediction must be a PredictionSettings, got {type(prediction).__name__}")
    return prediction


_DEFAULT_PREDICTION = PredictionSettings()


def kernel_settings(prediction: PredictionSettings) -> tuple[np.ndarray, np.ndarray]:
    """Read-only steps ``(n,)`` and uncertainty table ``(4, 8)`` of ``prediction`` (cached
    on the immutable settings object)."""
    cached = prediction.__dict__.get("_kernel")
    if cached is None:
        steps = prediction.steps_s
        unc = prediction.uncertainty.as_array()
        steps.flags.writeable = False
        unc.flags.writeable = False
        cached = (steps, unc)
        object.__setattr__(prediction, "_kernel", cached)
    return cached


_PACKED: dict[tuple[int, ...], tuple[Any, np.ndarray, np.ndarray]] = {}


def kernel_params(
    chosen: Mapping[str, Any], settings: PredictionSettings
) -> tuple[np.ndarray, np.ndarray]:
    """The kernel's parameter vectors, cached by the identity of the (immutable) parameter
    objects; the cache holds them, so an identity is never reused while cached."""
    objects = (*chosen.values(), settings)
    key = tuple(map(id, objects))
    hit = _PACKED.get(key)
    if hit is None:
        if len(_PACKED) > 256:
            _PACKED.clear()
        fp, ip = kernel.pack_params(chosen, settings.horizon_s, settings.dt_s)
        hit = _PACKED[key] = (objects, fp, ip)
    return hit[1], hit[2]


def kernel_inputs(
    params: Mapping[str, Any] | None, prediction: PredictionSettings | None
) -> tuple[Mapping[str, Any], PredictionSettings, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every model's parameter objects, the prediction settings and the kernel's arrays
    (steps, uncertainties, parameter vectors) for ``params`` and ``prediction``; resolved
    once per process for the defaults (both None), the usual call (then the parameter
    mapping is read-only: it is shared)."""
    if params is None and prediction is None:
        return _default_kernel_inputs()
    return _resolve_kernel_inputs(params, prediction)


def _resolve_kernel_inputs(
    params: Mapping[str, Any] | None, prediction: PredictionSettings | None
) -> tuple[dict[str, Any], PredictionSettings, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    chosen = resolve_params(params)
    settings = resolve_prediction(prediction)
    steps, unc = kernel_settings(settings)
    fp, ip = kernel_params(chosen, settings)
    return chosen, settings, steps, unc, fp, ip


@functools.cache
def _default_kernel_inputs() -> tuple[
    Mapping[str, Any], PredictionSettings, np.ndarray, np.ndarray, np.ndarray, np.ndarray
]:
    chosen, settings, steps, unc, fp, ip = _resolve_kernel_inputs(None, None)
    return types.MappingProxyType(chosen), settings, steps, unc, fp, ip


@functools.lru_cache(maxsize=256)
def _want(names: tuple[str, ...]) -> np.ndarray:
    want = np.zeros(kernel.N_MODELS, dtype=np.bool_)
    for name in names:
        want[kernel.SLOTS.index(name)] = True
    want.flags.writeable = False
    return want


def evaluate(
    frame: Frame,
    models: Iterable[str] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    prediction: PredictionSettings | None = None,
) -> dict[str, np.ndarray]:
    """Every requested model's risk for every agent of ``frame``.

    ``models``: names from :data:`MODELS` (None = all nine, in registry order);
    ``params``: model name -> that model's parameter object (missing = defaults);
    ``prediction``: horizon, step and uncertainty table (None = defaults).

    Returns name -> ``(N,)`` float64 in frame order, NaN for the ego and invalid agents.
    Computed by the compiled kernel (:mod:`risk.kernel`) in one pass per agent row: the
    shared work (extended paths, prediction, covariances) is done once per row and
    reused by every requested model.
    """
    names = resolve_models(models)
    _, _, steps, unc, fp, ip = kernel_inputs(params, prediction)
    out = kernel.run(frame, _want(tuple(names)), fp, ip, steps, unc)
    return {name: out[kernel.SLOTS.index(name)] for name in names}


def evaluate_numpy(
    frame: Frame,
    models: Iterable[str] | None = None,
    params: Mapping[str, Any] | None = None,
    *,
    prediction: PredictionSettings | None = None,
) -> dict[str, np.ndarray]:
    """:func:`evaluate` computed by the vectorised numpy modules (``ModelSpec.fn``).

    Not the production path: the oracle that the compiled kernel is tested against, with
    the plain-loop :func:`risk.reference.reference_evaluate`.
    """
    names = resolve_models(models)
    chosen = resolve_params(params)
    ctx = FrameContext(frame, resolve_prediction(prediction))
    return {name: MODELS[name].fn(ctx, chosen[name]) for name in names}
