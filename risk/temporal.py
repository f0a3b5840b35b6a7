"""Time models: closest encounter, with headway, with 2D headway (paper Sec. III-B).

- Closest encounter: ``d_E = min_s ||x_2(s) - x_1(s)||``, ``s_E = argmin``;
  ``R_E = eps / (eps + d_E)`` if ``s_E < s_max`` else 0 (paper eq. 6-7).
- Headway: ``TH = (l_2 - l_1) / v_1`` for an agent on the ego path, ``R_TH = tau / (tau +
  TH)``; the combined score is ``max(R_E, R_TH)``.
- 2D headway: an agent whose path crosses the ego path is placed on the ego path at the
  crossing's ego arc length minus its own remaining path length to the crossing.

Choices the spec leaves open are marked "Choice:" and listed in docs/models.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from risk import geometry
from risk.distance import check_positive, distance_to_risk, polyline_distance_rows
from risk.errors import RiskError
from risk.prediction import FrameContext


def _check_s_max(owner: str, value: float | None) -> None:
    if value is not None and not (
        isinstance(value, (int, float)) and not math.isnan(value) and value > 0
    ):
        raise RiskError(f"{owner}: encounter_time_max_s must be > 0 or None, got {value!r}")


def _eps() -> float:
    return field(default=1.0, metadata={"help": "distance scale of R = eps/(eps+d)", "unit": "m"})


def _s_max() -> float | None:
    return field(
        default=None,
        metadata={
            "help": "count an encounter only when s_E < this; None = the prediction horizon",
            "unit": "s",
        },
    )


def _tau() -> float:
    return field(default=1.0, metadata={"help": "time scale of R = tau/(tau+TH)", "unit": "s"})


def _tolerance() -> float:
    return field(
        default=1.75,
        metadata={
            "help": "an agent whose centre is within this of the ego path is on it",
            "unit": "m",
        },
    )


@dataclass(frozen=True)
class ClosestEncounterParams:
    """Parameters of the closest encounter model."""

    epsilon_m: float = _eps()
    encounter_time_max_s: float | None = _s_max()

    def __post_init__(self) -> None:
        check_positive("closest_encounter", "epsilon_m", self.epsilon_m)
        _check_s_max("closest_encounter", self.encounter_time_max_s)


@dataclass(frozen=True)
class HeadwayParams:
    """Parameters of closest encounter + headway."""

    epsilon_m: float = _eps()
    encounter_time_max_s: float | None = _s_max()
    tau_s: float = _tau()
    on_path_tolerance_m: float = _tolerance()

    def __post_init__(self) -> None:
        check_positive("headway", "epsilon_m", self.epsilon_m)
        check_positive("headway", "tau_s", self.tau_s)
        check_positive("headway", "on_path_tolerance_m", self.on_path_tolerance_m)
        _check_s_max("headway", self.encounter_time_max_s)


@dataclass(frozen=True)
class Headway2DParams:
    """Parameters of closest encounter + 2D headway."""

    epsilon_m: float = _eps()
    encounter_time_max_s: float | None = _s_max()
    tau_s: float = _tau()
    on_path_tolerance_m: float = _tolerance()

    def __post_init__(self) -> None:
        check_positive("headway_2d", "epsilon_m", self.epsilon_m)
        check_positive("headway_2d", "tau_s", self.tau_s)
        check_positive("headway_2d", "on_path_tolerance_m", self.on_path_tolerance_m)
        _check_s_max("headway_2d", self.encounter_time_max_s)


# ---------------------------------------------------------------------- closest encounter
#: Distances within this of the closest encounter count as reaching it (rounding ties).
TIE_TOLERANCE_M = 1e-9


def encounter_rows(ctx: FrameContext, ego_row: int) -> tuple[np.ndarray, np.ndarray]:
    """Closest encounter of every path row with ego candidate ``ego_row``.

    Returns ``d_E`` ``(M,)`` in m and the step index ``(M,)`` of ``s_E``.

    Choice: ``s_E`` is the first step whose distance is within ``TIE_TOLERANCE_M`` of the
    minimum. Agents at a constant distance (same speed, parallel paths) then meet at
    ``s = 0`` instead of wherever rounding noise puts the smallest value, which could be
    the last step and zero the risk.
    """

    def compute() -> tuple[np.ndarray, np.ndarray]:
        m = ctx.row_agent.size
        d_min, k = np.empty(m), np.empty(m, dtype=np.intp)
        ex, ey = ctx.traj_x[ego_row], ctx.traj_y[ego_row]
        for blk in ctx.row_blocks():
            dx = ctx.traj_x[blk] - ex
            dy = ctx.traj_y[blk] - ey
            dx *= dx
            dy *= dy
            dx += dy  # squared distance (rows, n); sqrt only at the minimum
            d_min[blk] = np.sqrt(dx.min(axis=1))
            k[blk] = np.argmax(dx <= ((d_min[blk] + TIE_TOLERANCE_M) ** 2)[:, None], axis=1)
        return d_min, k

    return ctx.memo(("encounter", int(ego_row)), compute)


def encounter_risk_rows(
    ctx: FrameContext, ego_row: int, epsilon_m: float, s_max: float | None
) -> np.ndarray:
    """``R_E`` ``(M,)`` for ego candidate ``ego_row``: 0 when ``s_E >= s_max``.

    Choice: ``s_max`` defaults to the horizon, so an encounter whose minimum lies on the
    last step (still closing at the horizon) is not counted; ties (within 1e-9 m) go to
    the earliest step.
    """
    d, k = encounter_rows(ctx, ego_row)
    limit = ctx.settings.horizon_s if s_max is None else s_max
    return np.where(ctx.steps_s[k] < limit, distance_to_risk(d, epsilon_m), 0.0)


def closest_encounter_distances(ctx: FrameContext) -> np.ndarray:
    """``d_E`` ``(N,)`` in m, least over candidate pairs (whatever ``s_E``)."""
    rows = np.min([encounter_rows(ctx, e)[0] for e in ctx.ego_rows], axis=0)
    return -ctx.reduce_rows(-rows)


def closest_encounter(ctx: FrameContext, params: ClosestEncounterParams) -> np.ndarray:
    """``R_E`` (paper eq. 7), ``(N,)`` in [0, 1]."""
    per_ego = [
        ctx.reduce_rows(encounter_risk_rows(ctx, e, params.epsilon_m, params.encounter_time_max_s))
        for e in ctx.ego_rows
    ]
    return ctx.finish(np.max(per_ego, axis=0))


# ---------------------------------------------------------------------- headway
def _projection(ctx: FrameContext, ego_row: int) -> tuple[np.ndarray, np.ndarray]:
    """Every agent's centre projected onto the extended ego candidate ``ego_row``.

    Returns the lateral distance ``(N,)`` in m and the arc length ``(N,)`` in m.
    """

    def compute() -> tuple[np.ndarray, np.ndarray]:
        path, cum = ctx.ego_path(ego_row)
        return geometry.project_points(ctx.frame.xy, path, cum)

    return ctx.memo(("projection", int(ego_row)), compute)


def _time_gap(ctx: FrameContext, ego_row: int, arc_m: np.ndarray) -> np.ndarray:
    """``(l_2 - l_1) / v_1`` for arc lengths ``arc_m`` on the ego path; inf when the
    position is behind the ego (``l_2 < l_1``), NaN, or when the ego stands (``v_1 = 0``).

    ``l_1`` is the ego's own projection onto its path (0 when the path starts at the ego).
    """
    _, arc = _projection(ctx, ego_row)
    ego = ctx.frame.ego
    l1 = arc[ego]
    v1 = float(ctx.frame.speed[ego])
    gap = arc_m - l1
    with np.errstate(invalid="ignore"):
        ahead = gap >= 0  # NaN compares False
    if v1 <= 0:
        return np.full(arc_m.shape, np.inf)
    with np.errstate(over="ignore"):  # a crawling ego: TH overflows to inf, risk 0
        return np.where(ahead, gap / v1, np.inf)


def headway_times(ctx: FrameContext, ego_row: int, on_path_tolerance_m: float) -> np.ndarray:
    """Headway ``TH`` ``(N,)`` in s to agents on the ego candidate's path; inf elsewhere.

    Choice: an agent is on the ego path when its centre is within ``on_path_tolerance_m``
    of the extended ego path (default 1.75 m, half a lane); its ``l_2`` is the arc length
    of that nearest point. An agent level with the ego (``l_2 = l_1``) has ``TH = 0``.
    """
    lateral, arc = _projection(ctx, ego_row)
    th = _time_gap(ctx, ego_row, arc)
    return np.where(lateral <= on_path_tolerance_m, th, np.inf)


def crossing_headway_rows(
    ctx: FrameContext, ego_row: int, on_path_tolerance_m: float
) -> np.ndarray:
    """2D headway ``TH`` ``(M,)`` in s of every path row through its first ego crossing.

    The agent is projected to ego arc length ``l_cross_ego - l_cross_agent`` (the
    crossing's ego arc length minus the agent's remaining path length to it). inf for
    rows whose path never meets the ego path, when that point is behind the ego, and for
    agents on the ego path (they use plain headway; skipping them saves the costly
    collinear-overlap search).

    Choice: the crossing is the first point along the agent's extended path that lies on
    the extended ego path (exact segment intersection, touching included).
    """

    def compute() -> np.ndarray:
        lateral, _ = _projection(ctx, ego_row)
        off_path = (lateral > on_path_tolerance_m)[ctx.row_agent]
        meets = (polyline_distance_rows(ctx, ego_row, "path") == 0.0) & off_path
        arc_agent, arc_ego = geometry.first_intersections(
            ctx.ext_chunks.row(int(ego_row)), ctx.ext_chunks, rows=meets
        )
        return _time_gap(ctx, ego_row, arc_ego - arc_agent)

    return ctx.memo(("crossing_headway", int(ego_row), on_path_tolerance_m), compute)


def headway_risk(time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """``R_TH = tau / (tau + TH)``: 1 at ``TH = 0``, 0 at ``TH = inf``."""
    return tau_s / (tau_s + time_s)


def headway(ctx: FrameContext, params: HeadwayParams) -> np.ndarray:
    """Closest encounter + headway: ``max(R_E, R_TH)``, ``(N,)`` in [0, 1]."""
    per_ego = []
    for e in ctx.ego_rows:
        r_e = ctx.reduce_rows(
            encounter_risk_rows(ctx, e, params.epsilon_m, params.encounter_time_max_s)
        )
        r_th = headway_risk(headway_times(ctx, e, params.on_path_tolerance_m), params.tau_s)
        per_ego.append(np.maximum(r_e, r_th))
    return ctx.finish(np.max(per_ego, axis=0))


def headway_2d_times(ctx: FrameContext, ego_row: int, on_path_tolerance_m: float) -> np.ndarray:
    """2D headway ``(M,)`` in s per path row: plain headway for agents on the ego path,
    crossing headway for rows whose path meets the ego path, inf otherwise."""
    lateral, _ = _projection(ctx, ego_row)
    on_path = (lateral <= on_path_tolerance_m)[ctx.row_agent]
    plain = headway_times(ctx, ego_row, on_path_tolerance_m)[ctx.row_agent]
    return np.where(on_path, plain, crossing_headway_rows(ctx, ego_row, on_path_tolerance_m))


def headway_2d(ctx: FrameContext, params: Headway2DParams) -> np.ndarray:
    """Closest encounter + 2D headway: ``max(R_E, R_2D-TH)``, ``(N,)`` in [0, 1]."""
    per_ego = []
    for e in ctx.ego_rows:
        r_e = encounter_risk_rows(ctx, e, params.epsilon_m, params.encounter_time_max_s)
        r_th = headway_risk(headway_2d_times(ctx, e, params.on_path_tolerance_m), params.tau_s)
        per_ego.append(ctx.reduce_rows(np.maximum(r_e, r_th)))
    return ctx.finish(np.max(per_ego, axis=0))
