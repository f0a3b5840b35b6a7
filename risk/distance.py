"""Distance models: current distance, path distance, trajectory distance (paper Sec. III-A, III-D).

Each turns a distance ``d`` (m) into a risk ``R = eps / (eps + d)`` (paper eq. 4), which
is 1 at ``d = 0``, in (0, 1], and ranks exactly like ``-d``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from risk import geometry
from risk.errors import RiskError
from risk.prediction import FrameContext


def distance_to_risk(distance_m: np.ndarray, epsilon_m: float) -> np.ndarray:
    """``eps / (eps + d)`` elementwise (paper eq. 4); ``d`` in m, result in (0, 1]."""
    return epsilon_m / (epsilon_m + distance_m)


def check_positive(owner: str, name: str, value: object) -> None:
    """Raise RiskError unless ``value`` is a finite number > 0."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise RiskError(f"{owner}: {name} must be a finite number > 0, got {value!r}")


def _epsilon_field() -> float:
    return field(default=1.0, metadata={"help": "distance scale of R = eps/(eps+d)", "unit": "m"})


@dataclass(frozen=True)
class CurrentDistanceParams:
    """Parameters of the current distance model."""

    epsilon_m: float = _epsilon_field()

    def __post_init__(self) -> None:
        check_positive("current_distance", "epsilon_m", self.epsilon_m)


@dataclass(frozen=True)
class PathDistanceParams:
    """Parameters of the path distance model."""

    epsilon_m: float = _epsilon_field()

    def __post_init__(self) -> None:
        check_positive("path_distance", "epsilon_m", self.epsilon_m)


@dataclass(frozen=True)
class TrajectoryDistanceParams:
    """Parameters of the trajectory distance model (the horizon is the prediction's ``T``)."""

    epsilon_m: float = _epsilon_field()

    def __post_init__(self) -> None:
        check_positive("trajectory_distance", "epsilon_m", self.epsilon_m)


# ---------------------------------------------------------------------- distances
def current_distances(ctx: FrameContext) -> np.ndarray:
    """Centre distance ``(N,)`` in m from the ego to every agent, now."""
    xy = ctx.frame.xy
    d = xy - xy[ctx.frame.ego]
    return np.hypot(d[:, 0], d[:, 1])


def polyline_distance_rows(ctx: FrameContext, ego_row: int, which: str) -> np.ndarray:
    """Distance ``(M,)`` in m from ego candidate ``ego_row`` to every path row.

    ``which`` is ``"path"`` (extended paths) or ``"cut"`` (cut at ``v * T``). Cached: the
    2D headway reuses the path distances to find crossing rows.
    """
    chunks = ctx.ext_chunks if which == "path" else ctx.cut_chunks
    return ctx.memo(
        (which, "rows", int(ego_row)),
        lambda: geometry.polyline_distances(chunks.row(int(ego_row)), chunks),
    )


def _min_polyline_distance(ctx: FrameContext, which: str) -> np.ndarray:
    """Least distance ``(N,)`` in m between any ego candidate and any agent candidate."""
    rows = np.min([polyline_distance_rows(ctx, e, which) for e in ctx.ego_rows], axis=0)
    return -ctx.reduce_rows(-rows)


def path_distances(ctx: FrameContext) -> np.ndarray:
    """Minimum distance ``(N,)`` in m between the whole (extended) forward paths.

    Choice: the paths are the extended ones every model sees (a path shorter than
    ``v * T`` is extended straight), so ``d_path <= d_traj`` always holds.
    """
    return ctx.memo("path_distances", lambda: _min_polyline_distance(ctx, "path"))


def trajectory_distances(ctx: FrameContext) -> np.ndarray:
    """Minimum distance ``(N,)`` in m between the paths cut at ``v * T`` (dynamic horizon)."""
    return ctx.memo("trajectory_distances", lambda: _min_polyline_distance(ctx, "cut"))


# ---------------------------------------------------------------------- models
def current_distance(ctx: FrameContext, params: CurrentDistanceParams) -> np.ndarray:
    """``R_d = eps / (eps + ||x_2 - x_1||)`` (paper eq. 3-4), ``(N,)`` in (0, 1]."""
    return ctx.finish(distance_to_risk(current_distances(ctx), params.epsilon_m))


def path_distance(ctx: FrameContext, params: PathDistanceParams) -> np.ndarray:
    """``R_p = eps / (eps + min ||p_2(m_2) - p_1(m_1)||)`` (paper eq. 5), ``(N,)``."""
    return ctx.finish(distance_to_risk(path_distances(ctx), params.epsilon_m))


def trajectory_distance(ctx: FrameContext, params: TrajectoryDistanceParams) -> np.ndarray:
    """``R_T``: path distance over ``m_i in [0, v_i T]`` (paper eq. 12), ``(N,)``."""
    return ctx.finish(distance_to_risk(trajectory_distances(ctx), params.epsilon_m))
