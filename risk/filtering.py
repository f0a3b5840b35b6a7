"""The filter's answer for one frame, by agent id: what a planner stack consumes.

A *filter* decides which of a frame's other agents a planner gets. Five kinds, all behind
one small interface (:class:`Filter`: a ``name`` and ``apply(frame) -> FilterResult``):

- ``none``: every valid other agent (the planner's reference: nothing dropped);
- ``cascade``: the paper's cascade (:func:`risk.cascade.run_cascade`): cheap stages, then
  survival analysis sorts the survivors into planner tiers; ``cascade:NAME`` a shipped
  cascade by name (``cascade:planner``, ``cascade:survival``;
  :data:`risk.cascade.NAMED_CASCADES`);
- ``nearest:K``: the K agents nearest to the ego (centre distance), as learned planners
  keep their 32-64 nearest;
- ``radius:R``: every agent whose centre lies within R metres of the ego's, as nuPlan's
  IDM planner does;
- ``model:NAME[:THRESHOLD]``: one risk model at a threshold (default: the threshold of
  that model's stage in the cascade file, i.e. the calibrated one).

:func:`filter_frame` is the notebook's entry point for the cascade; ``replay run`` and
``replay plan`` call the same code (:class:`CascadeFilter`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from risk.cascade import NAMED_CASCADES, CascadeConfig, CascadeResult, run_cascade
from risk.errors import RiskError
from risk.frame import Frame
from risk.registry import MODELS
from risk.registry import evaluate as risk_evaluate

#: The forms ``parse_filter`` understands, for help texts and error messages.
FILTER_FORMS = ("none", "cascade[:NAME]", "nearest:K", "radius:R", "model:NAME[:THRESHOLD]")

#: Why an agent was dropped by a filter other than the cascade's stages.
REACHABILITY = "reachability"
#: ... and by the corridor stage (a follower that cannot reach the ego).
CORRIDOR = "corridor"


class FilterSpecError(RiskError):
    """A filter spec that ``parse_filter`` cannot read; the message lists the valid forms."""

    def __init__(self, spec: str, problem: str) -> None:
        self.spec = spec
        super().__init__(
            f"--filter {spec!r}: {problem}; valid forms: {', '.join(FILTER_FORMS)} "
            "(e.g. nearest:32, radius:50, model:gaussian)"
        )


@dataclass(frozen=True, eq=False)
class FilterResult:
    """What a filter keeps of one frame, by agent id.

    ``kept_ids`` ``(K,)`` int64: the agents the planner gets, most important first where
    the filter ranks them (the cascade: by survival risk; nearest: by distance).
    ``tiers``: tier name -> ids that reached it (nested; the cascade's planner tiers, one
    tier ``"kept"`` for the other filters). ``dropped``: agent id -> the stage or rule
    that dropped it. ``time_ms``: the filter's own compute time (for the cascade, the
    reachability bound, its stages and the tier sort, without the survival-on-all
    comparison that ``replay run`` reports beside it).
    """

    filter_name: str
    t_s: float
    ego_id: int
    kept_ids: np.ndarray
    tiers: Mapping[str, tuple[int, ...]]
    dropped: Mapping[int, str]
    time_ms: float
    n_others: int
    cascade: CascadeResult | None = field(default=None, repr=False)

    @property
    def n_kept(self) -> int:
        return int(self.kept_ids.size)

    def dropped_by(self) -> dict[str, int]:
        """How many agents each stage or rule dropped."""
        counts: dict[str, int] = {}
        for stage in self.dropped.values():
            counts[stage] = counts.get(stage, 0) + 1
        return counts

    def __repr__(self) -> str:
        tiers = ", ".join(f"{name} {len(ids)}" for name, ids in self.tiers.items())
        dropped = ", ".join(f"{name} {n}" for name, n in self.dropped_by().items()) or "none"
        return (
            f"FilterResult({self.filter_name}, t={self.t_s:g} s, ego {self.ego_id}: kept "
            f"{self.n_kept} of {self.n_others} ({tiers}); dropped by {dropped}; "
            f"{self.time_ms:.3g} ms)"
        )


class Filter(Protocol):
    """A rule that picks the agents a planner gets from one frame."""

    @property
    def name(self) -> str: ...

    def apply(self, frame: Frame) -> FilterResult: ...


def _others(frame: Frame) -> np.ndarray:
    return np.flatnonzero(frame.others)


def _result(
    name: str,
    frame: Frame,
    kept: np.ndarray,
    dropped: np.ndarray,
    why: str,
    elapsed_s: float,
) -> FilterResult:
    kept_ids = frame.ids[kept].astype(np.int64)
    return FilterResult(
        filter_name=name,
        t_s=float(frame.t),
        ego_id=frame.ego_id,
        kept_ids=kept_ids,
        tiers={"kept": tuple(int(i) for i in kept_ids)},
        dropped=dict.fromkeys((int(i) for i in frame.ids[dropped]), why),
        time_ms=elapsed_s * 1e3,
        n_others=int(frame.others.sum()),
    )


def _centre_distances(frame: Frame, others: np.ndarray) -> np.ndarray:
    d = frame.xy[others] - frame.xy[frame.ego]
    return np.hypot(d[:, 0], d[:, 1])


@dataclass(frozen=True)
class KeepAll:
    """Every valid other agent: what the planner gets without a filter."""

    name: str = "none"

    def apply(self, frame: Frame) -> FilterResult:
        start = time.perf_counter()
        others = _others(frame)
        return _result(self.name, frame, others, others[:0], "", time.perf_counter() - start)


@dataclass(frozen=True)
class NearestFilter:
    """The ``k`` agents nearest to the ego by centre distance (ties: lower index first)."""

    k: int
    name: str = ""

    def __post_init__(self) -> None:
        if self.k < 0:
            raise FilterSpecError(f"nearest:{self.k}", "K must be 0 or more")
        if not self.name:
            object.__setattr__(self, "name", f"nearest:{self.k}")

    def apply(self, frame: Frame) -> FilterResult:
        start = time.perf_counter()
        others = _others(frame)
        order = np.argsort(_centre_distances(frame, others), kind="stable")
        kept, dropped = others[order[: self.k]], others[order[self.k :]]
        return _result(self.name, frame, kept, dropped, self.name, time.perf_counter() - start)


@dataclass(frozen=True)
class RadiusFilter:
    """Every agent whose centre lies within ``radius_m`` of the ego's (nearest first)."""

    radius_m: float
    name: str = ""

    def __post_init__(self) -> None:
        if not (self.radius_m >= 0 and math.isfinite(self.radius_m)):
            raise FilterSpecError(f"radius:{self.radius_m}", "R must be a finite number >= 0")
        if not self.name:
            object.__setattr__(self, "name", f"radius:{self.radius_m:g}")

    def apply(self, frame: Frame) -> FilterResult:
        start = time.perf_counter()
        others = _others(frame)
        d = _centre_distances(frame, others)
        order = np.argsort(d, kind="stable")
        inside = d[order] <= self.radius_m
        kept, dropped = others[order[inside]], others[order[~inside]]
        return _result(self.name, frame, kept, dropped, self.name, time.perf_counter() - start)


@dataclass(frozen=True)
class ModelFilter:
    """One risk model: keep an agent when its risk reaches ``threshold`` (riskiest first)."""

    model: str
    threshold: float
    params: Mapping[str, Any] | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise FilterSpecError(
                f"model:{self.model}", f"unknown model; models: {', '.join(MODELS)}"
            )
        if not self.name:
            object.__setattr__(self, "name", f"model:{self.model}")

    def apply(self, frame: Frame) -> FilterResult:
        start = time.perf_counter()
        others = _others(frame)
        risk = risk_evaluate(frame, models=[self.model], params=self.params)[self.model][others]
        order = np.argsort(-risk, kind="stable")
        keep = risk[order] >= self.threshold
        kept, dropped = others[order[keep]], others[order[~keep]]
        return _result(self.name, frame, kept, dropped, self.model, time.perf_counter() - start)


@dataclass(frozen=True)
class CascadeFilter:
    """The paper's cascade: the agents kept by every stage, sorted by survival risk.

    ``baseline``: also run survival analysis on every agent (the result's ``baseline``
    and ``false_negatives``, which the answer does not use). Off by default: it is not
    part of the filter, and it cost as much again as the filter itself.

    ``tiers``: sort the survivors into the config's planner tiers, which takes survival
    analysis of every survivor. False for a planner that reads only the kept agents
    (``replay plan``'s planners): the same kept agents, no tiers, in the order of the
    frame, for about half the time."""

    config: CascadeConfig = field(default_factory=CascadeConfig.default)
    name: str = "cascade"
    baseline: bool = False
    tiers: bool = True

    @functools.cached_property
    def _prepared(self) -> tuple[CascadeConfig, Mapping[str, Any] | None, Any]:
        """The config to run (without tiers when not wanted), and the parameters and
        prediction it names, parsed once per filter."""
        named = self.config.model_settings()
        config = self.config if self.tiers else dataclasses.replace(self.config, tiers=())
        return config, named.params_or_none(), named.prediction_or_none()

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state.pop("_prepared", None)  # prepared again where it is unpickled
        return state

    def apply(self, frame: Frame) -> FilterResult:
        config, params, prediction = self._prepared
        result = run_cascade(
            frame, config, params=params, prediction=prediction, baseline=self.baseline
        )
        return cascade_answer(frame, result, config, self.name)


def cascade_answer(
    frame: Frame, result: CascadeResult, config: CascadeConfig, name: str = "cascade"
) -> FilterResult:
    """The by-id answer of a cascade run on ``frame`` (what ``replay run`` exports)."""
    kept = np.flatnonzero(result.kept[-1]) if result.kept.shape[0] else _others(frame)
    risk = result.survival[kept]
    order = np.argsort(-np.where(np.isnan(risk), -np.inf, risk), kind="stable")
    kept = kept[order]
    kept_tier = result.tier[kept]
    kept_ids = frame.ids[kept].astype(np.int64)
    tiers = {
        tier.name: tuple(kept_ids[kept_tier >= k].tolist()) for k, tier in enumerate(config.tiers)
    }
    dropped_idx = np.flatnonzero(result.dropped_at >= 0)
    # Why each was dropped, as an index into the stage names, then the bound and the
    # corridor (which both leave dropped_at = 0): one vectorised pick, no loop per agent.
    names = (*result.stage_names, REACHABILITY, CORRIDOR)
    why = result.dropped_at[dropped_idx].astype(np.intp)
    if result.behind is not None:
        why[result.behind[dropped_idx]] = len(names) - 1
    if result.unreachable is not None:
        why[result.unreachable[dropped_idx]] = len(names) - 2
    dropped = dict(
        zip(frame.ids[dropped_idx].tolist(), np.asarray(names, object)[why].tolist(), strict=True)
    )
    own_s = (
        result.corridor_time_s
        + result.reach_time_s
        + float(result.stage_time_s.sum())
        + result.sort_time_s
    )
    return FilterResult(
        filter_name=name,
        t_s=float(frame.t),
        ego_id=frame.ego_id,
        kept_ids=kept_ids,
        tiers=tiers,
        dropped=dropped,
        time_ms=own_s * 1e3,
        n_others=int(frame.others.sum()),
        cascade=result,
    )


def filter_frame(frame: Frame, cascade: CascadeConfig | None = None) -> FilterResult:
    """The cascade's answer for one frame: kept ids by tier, dropped ids by stage, time.

    ``cascade``: stages, thresholds and tiers (default: the calibrated cascade shipped
    with riskreplay, ``CascadeConfig.default()``).
    """
    return CascadeFilter(CascadeConfig.default() if cascade is None else cascade).apply(frame)


def parse_filter(spec: str, cascade: CascadeConfig | None = None, *, tiers: bool = True) -> Filter:
    """A filter from its text form (:data:`FILTER_FORMS`).

    ``cascade`` is the cascade of ``cascade`` and where ``model:NAME`` finds its
    calibrated threshold (the threshold of NAME's stage). ``tiers``: whether a cascade
    filter sorts its survivors into tiers (see :class:`CascadeFilter`).
    """
    config = CascadeConfig.default() if cascade is None else cascade
    text = spec.strip()
    kind, _, arg = text.partition(":")
    if kind == "none" and not arg:
        return KeepAll()
    if kind == "cascade" and not arg:
        return CascadeFilter(config, tiers=tiers)
    if kind == "cascade":
        if arg not in NAMED_CASCADES:
            raise FilterSpecError(
                spec, f"no shipped cascade {arg!r}; named: {', '.join(NAMED_CASCADES)}"
            )
        return CascadeFilter(CascadeConfig.named(arg), name=text, tiers=tiers)
    if kind == "nearest":
        try:
            k = int(arg)
        except ValueError:
            raise FilterSpecError(spec, "K must be a whole number") from None
        return NearestFilter(k)
    if kind == "radius":
        try:
            radius = float(arg)
        except ValueError:
            raise FilterSpecError(spec, "R must be a number of metres") from None
        return RadiusFilter(radius)
    if kind == "model" and arg:
        model, _, threshold_text = arg.partition(":")
        if model not in MODELS:
            raise FilterSpecError(spec, f"unknown model {model!r}; models: {', '.join(MODELS)}")
        named = config.model_settings()
        params = named.params_or_none()
        if threshold_text:
            try:
                threshold = float(threshold_text)
            except ValueError:
                raise FilterSpecError(spec, "THRESHOLD must be a number") from None
            if math.isnan(threshold):
                raise FilterSpecError(spec, "THRESHOLD must not be NaN")
            return ModelFilter(model, threshold, params)
        stages = {stage.model: stage.threshold for stage in config.stages}
        if model not in stages:
            raise FilterSpecError(
                spec,
                f"the cascade has no calibrated threshold for {model} (its stages: "
                f"{', '.join(stages) or 'none'}); give one as model:{model}:THRESHOLD",
            )
        return ModelFilter(model, stages[model], params)
    raise FilterSpecError(spec, "not a filter")
