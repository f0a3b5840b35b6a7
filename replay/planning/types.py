"""The planner interface: what a planner is given and what it returns.

Structure of arrays, numpy, units in the names. ``K`` agents, ``T`` forecast times, ``P``
reference points. Frozen dataclasses: build once, trust afterwards (shapes are checked at
construction, values are not).

- :class:`EgoState`: the ego now.
- :class:`AgentForecasts`: the other agents' predicted boxes over shared times.
- :class:`PlanRequest`: everything one planner call needs.
- :class:`Plan`: what it returns (a trajectory on the request's time grid, or a failure
  with its reason).
- :class:`Planner`: the protocol every planner implements (``plan``, ``may_matter``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Protocol, runtime_checkable

import numpy as np

#: Speed below which a plan counts as stopped (m/s).
STOP_SPEED_MPS = 0.5


def _shape(name: str, a: np.ndarray, shape: tuple[int | None, ...]) -> None:
    ok = a.ndim == len(shape) and all(
        s is None or s == d for s, d in zip(shape, a.shape, strict=False)
    )
    if not ok:
        want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {a.shape}")


@dataclass(frozen=True, eq=False, kw_only=True)
class EgoState:
    """The ego now: centre ``xy`` (2,) in m, heading in rad (counter-clockwise from +x),
    speed and acceleration along its path, box size; ``steer_rad``: its front-wheel
    steering angle when known (a closed loop's tracked vehicle), else None (a planner that
    simulates the ego then assumes it follows its path's curvature)."""

    xy: np.ndarray  # (2,) float64, m
    heading_rad: float
    speed_mps: float
    accel_mps2: float = 0.0
    length_m: float = 4.5
    width_m: float = 1.8
    steer_rad: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "xy", np.asarray(self.xy, dtype=np.float64))
        _shape("EgoState.xy", self.xy, (2,))


@dataclass(frozen=True, eq=False, kw_only=True)
class AgentForecasts:
    """Predicted boxes of ``K`` agents at ``T`` shared times (structure of arrays).

    ``times_s`` (T,) s from now (``times_s[0] == 0``: the present); ``xy`` (K, T, 2) m,
    predicted box centres; ``heading_rad`` (K, T); ``length_m``, ``width_m`` (K,) m;
    ``ids`` (K,) int64 agent ids; ``kinds`` (K,) int8 :class:`risk.Kind` codes.
    ``speed_mps`` (K,) m/s or None: each agent's speed now, along ``heading_rad[:, 0]``
    (what a constant-velocity forecast needs; :func:`replay.planning.inputs.forecasts_for`
    fills it, None where a caller does not know it).
    """

    ids: np.ndarray  # (K,) int64
    kinds: np.ndarray  # (K,) int8
    length_m: np.ndarray  # (K,) float64, m
    width_m: np.ndarray  # (K,) float64, m
    times_s: np.ndarray  # (T,) float64, s
    xy: np.ndarray  # (K, T, 2) float64, m
    heading_rad: np.ndarray  # (K, T) float64, rad
    speed_mps: np.ndarray | None = None  # (K,) float64, m/s: the speed now

    def __post_init__(self) -> None:
        if self.speed_mps is not None:
            object.__setattr__(self, "speed_mps", np.asarray(self.speed_mps, dtype=np.float64))
        for name, dtype in (
            ("ids", np.int64),
            ("kinds", np.int8),
            ("length_m", np.float64),
            ("width_m", np.float64),
            ("times_s", np.float64),
            ("xy", np.float64),
            ("heading_rad", np.float64),
        ):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=dtype))
        k = self.ids.shape[0] if self.ids.ndim == 1 else -1
        _shape("AgentForecasts.ids", self.ids, (None,))
        _shape("AgentForecasts.times_s", self.times_s, (None,))
        t = self.times_s.shape[0]
        for name in ("kinds", "length_m", "width_m"):
            _shape(f"AgentForecasts.{name}", getattr(self, name), (k,))
        _shape("AgentForecasts.xy", self.xy, (k, t, 2))
        _shape("AgentForecasts.heading_rad", self.heading_rad, (k, t))
        if self.speed_mps is not None:
            _shape("AgentForecasts.speed_mps", self.speed_mps, (k,))

    @property
    def n(self) -> int:
        """Number of agents ``K``."""
        return int(self.ids.shape[0])

    def subset(self, which: np.ndarray) -> AgentForecasts:
        """The agents selected by a boolean mask (K,) or an index array, in that order."""
        sel = np.asarray(which)
        if sel.dtype == bool:
            _shape("subset mask", sel, (self.n,))
        return AgentForecasts(
            ids=self.ids[sel],
            kinds=self.kinds[sel],
            length_m=self.length_m[sel],
            width_m=self.width_m[sel],
            times_s=self.times_s,
            xy=self.xy[sel],
            heading_rad=self.heading_rad[sel],
            speed_mps=None if self.speed_mps is None else self.speed_mps[sel],
        )

    def on_times(self, times_s: np.ndarray) -> AgentForecasts:
        """The forecasts at other times (T',): linear in position and heading, held at
        the first / last forecast outside their span. Returns ``self`` when the times are
        the same."""
        new = np.asarray(times_s, dtype=np.float64)
        if new.shape == self.times_s.shape and np.allclose(new, self.times_s):
            return self
        old = self.times_s
        j = np.clip(np.searchsorted(old, new, side="right") - 1, 0, max(old.size - 2, 0))
        j1 = np.minimum(j + 1, old.size - 1)
        span = old[j1] - old[j]
        w = np.clip(np.where(span > 0, (new - old[j]) / np.where(span > 0, span, 1.0), 0.0), 0, 1)
        heading = np.unwrap(self.heading_rad, axis=1)
        return AgentForecasts(
            ids=self.ids,
            kinds=self.kinds,
            length_m=self.length_m,
            width_m=self.width_m,
            times_s=new,
            xy=self.xy[:, j] * (1 - w)[None, :, None] + self.xy[:, j1] * w[None, :, None],
            heading_rad=heading[:, j] * (1 - w)[None, :] + heading[:, j1] * w[None, :],
            speed_mps=self.speed_mps,
        )

    @classmethod
    def empty(cls, times_s: np.ndarray) -> AgentForecasts:
        """No agents, on the time grid ``times_s`` (T,)."""
        t = np.asarray(times_s, dtype=np.float64)
        return cls(
            ids=np.zeros(0, np.int64),
            kinds=np.zeros(0, np.int8),
            length_m=np.zeros(0),
            width_m=np.zeros(0),
            times_s=t,
            xy=np.zeros((0, t.size, 2)),
            heading_rad=np.zeros((0, t.size)),
        )


@dataclass(frozen=True, eq=False, kw_only=True)
class PlanRequest:
    """One planner call.

    ``reference`` (P, 2) m: the ego's reference path, a polyline that starts at (or near)
    the ego, runs in its driving direction and is long enough for the horizon.
    ``lanes_left`` / ``lanes_right``: usable lanes parallel to the reference lane, each
    ``lane_width_m`` wide, beside it. ``agents``: the agents the planner may see (a
    filter's choice), forecast on the times ``0, dt_s, ..., horizon_s``.
    """

    ego: EgoState
    reference: np.ndarray  # (P, 2) float64, m
    target_speed_mps: float
    agents: AgentForecasts
    lane_width_m: float = 3.5
    lanes_left: int = 0
    lanes_right: int = 0
    horizon_s: float = 5.0
    dt_s: float = 0.1

    def __post_init__(self) -> None:
        object.__setattr__(self, "reference", np.asarray(self.reference, dtype=np.float64))
        _shape("PlanRequest.reference", self.reference, (None, 2))

    @property
    def times_s(self) -> np.ndarray:
        """The plan's time grid ``0, dt_s, ..., horizon_s`` (T,) in s."""
        return plan_times(self.horizon_s, self.dt_s)

    def with_agents(self, agents: AgentForecasts) -> PlanRequest:
        """The same request with another set of agents (e.g. a filter's choice)."""
        return replace(self, agents=agents)


def plan_times(horizon_s: float, dt_s: float) -> np.ndarray:
    """Times ``0, dt, ..., horizon`` (T,) in s; the horizon is rounded to whole steps."""
    steps = round(horizon_s / dt_s)
    return np.arange(steps + 1) * dt_s


@dataclass(frozen=True, eq=False, kw_only=True)
class Plan:
    """A planner's answer.

    ``times_s`` (T,) s, ``xy`` (T, 2) m, ``heading_rad`` (T,), ``speed_mps`` (T,): the
    planned trajectory on the request's times ``0, dt_s, ...`` (empty arrays when ``ok``
    is False). It may end before the horizon: fiss-planner samples end times from 3 s up
    to the horizon, and its plan is not continued beyond its own end. ``plan_ms``: wall time of the
    planner call. ``lane``: the lane the plan ends in, 0 = the reference lane, +1 one lane
    to the left, -1 one to the right. ``stops``: the plan comes to a stop (speed below
    STOP_SPEED_MPS) within the horizon. ``blocking_id``: the agent that constrained the
    plan, -1 when none or not reported. ``reason``: "" when ok, else why not.
    ``sole_constraints``: the ids of the agents without which this very plan could differ
    (for every other agent, the plan with all agents but that one is provably the same);
    None when the planner does not report it. Planner truth plans counterfactually only
    for these (:func:`replay.planning.truth.planner_truth`).
    """

    ok: bool
    times_s: np.ndarray  # (T,) float64, s
    xy: np.ndarray  # (T, 2) float64, m
    heading_rad: np.ndarray  # (T,) float64, rad
    speed_mps: np.ndarray  # (T,) float64, m/s
    plan_ms: float
    lane: int = 0
    stops: bool = False
    blocking_id: int = -1
    reason: str = ""
    extras: dict[str, float] = field(default_factory=dict)  # planner-specific numbers
    sole_constraints: np.ndarray | None = None  # (J,) int64 agent ids, or None

    def __post_init__(self) -> None:
        for name in ("times_s", "xy", "heading_rad", "speed_mps"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        t = self.times_s.shape[0]
        _shape("Plan.xy", self.xy, (t, 2))
        _shape("Plan.heading_rad", self.heading_rad, (t,))
        _shape("Plan.speed_mps", self.speed_mps, (t,))

    @classmethod
    def failed(cls, reason: str, *, plan_ms: float = 0.0, blocking_id: int = -1) -> Plan:
        """A failed plan: no trajectory, ``ok`` False, with the reason."""
        return cls(
            ok=False,
            times_s=np.zeros(0),
            xy=np.zeros((0, 2)),
            heading_rad=np.zeros(0),
            speed_mps=np.zeros(0),
            plan_ms=plan_ms,
            blocking_id=blocking_id,
            reason=reason,
        )


@runtime_checkable
class Planner(Protocol):
    """A planner: a name, ``plan`` and ``may_matter``.

    ``may_matter(request)`` (K,) bool is False only where the agent provably cannot
    change this planner's plan for this request (each planner documents its argument);
    callers skip the counterfactual "all agents but this one" plan for those agents.
    """

    name: str

    def plan(self, request: PlanRequest) -> Plan: ...

    def may_matter(self, request: PlanRequest) -> np.ndarray: ...


def cold(planner: Planner) -> Planner:
    """``planner`` with any cache of earlier calls dropped (its ``forget()``, where it has
    one), so that the next call's ``plan_ms`` is what that call costs on its own: the
    planner study times the all-agents plan and each filter's plan on the same request,
    and a filtered plan that reused the all-agents plan's projections would look cheaper
    than it is."""
    forget = getattr(planner, "forget", None)
    if callable(forget):
        forget()
    return planner
