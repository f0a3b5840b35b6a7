"""The registry of the nine risk models and :func:`evaluate`, the one entry point.

Code that uses models (replay, cascade, calibration, ROC, recordings) iterates over
:data:`MODELS` and never special-cases a model by name.

Paper references count equations and sections as the paper source
(``../shared/paper/*.tex``) compiles: the TPR/FPR pair is eq. 1-2 and the models are in
Sec. III. (The model spec, ``../shared/docs/risk-models.md``, numbers some of them
differently.)
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any, Literal

import numpy as np

from risk import distance, stochastic, temporal
from risk.errors import RiskError, UnknownModelError
from risk.frame import Frame
from risk.prediction import FrameContext, PredictionSettings

Family = Literal["distance", "time", "stochastic"]
ModelFn = Callable[[FrameContext, Any], np.ndarray]


@dataclass(frozen=True)
class ModelSpec:
    """One risk model: how to call it and how to describe it.

    ``fn(ctx, params)`` returns ``(N,)`` float64 risks, higher = riskier, NaN for the ego
    and invalid agents; ``params`` is an instance of ``params_type`` (a frozen dataclass).
    """

    name: str
    title: str
    family: Family
    paper_ref: str
    complexity: str
    params_type: type
    fn: ModelFn
    unit: str = ""  # unit of the risk value ("" = dimensionless)

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
            "current_distance",
            "Current distance",
            "distance",
            "eq. 3-4, Sec. III-A",
            "O(1)",
            distance.CurrentDistanceParams,
            distance.current_distance,
        ),
        ModelSpec(
            "path_distance",
            "Path distance",
            "distance",
            "eq. 5, Sec. III-A",
            "O(p^2)",
            distance.PathDistanceParams,
            distance.path_distance,
        ),
        ModelSpec(
            "trajectory_distance",
            "Trajectory distance (dynamic horizon)",
            "distance",
            "eq. 12, Sec. III-D",
            "O(p^2)",
            distance.TrajectoryDistanceParams,
            distance.trajectory_distance,
        ),
        ModelSpec(
            "closest_encounter",
            "Closest encounter",
            "time",
            "eq. 6-7, Sec. III-B",
            "O(n)",
            temporal.ClosestEncounterParams,
            temporal.closest_encounter,
        ),
        ModelSpec(
            "headway",
            "Closest encounter + headway",
            "time",
            "eq. 7-8, Sec. III-B",
            "O(n + p)",
            temporal.HeadwayParams,
            temporal.headway,
        ),
        ModelSpec(
            "headway_2d",
            "Closest encounter + 2D headway",
            "time",
            "eq. 8, Sec. III-B",
            "O(n + p^2)",
            temporal.Headway2DParams,
            temporal.headway_2d,
        ),
        ModelSpec(
            "circles",
            "Circle approximation",
            "stochastic",
            "eq. 9, Sec. III-C",
            "O(k n)",
            stochastic.CirclesParams,
            stochastic.circles,
        ),
        ModelSpec(
            "gaussian",
            "2D Gaussians",
            "stochastic",
            "eq. 10, Sec. III-C",
            "O(n)",
            stochastic.GaussianParams,
            stochastic.gaussian,
            unit="1/m^2",
        ),
        ModelSpec(
            "survival",
            "Survival analysis",
            "stochastic",
            "eq. 11, Sec. III-C",
            "O(n)",
            stochastic.SurvivalParams,
            stochastic.survival,
        ),
    )
}

#: The model whose thresholded set is the ground truth of the ROC curves (paper Sec. IV-B).
BASELINE_MODEL = "survival"
#: An agent is important when its survival risk is at least this (paper Sec. IV-B).
BASELINE_THRESHOLD = 1e-25


def baseline_mask(risks: np.ndarray) -> np.ndarray:
    """Important agents ``(N,)`` bool: ``risk >= BASELINE_THRESHOLD``; False for NaN."""
    r = np.asarray(risks, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return r >= BASELINE_THRESHOLD


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


def resolve_params(params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Parameter objects for every model: the given ones, defaults for the rest."""
    given = dict(params or {})
    for name, value in given.items():
        if name not in MODELS:
            raise UnknownModelError(str(name), list(MODELS))
        expected = MODELS[name].params_type
        if not isinstance(value, expected):
            raise RiskError(
                f"parameters for {name!r} must be a {expected.__name__}, got {type(value).__name__}"
            )
    return {name: given.get(name, spec.default_params()) for name, spec in MODELS.items()}


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
    Shared work (extended paths, predictions, covariances, pairwise overlaps) is computed
    once per call and reused by every model.
    """
    names = resolve_models(models)
    chosen = resolve_params(params)
    if prediction is not None and not isinstance(prediction, PredictionSettings):
        raise RiskError(f"prediction must be a PredictionSettings, got {type(prediction).__name__}")
    ctx = FrameContext(frame, prediction)
    return {name: MODELS[name].fn(ctx, chosen[name]) for name in names}
