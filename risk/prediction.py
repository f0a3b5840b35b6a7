"""Prediction settings, the uncertainty model, and the shared per-frame context.

Prediction (the model spec, "Common set-up"; docs/models.md): constant speed along the path,
``x_i(s) = p_i(v_i * s)`` for ``s = 0, dt, ..., T``. A path shorter than ``v_i * T`` is
extended straight along its last segment, and every model sees the same extended path.

Uncertainty: a Gaussian per agent and step with covariance
``Rot(theta) diag(sig_lon^2, sig_lat^2) Rot(theta)^T``, ``theta`` the path heading at the
predicted point, ``sig(s) = min(sig0 + k * v * s + g_t * s, sig_max)`` per axis and kind
(``g_t = 0`` by default, the spec's model; ``g_t > 0`` lets the uncertainty of an agent
that stands now grow with time too).

:class:`FrameContext` computes the shared work (extended and cut paths, predicted
trajectories, covariances, pairwise results) once per frame, lazily, and every model
reads it from there. Choices the spec leaves open are marked "Choice:".
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any, TypeVar

import numpy as np

from risk import geometry
from risk.errors import RiskError
from risk.frame import Frame, Kind

T = TypeVar("T")


# ---------------------------------------------------------------------- settings
@dataclass(frozen=True, kw_only=True)
class KindUncertainty:
    """Position uncertainty of one agent kind:
    ``sig(s) = min(sig0 + k * v * s + g_t * s, sig_max)`` per axis.

    ``growth_*`` (``k``) is dimensionless: metres of standard deviation per metre
    travelled. ``time_growth_*`` (``g_t``) is in m/s: metres of standard deviation per
    second of prediction whatever the speed, so that an agent standing now still gets a
    growing uncertainty (0 by default, the spec's model).
    """

    sigma0_lon_m: float
    sigma0_lat_m: float
    growth_lon: float
    growth_lat: float
    sigma_max_lon_m: float
    sigma_max_lat_m: float
    time_growth_lon_mps: float = 0.0
    time_growth_lat_mps: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise RiskError(f"uncertainty {f.name} must be a finite number >= 0, got {value!r}")
        # A zero initial sigma would make the Gaussian overlap singular at s = 0.
        if self.sigma0_lon_m <= 0 or self.sigma0_lat_m <= 0:
            raise RiskError("uncertainty sigma0_lon_m and sigma0_lat_m must be > 0")
        if self.sigma_max_lon_m <= 0 or self.sigma_max_lat_m <= 0:
            raise RiskError("uncertainty sigma_max_lon_m and sigma_max_lat_m must be > 0")


VEHICLE_UNCERTAINTY = KindUncertainty(
    sigma0_lon_m=0.75,
    sigma0_lat_m=0.33,
    growth_lon=0.125,
    growth_lat=0.10,
    sigma_max_lon_m=5.0,
    sigma_max_lat_m=0.5,
)
CYCLIST_UNCERTAINTY = KindUncertainty(
    sigma0_lon_m=0.33,
    sigma0_lat_m=0.13,
    growth_lon=0.125,
    growth_lat=0.10,
    sigma_max_lon_m=3.3,
    sigma_max_lat_m=0.33,
)
PEDESTRIAN_UNCERTAINTY = KindUncertainty(
    sigma0_lon_m=0.10,
    sigma0_lat_m=0.10,
    growth_lon=0.03,
    growth_lat=0.03,
    sigma_max_lon_m=0.4,
    sigma_max_lat_m=1.5,
)


@dataclass(frozen=True)
class UncertaintyTable:
    """The per-kind uncertainty of the spec. Defaults are the spec's table.

    Choice: the spec gives no row for ``other``; it uses the vehicle row (the largest
    bodies and the widest spread, so an unknown object is never under-weighted).
    """

    vehicle: KindUncertainty = VEHICLE_UNCERTAINTY
    pedestrian: KindUncertainty = PEDESTRIAN_UNCERTAINTY
    cyclist: KindUncertainty = CYCLIST_UNCERTAINTY
    other: KindUncertainty = VEHICLE_UNCERTAINTY

    def for_kind(self, kind: Kind | int | str) -> KindUncertainty:
        return getattr(self, Kind.parse(kind).name.lower())

    def as_array(self) -> np.ndarray:
        """``(4, 8)`` table indexed by Kind code: sig0 lon/lat, growth lon/lat, max lon/lat,
        time growth lon/lat."""
        return np.array(
            [[getattr(self.for_kind(k), f.name) for f in fields(KindUncertainty)] for k in Kind],
            dtype=np.float64,
        )


@dataclass(frozen=True)
class PredictionSettings:
    """Horizon and step of the constant-speed prediction, and the uncertainty table.

    ``horizon_s`` must be a whole number of steps ``dt_s``; the steps are
    ``s_k = k * horizon_s / n`` for ``k = 0..n`` with ``n = horizon_s / dt_s``, so the last
    step is exactly the horizon.
    """

    horizon_s: float = 12.0
    dt_s: float = 0.1
    uncertainty: UncertaintyTable = field(default_factory=UncertaintyTable)

    def __post_init__(self) -> None:
        for name in ("horizon_s", "dt_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise RiskError(f"prediction {name} must be a finite number > 0, got {value!r}")
        ratio = self.horizon_s / self.dt_s
        if abs(ratio - round(ratio)) > 1e-9 * max(1.0, ratio):
            raise RiskError(
                f"prediction horizon_s={self.horizon_s} must be a whole number of "
                f"steps dt_s={self.dt_s}"
            )
        if round(ratio) > 100_000:
            raise RiskError(f"prediction has {round(ratio)} steps; at most 100000 are supported")

    @property
    def n_steps(self) -> int:
        """Number of predicted positions including ``s = 0``."""
        return round(self.horizon_s / self.dt_s) + 1

    @property
    def steps_s(self) -> np.ndarray:
        """Prediction times ``(n_steps,)`` in s, from 0 to exactly ``horizon_s``."""
        return np.linspace(0.0, self.horizon_s, self.n_steps)

    def to_dict(self) -> dict[str, Any]:
        """Plain values for JSON and result files."""
        table = {
            k.name.lower(): {
                f.name: getattr(self.uncertainty.for_kind(k), f.name)
                for f in fields(KindUncertainty)
            }
            for k in Kind
        }
        return {"horizon_s": self.horizon_s, "dt_s": self.dt_s, "uncertainty": table}


def uncertainty_sigmas(
    kinds: np.ndarray, speed: np.ndarray, steps_s: np.ndarray, table: UncertaintyTable
) -> tuple[np.ndarray, np.ndarray]:
    """Standard deviations ``(A, n)`` in m, longitudinal and lateral, for agents ``(A,)``.

    ``sig(s) = min(sig0 + k * v * s + g_t * s, sig_max)`` with the kind's row of ``table``.
    """
    rows = table.as_array()[kinds.astype(np.intp)]  # (A, 8)
    travelled = speed[:, None] * steps_s[None, :]  # (A, n), m
    s = steps_s[None, :]
    lon = np.minimum(rows[:, 0:1] + rows[:, 2:3] * travelled + rows[:, 6:7] * s, rows[:, 4:5])
    lat = np.minimum(rows[:, 1:2] + rows[:, 3:4] * travelled + rows[:, 7:8] * s, rows[:, 5:6])
    return lon, lat


def covariances(
    sig_lon: np.ndarray, sig_lat: np.ndarray, cos: np.ndarray, sin: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covariance entries ``(xx, xy, yy)``, each shaped like ``sig_lon``, in m^2.

    ``R diag(lon^2, lat^2) R^T`` with ``R`` the rotation by the path heading, given as
    its unit vector components ``cos``, ``sin``.
    """
    a, b = sig_lon**2, sig_lat**2
    cc, ss = cos * cos, sin * sin
    return a * cc + b * ss, (a - b) * cos * sin, a * ss + b * cc


# ---------------------------------------------------------------------- shared context
class FrameContext:
    """Everything the models share for one frame, computed lazily and at most once.

    Shapes: ``N`` agents, ``M`` path rows (candidates; row ``m`` belongs to agent
    ``row_agent[m]``), ``n`` prediction steps, ``P`` points per extended path.

    Choice (several candidates): each model is computed for every (ego candidate, agent
    candidate) pair and the riskiest pair counts (max of risk over both).
    """

    def __init__(self, frame: Frame, settings: PredictionSettings | None = None) -> None:
        self.frame = frame
        self.settings = PredictionSettings() if settings is None else settings
        self.row_agent = frame.path_agent
        # Rows are grouped by owner, so each agent's rows start where the owner changes.
        self.row_starts = np.flatnonzero(np.r_[True, self.row_agent[1:] != self.row_agent[:-1]])
        self.ego_rows: list[int] = [int(r) for r in np.flatnonzero(self.row_agent == frame.ego)]
        self._memo: dict[Hashable, Any] = {}

    # ------------------------------------------------------------------ helpers
    def memo(self, key: Hashable, compute: Callable[[], T]) -> T:
        """The cached value for ``key``, computed by ``compute()`` on first use."""
        if key not in self._memo:
            self._memo[key] = compute()
        return self._memo[key]

    def reduce_rows(self, values: np.ndarray) -> np.ndarray:
        """Per-row values ``(M,)`` -> per-agent maximum ``(N,)`` (the riskiest candidate)."""
        return np.maximum.reduceat(values, self.row_starts)

    def finish(self, risk: np.ndarray) -> np.ndarray:
        """Per-agent risks ``(N,)`` as float64 with NaN for the ego and invalid agents."""
        out = np.array(risk, dtype=np.float64)
        out[~self.frame.others] = np.nan
        return out

    @property
    def steps_s(self) -> np.ndarray:
        return self.memo("steps", lambda: self.settings.steps_s)

    # ------------------------------------------------------------------ per-row basics
    @cached_property
    def row_speed(self) -> np.ndarray:
        """Speed ``(M,)`` in m/s of each row's owner."""
        return self.frame.speed[self.row_agent]

    @cached_property
    def horizon_length_m(self) -> np.ndarray:
        """Distance ``(M,)`` in m each row's owner travels within the horizon, ``v * T``."""
        return self.row_speed * self.settings.horizon_s

    @cached_property
    def ext_paths(self) -> np.ndarray:
        """Paths extended to at least ``v * T``: ``(M, P, 2)`` in m."""
        f = self.frame
        ext, _ = geometry.extend_paths(
            f.paths, f.path_points, f.heading[self.row_agent], self.horizon_length_m
        )
        return ext

    @property
    def ext_points(self) -> np.ndarray:
        """Number of real points ``(M,)`` of each extended path (one more than given)."""
        return self.frame.path_points + 1

    def ego_path(self, ego_row: int) -> tuple[np.ndarray, np.ndarray]:
        """One extended ego candidate without padding: points ``(P_e, 2)``, arc lengths ``(P_e,)``."""
        n = int(self.ext_points[ego_row])
        return self.ext_paths[ego_row, :n], self.ext_cum[ego_row, :n]

    @cached_property
    def ext_cum(self) -> np.ndarray:
        """Arc lengths ``(M, P)`` in m along the extended paths."""
        return geometry.cumulative_lengths(self.ext_paths)

    @cached_property
    def ext_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """Components ``(M, P)`` x and y of the extended paths, contiguous."""
        p = self.ext_paths
        return np.ascontiguousarray(p[..., 0]), np.ascontiguousarray(p[..., 1])

    @cached_property
    def ext_unit(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit segment direction components ``(M, P-1)`` of the extended paths."""
        return geometry.segment_unit_vectors(self.ext_paths, self.frame.heading[self.row_agent])

    @cached_property
    def ext_chunks(self) -> geometry.ChunkedPolylines:
        return geometry.chunk_polylines(self.ext_paths, self.ext_cum, self.ext_points)

    @cached_property
    def _cut(self) -> tuple[np.ndarray, np.ndarray]:
        return geometry.cut_paths(self.ext_paths, self.ext_cum, self.horizon_length_m)

    @property
    def cut_paths(self) -> np.ndarray:
        """Extended paths cut at ``v * T`` (the dynamic horizon): ``(M, P, 2)`` in m."""
        return self._cut[0]

    @cached_property
    def cut_chunks(self) -> geometry.ChunkedPolylines:
        return geometry.chunk_polylines(self.cut_paths, None, self._cut[1])

    # ------------------------------------------------------------------ prediction
    def row_blocks(self) -> list[slice]:
        """Row slices for per-step work: blocks of rows whose ``(rows, n)`` temporaries stay
        under geometry.BLOCK_ELEMENTS (large temporaries cost page faults), so the cost
        grows linearly with the number of agents."""
        return geometry.blocks(self.row_agent.size, self.settings.n_steps)

    @cached_property
    def _trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        m, n = self.row_agent.size, self.settings.n_steps
        out = [np.empty((m, n)) for _ in range(4)]
        px, py = self.ext_xy
        ux, uy = self.ext_unit
        cum, steps, speed = self.ext_cum, self.steps_s, self.row_speed
        for blk in self.row_blocks():
            arc = speed[blk, None] * steps[None, :]  # (rows, n), m
            x, y, seg = geometry.interpolate_components(px[blk], py[blk], cum[blk], arc)
            flat = seg + (np.arange(seg.shape[0]) * ux.shape[1])[:, None]
            out[0][blk], out[1][blk] = x, y
            out[2][blk] = np.take(ux[blk].ravel(), flat)
            out[3][blk] = np.take(uy[blk].ravel(), flat)
        return out[0], out[1], out[2], out[3]

    @property
    def traj_x(self) -> np.ndarray:
        """Predicted x ``(M, n)`` in m, constant speed along the extended path."""
        return self._trajectory[0]

    @property
    def traj_y(self) -> np.ndarray:
        """Predicted y ``(M, n)`` in m."""
        return self._trajectory[1]

    @property
    def dir_x(self) -> np.ndarray:
        """x component ``(M, n)`` of the unit path heading at each predicted position."""
        return self._trajectory[2]

    @property
    def dir_y(self) -> np.ndarray:
        """y component ``(M, n)`` of the unit path heading at each predicted position."""
        return self._trajectory[3]

    @property
    def traj_xy(self) -> np.ndarray:
        """Predicted positions ``(M, n, 2)`` in m (stacked copy, for inspection)."""
        return np.stack([self.traj_x, self.traj_y], axis=-1)

    @property
    def traj_dir(self) -> np.ndarray:
        """Unit path headings ``(M, n, 2)`` (stacked copy, for inspection)."""
        return np.stack([self.dir_x, self.dir_y], axis=-1)

    @cached_property
    def _sigmas(self) -> tuple[np.ndarray, np.ndarray]:
        f = self.frame
        lon, lat = np.empty((2, self.row_agent.size, self.settings.n_steps))
        for blk in self.row_blocks():
            agent = self.row_agent[blk]
            lon[blk], lat[blk] = uncertainty_sigmas(
                f.kinds[agent], f.speed[agent], self.steps_s, self.settings.uncertainty
            )
        return lon, lat

    @property
    def sigma_lon(self) -> np.ndarray:
        """Longitudinal standard deviation ``(M, n)`` in m."""
        return self._sigmas[0]

    @property
    def sigma_lat(self) -> np.ndarray:
        """Lateral standard deviation ``(M, n)`` in m."""
        return self._sigmas[1]

    @cached_property
    def cov(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position covariance ``(xx, xy, yy)``, each ``(M, n)`` in m^2."""
        xx, xy, yy = np.empty((3, self.row_agent.size, self.settings.n_steps))
        for blk in self.row_blocks():
            xx[blk], xy[blk], yy[blk] = covariances(
                self.sigma_lon[blk], self.sigma_lat[blk], self.dir_x[blk], self.dir_y[blk]
            )
        return xx, xy, yy
