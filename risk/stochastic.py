"""Stochastic models: circle approximation, 2D Gaussians, survival analysis (paper Sec. III-C).

All three read the shared prediction (positions, path headings and the per-kind
covariances of :mod:`risk.prediction`). The Gaussian overlap ``P_o(s)`` of a pair is
computed once per frame and shared by the Gaussian and survival models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from risk.distance import check_positive, distance_to_risk
from risk.errors import RiskError
from risk.prediction import FrameContext


@dataclass(frozen=True)
class CirclesParams:
    """Parameters of the circle approximation."""

    epsilon_m: float = field(
        default=1.0, metadata={"help": "distance scale of R = eps/(eps+d)", "unit": "m"}
    )
    n_circles: int = field(
        default=3, metadata={"help": "circles along the other agent's length", "unit": ""}
    )
    sigma_scale: float = field(
        default=2.0, metadata={"help": "radius grows by this many sig_lon(s)", "unit": ""}
    )
    radius_rule: str = field(
        default="spec",
        metadata={
            "help": "ego circle radius: 'spec' = ego length/2, 'width' = ego width/2 "
            "(plus sigma_scale * sig_lon either way)",
            "unit": "",
        },
    )

    def __post_init__(self) -> None:
        check_positive("circles", "epsilon_m", self.epsilon_m)
        if not (isinstance(self.n_circles, int) and 1 <= self.n_circles <= 64):
            raise RiskError(
                f"circles: n_circles must be an integer in 1..64, got {self.n_circles!r}"
            )
        if not (
            isinstance(self.sigma_scale, (int, float))
            and math.isfinite(self.sigma_scale)
            and self.sigma_scale >= 0
        ):
            raise RiskError(
                f"circles: sigma_scale must be a finite number >= 0, got {self.sigma_scale!r}"
            )
        if self.radius_rule not in ("spec", "width"):
            raise RiskError(
                f"circles: radius_rule must be 'spec' or 'width', got {self.radius_rule!r}"
            )


@dataclass(frozen=True)
class GaussianParams:
    """The 2D Gaussian model has no parameters of its own (only the prediction's)."""


@dataclass(frozen=True)
class SurvivalParams:
    """Parameters of survival analysis."""

    escape_time_s: float = field(
        default=0.4,
        metadata={"help": "tau_esc: escape rate 1/tau_esc of the Poisson process", "unit": "s"},
    )

    def __post_init__(self) -> None:
        check_positive("survival", "escape_time_s", self.escape_time_s)


# ---------------------------------------------------------------------- shared overlap
def overlap_rows(ctx: FrameContext, ego_row: int) -> np.ndarray:
    """Gaussian overlap ``P_o(s)`` ``(M, n)`` in 1/m^2 of every row with ego candidate
    ``ego_row`` (paper eq. 10):

    ``det(2 pi S)^(-1/2) exp(-1/2 dmu^T S^-1 dmu)``, ``S = Sigma_1 + Sigma_2``, with the 2x2
    determinant and inverse in closed form. Values below ~1e-308 underflow to 0.
    """

    def compute() -> np.ndarray:
        xx, xy, yy = ctx.cov
        out = np.empty_like(xx)
        for blk in ctx.row_blocks():
            out[blk] = _overlap(
                xx[blk] + xx[ego_row],
                xy[blk] + xy[ego_row],
                yy[blk] + yy[ego_row],
                ctx.traj_x[blk] - ctx.traj_x[ego_row],
                ctx.traj_y[blk] - ctx.traj_y[ego_row],
            )
        return out

    return ctx.memo(("overlap", int(ego_row)), compute)


def _overlap(sxx, sxy, syy, dx, dy) -> np.ndarray:
    """``P_o`` from the summed covariance entries and the mean offset (all the same
    shape); overwrites ``sxx``, ``sxy``, ``syy`` to spare temporaries."""
    det = sxx * syy - sxy * sxy
    # -1/2 dmu^T S^-1 dmu with the closed-form inverse
    syy *= dx * dx
    sxx *= dy * dy
    sxy *= dx * dy
    syy -= 2.0 * sxy
    syy += sxx
    syy /= det
    syy *= -0.5
    np.exp(syy, out=syy)
    np.sqrt(det, out=det)
    det *= 2.0 * np.pi
    syy /= det
    return syy


# ---------------------------------------------------------------------- circles
def circle_distances_rows(ctx: FrameContext, ego_row: int, params: CirclesParams) -> np.ndarray:
    """``d_c`` ``(M,)`` in m: least gap between the ego circle and the other's circles.

    Ego: one circle at its centre, radius ``length/2 + c sig_lon(s)``. Other agent:
    ``k`` circles of radius ``width/2 + c sig_lon(s)``. Choice: their centres split the
    body length into ``k`` equal slices (offsets ``((j + 1/2)/k - 1/2) * length`` along the
    path heading; ``k = 1`` is the centre). Minimum over circles and steps, clipped at 0.
    """
    f = ctx.frame
    c = params.sigma_scale
    k = params.n_circles
    ego = f.ego
    ego_body = f.length[ego] if params.radius_rule == "spec" else f.width[ego]
    r_ego = 0.5 * ego_body + c * ctx.sigma_lon[ego_row]  # (n,)
    agent = ctx.row_agent
    r_other = 0.5 * f.width[agent][:, None] + c * ctx.sigma_lon  # (M, n), stored once
    slices = (np.arange(k) + 0.5) / k - 0.5  # (k,)
    length = f.length[agent][:, None]  # (M, 1)
    best = np.full(agent.size, np.inf)
    for blk in ctx.row_blocks():
        rel_x = ctx.traj_x[blk] - ctx.traj_x[ego_row]  # (rows, n)
        rel_y = ctx.traj_y[blk] - ctx.traj_y[ego_row]
        reach = r_ego[None, :] + r_other[blk]  # (rows, n)
        # |rel + o u|^2 = |rel|^2 + 2 o (rel . u) + o^2 for the unit heading u: two shared
        # terms, then a few operations per circle. No cancellation: o is at most half a
        # body length, so the centre distance is never much smaller than |rel|.
        rel2 = rel_x * rel_x + rel_y * rel_y
        along = rel_x * ctx.dir_x[blk] + rel_y * ctx.dir_y[blk]
        for frac in slices:  # a loop over the k circles (not agents)
            o = length[blk] * frac  # (rows, 1), m
            centre2 = rel2 + (2.0 * o) * along + o * o
            gap = np.sqrt(np.maximum(centre2, 0.0)) - reach
            np.minimum(best[blk], gap.min(axis=1), out=best[blk])
    return np.maximum(best, 0.0)


def circles(ctx: FrameContext, params: CirclesParams) -> np.ndarray:
    """Circle approximation ``R_c = eps / (eps + d_c)`` (paper eq. 9), ``(N,)`` in (0, 1]."""
    per_ego = [
        ctx.reduce_rows(distance_to_risk(circle_distances_rows(ctx, e, params), params.epsilon_m))
        for e in ctx.ego_rows
    ]
    return ctx.finish(np.max(per_ego, axis=0))


# ---------------------------------------------------------------------- Gaussians
def gaussian(ctx: FrameContext, params: GaussianParams) -> np.ndarray:
    """2D Gaussians ``R_G = max_s P_o(s)`` (paper eq. 10), ``(N,)`` in 1/m^2, >= 0."""
    per_ego = [ctx.reduce_rows(overlap_rows(ctx, e).max(axis=1)) for e in ctx.ego_rows]
    return ctx.finish(np.max(per_ego, axis=0))


# ---------------------------------------------------------------------- survival
def survival_risk(overlap: np.ndarray, dt_s: float, escape_time_s: float) -> np.ndarray:
    """Survival risk ``(...,)`` from overlaps ``(..., n)`` per step (paper eq. 11).

    ``S_0 = 1``, ``S_{k+1} = S_k exp(-(P_k + dt/tau_esc))``, ``R_S = sum_k P_k S_k`` over
    all ``n`` steps, with ``log S_k`` as an exclusive cumulative sum (O(n) per pair).
    """
    return (overlap * survival_function(overlap, dt_s, escape_time_s)).sum(axis=-1)


def survival_function(overlap: np.ndarray, dt_s: float, escape_time_s: float) -> np.ndarray:
    """``S_k`` ``(..., n)``: the probability of no critical event before step ``k``."""
    hazard = overlap + dt_s / escape_time_s
    log_s = np.zeros_like(overlap)
    np.cumsum(hazard[..., :-1], axis=-1, out=log_s[..., 1:])
    return np.exp(-log_s)


def survival(ctx: FrameContext, params: SurvivalParams) -> np.ndarray:
    """Survival analysis ``R_S`` (paper eq. 11, after Eggert 2014), ``(N,)``, >= 0.

    Per pair (ego and one agent), so an agent's risk does not depend on who else is
    present. The value depends on ``dt`` and ``tau_esc``.
    """
    dt = ctx.settings.dt_s
    per_ego = []
    for e in ctx.ego_rows:
        p_o = overlap_rows(ctx, e)
        rows = np.empty(p_o.shape[0])
        for blk in ctx.row_blocks():
            rows[blk] = survival_risk(p_o[blk], dt, params.escape_time_s)
        per_ego.append(ctx.reduce_rows(rows))
    return ctx.finish(np.max(per_ego, axis=0))
