"""Hindsight truth: what really happened next between the ego and each agent.

Pure numpy over a scene's recorded track arrays (no I/O). For every (ego, frame, agent)
this gives, from the recording's own future within a horizon ``H``:

- **gap** ``truth_gap_m``: the minimum clearance between the two oriented boxes (the
  agents' recorded footprints: centre, heading, length, width) *at equal times*, over the
  frames ``f .. f + H`` at which both are recorded. Exact rectangle-to-rectangle distance
  (:func:`box_gap`), 0 when the boxes touch or overlap. NaN when the two are never both
  recorded in the window.
- **PET** ``truth_pet_s`` (post-encroachment time): the time between the first of the two
  leaving a place and the second reaching it, minimised over every place both footprints
  cover within the window. On the frame grid: the least ``|t_i - t_j|`` over the frames
  ``i`` (ego) and ``j`` (agent) of the window whose boxes overlap (touching counts). This
  equals ``min over points x of (t_in,second(x) - t_out,first(x))``: when the first road
  user occupies ``x`` last at ``t_i`` and the second first at ``t_j``, boxes ``i`` and
  ``j`` both contain ``x``; conversely every overlapping pair bounds that point's PET from
  above. A collision (overlap at ``i == j``) gives 0. NaN when the swept footprints never
  meet within the window. The resolution is one frame period.

  Why per point and not "the first leaves the whole shared area, the second enters it":
  for agents on the same lane or merging, the shared area is a long strip that both
  occupy at once without ever coming close, so the area-level time is negative and
  meaningless; per point it is the follower's time gap, the usual rear-end surrogate. For
  a perpendicular crossing the two agree to within the time a body takes to cross its
  own width.
- **label**: an *interaction* when ``gap <= gap_m`` or ``PET <= pet_s`` (defaults 0.5 m
  and 1.0 s, see ``docs/hindsight.md`` for the sources). A close approach seen in the
  recorded part of the window is a positive even when the window is censored.
- **censoring**: a (frame, agent) is *censored* when the window ``f .. f + H`` is not
  recorded enough for both: the scene ends before ``t_f + H``, or the ego or the agent is
  not recorded at some step of the window (it left or had not yet entered the recorded
  area), i.e. fewer than ``coverage * (H_steps + 1)`` of the window's steps hold both
  (default ``coverage = 1``: every step). A censored pair that was not seen coming close
  has label *unknown* (-1, null in tables), never a silent negative.

- **yielded** (kept apart from "came close"): the ego *braked*, i.e. within the window it
  decelerated at :data:`YIELD_DECEL_MPS2` or harder, or its speed fell to
  :data:`YIELD_SPEED_SHARE` of its speed at the frame (from at least
  :data:`YIELD_MIN_SPEED_MPS`), *while the agent was ahead on its path*: at some step of
  the window at which the ego was slowing down (or standing after braking), the agent's
  centre was in the corridor ahead of the ego's recorded pose (ahead, within
  :data:`AHEAD_REACH_M` plus :data:`AHEAD_HEADWAY_S` of its speed, and laterally within
  the two half-widths plus :data:`AHEAD_MARGIN_M`). Speeds are finite differences of
  recorded positions over :data:`SPEED_SPAN_S`. A standing car the ego stops behind is
  yielded-to and never comes close.
- **track consistency**: a step of an agent's track is *inconsistent* when the speed it
  implies since the agent's previous recorded position (across any gap) or its
  acceleration over :data:`SPEED_SPAN_S` is beyond what its kind can do
  (:data:`KIND_LIMITS`: a teleport, a jump between tracks). A row whose ego or agent has
  an inconsistent step in the window is *flagged* (``track_ok`` false) and kept out of the
  truth: its label is unknown.
- **complete**: the window is recorded for both at every step needed (the complement of
  censoring); ``replay evaluate`` scores on complete windows only by default.

Times are on the scene's frame grid ``t_k = t_0 + k dt``; ``H_steps = floor(H / dt)``
(a horizon that is not a whole number of frames is rounded down; 1e-9 s tolerance).

Cost per ego: ``T x N`` box gaps and ``(2 H_steps + 1) x T x N`` overlap tests (one
vectorised pass per time lag, a cheap bounding-circle test first); egos are processed
in vectorised blocks, so there is no Python loop over agents.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# The box geometry and the windows live in risk.boxes; importable from here as before.
from risk.boxes import TOUCH_M as TOUCH_M
from risk.boxes import box_corners as box_corners
from risk.boxes import box_gap as box_gap
from risk.boxes import boxes_overlap as boxes_overlap
from risk.boxes import forward_window_min as forward_window_min
from risk.boxes import forward_window_sum as forward_window_sum
from risk.errors import RiskError
from risk.frame import Frame

#: Label codes of :class:`Truth`.
LABEL_UNKNOWN = -1
LABEL_NEGATIVE = 0
LABEL_POSITIVE = 1
#: Elements of one (T, E, N) block of the vectorised computation (bounds memory).
BLOCK_ELEMENTS = 400_000
#: The yielded label (see the module docstring): hard braking (m/s^2), the share of the
#: frame's speed that counts as "halved", the least frame speed for that rule (m/s), the
#: span of the finite differences (s), a step "slowing down" (m/s^2) or "standing" (m/s).
YIELD_DECEL_MPS2 = 3.0
YIELD_SPEED_SHARE = 0.5
YIELD_MIN_SPEED_MPS = 2.0
SPEED_SPAN_S = 0.5
SLOWING_MPS2 = 0.5
STANDING_MPS = 0.5
#: The corridor ahead of the ego: reach (m) plus headway (s) times its speed, lateral
#: margin beyond the two half-widths (m).
AHEAD_REACH_M = 10.0
AHEAD_HEADWAY_S = 3.0
AHEAD_MARGIN_M = 0.5
#: Per kind code (vehicle, pedestrian, cyclist, other): the highest plausible speed (m/s)
#: and acceleration magnitude (m/s^2) of a track. Generous: a sports car's top speed and
#: about 1.5 g; a sprinter; a racing cyclist.
KIND_LIMITS: dict[int, tuple[float, float]] = {
    0: (70.0, 15.0),
    1: (12.0, 10.0),
    2: (25.0, 10.0),
    3: (70.0, 15.0),
}


# ---------------------------------------------------------------------- settings
@dataclass(frozen=True)
class HindsightSettings:
    """Parameters of the hindsight truth (see the module docstring and docs/hindsight.md).

    - ``horizon_s``: how far ahead of each frame the recording is searched (s);
    - ``gap_m``: a box clearance at or below this is an interaction (m);
    - ``pet_s``: a post-encroachment time at or below this is an interaction (s);
    - ``coverage``: the share of the window's steps at which both agents must be recorded
      for a negative to be trusted (1 = every step).
    """

    horizon_s: float = 5.0
    gap_m: float = 0.5
    pet_s: float = 1.0
    coverage: float = 1.0

    def __post_init__(self) -> None:
        for name in ("horizon_s", "gap_m", "pet_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise RiskError(f"hindsight {name} must be a finite number >= 0, got {value}")
        if not (0.0 < self.coverage <= 1.0):
            raise RiskError(f"hindsight coverage must be in (0, 1], got {self.coverage}")

    def horizon_steps(self, dt_s: float) -> int:
        """Frames in the horizon (rounded down)."""
        return math.floor(self.horizon_s / dt_s + 1e-9)


# ---------------------------------------------------------------------- tracks
@dataclass(frozen=True, eq=False)
class Tracks:
    """A scene's recorded agents as arrays over ``T`` frames and ``N`` agents.

    ``xy (T, N, 2)`` m, ``heading (T, N)`` rad, ``length``, ``width (T, N)`` m and
    ``valid (T, N)`` bool (recorded in that frame); ``ids (N,)`` int64 unique,
    ``kinds (N,)`` int8 (:class:`risk.Kind` codes, the first recorded); ``t0_s`` and
    ``dt_s``: frame ``k`` is at ``t0_s + k * dt_s``. Fields of unrecorded entries are
    ignored.
    """

    ids: np.ndarray
    kinds: np.ndarray
    xy: np.ndarray
    heading: np.ndarray
    length: np.ndarray
    width: np.ndarray
    valid: np.ndarray
    t0_s: float
    dt_s: float

    def __post_init__(self) -> None:
        t, n = self.valid.shape
        shapes = {
            "xy": (t, n, 2),
            "heading": (t, n),
            "length": (t, n),
            "width": (t, n),
            "ids": (n,),
            "kinds": (n,),
        }
        for name, shape in shapes.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise RiskError(f"tracks: {name} must have shape {shape}, got {got}")
        if not (math.isfinite(self.dt_s) and self.dt_s > 0):
            raise RiskError(f"tracks: the frame period must be > 0, got {self.dt_s}")
        ids = np.sort(self.ids)  # (not np.unique: numpy 2 imports numpy.ma for it, 40 ms)
        if (ids[1:] == ids[:-1]).any():
            raise RiskError("tracks: agent ids must be unique")

    @property
    def n_frames(self) -> int:
        return int(self.valid.shape[0])

    @property
    def n_agents(self) -> int:
        return int(self.valid.shape[1])

    def index_of(self, agent_ids: np.ndarray | Sequence[int]) -> np.ndarray:
        """Column indices of ``agent_ids`` (-1 for an id the tracks do not hold)."""
        ids = np.asarray(agent_ids, dtype=np.int64)
        if self.ids.size == 0:
            return np.full(ids.shape, -1, dtype=np.int64)
        order = np.argsort(self.ids)
        pos = np.clip(np.searchsorted(self.ids[order], ids), 0, self.ids.size - 1)
        return np.where(self.ids[order][pos] == ids, order[pos], -1)

    def frame_of(self, t_s: np.ndarray | float) -> np.ndarray:
        """The frame index nearest to each time ``t_s``."""
        return np.rint((np.asarray(t_s, dtype=np.float64) - self.t0_s) / self.dt_s).astype(np.int64)


def tracks_from_states(
    frame_index: np.ndarray,
    agent_id: np.ndarray,
    kind: np.ndarray,
    xy: np.ndarray,
    heading: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    *,
    t0_s: float,
    dt_s: float,
    n_frames: int | None = None,
) -> Tracks:
    """Tracks from flat recorded states, one row per (frame, agent) that is recorded.

    ``frame_index (R,)`` int (0-based on the grid ``t0_s + k dt_s``), ``agent_id (R,)``,
    ``kind (R,)``, ``xy (R, 2)``, ``heading``, ``length``, ``width (R,)``. A (frame,
    agent) given twice keeps the last row.
    """
    fi = np.asarray(frame_index, dtype=np.int64)
    if fi.size and fi.min() < 0:
        raise RiskError("tracks: frame indices must be >= 0")
    t = int(n_frames if n_frames is not None else (fi.max() + 1 if fi.size else 0))
    ids, col = np.unique(np.asarray(agent_id, dtype=np.int64), return_inverse=True)
    n = ids.size
    out_xy = np.zeros((t, n, 2))
    out_h = np.zeros((t, n))
    out_l = np.zeros((t, n))
    out_w = np.zeros((t, n))
    valid = np.zeros((t, n), dtype=bool)
    out_xy[fi, col] = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    out_h[fi, col] = heading
    out_l[fi, col] = length
    out_w[fi, col] = width
    valid[fi, col] = True
    kinds = np.zeros(n, dtype=np.int8)
    first = np.lexsort((fi, col))  # by agent, then frame
    starts = np.r_[0, np.flatnonzero(np.diff(col[first])) + 1] if fi.size else np.empty(0, int)
    kinds[col[first[starts]]] = np.asarray(kind)[first[starts]]
    return Tracks(ids, kinds, out_xy, out_h, out_l, out_w, valid, float(t0_s), float(dt_s))


def check_period(frame_t: np.ndarray, frame_period_s: float) -> None:
    """Refuse a frame period far below the frames' own spacing: the tracks' grid spans
    the scene's time in steps of the period, so a wrong period (``1e-12`` s in a
    file's metadata) would size it from one bad number (78 TiB for a 20 s scene)
    rather than from the frames. Some two frames must be about one period apart."""
    steps = np.diff(np.unique(np.asarray(frame_t, dtype=np.float64)))
    if steps.size and steps.min() > 1.5 * frame_period_s:
        raise RiskError(
            f"the frame period is {frame_period_s:g} s, but no two frames are that close"
            f" (the closest are {steps.min():g} s apart); the scene's frame_period_s is"
            " wrong: convert the source again"
        )


def tracks_from_frames(frames: Sequence[Frame], *, frame_period_s: float) -> Tracks:
    """Tracks of a scene's frames (every valid agent of every frame; frame ``k`` of the
    grid is the one nearest ``t0 + k dt``, ``t0`` the first frame's time)."""
    if not frames:
        raise RiskError("tracks: no frames")
    check_period(np.array([f.t for f in frames]), frame_period_s)
    t0 = float(frames[0].t)
    rows = [(f, np.flatnonzero(f.valid)) for f in frames]
    fi = np.concatenate(
        [np.full(r.size, round((f.t - t0) / frame_period_s), dtype=np.int64) for f, r in rows]
    )
    return tracks_from_states(
        fi,
        np.concatenate([f.ids[r] for f, r in rows]),
        np.concatenate([f.kinds[r] for f, r in rows]),
        np.concatenate([f.xy[r] for f, r in rows]),
        np.concatenate([f.heading[r] for f, r in rows]),
        np.concatenate([f.length[r] for f, r in rows]),
        np.concatenate([f.width[r] for f, r in rows]),
        t0_s=t0,
        dt_s=frame_period_s,
    )


# ---------------------------------------------------------------------- truth
@dataclass(frozen=True, eq=False)
class Truth:
    """Hindsight truth for egos ``E`` over ``T`` frames and ``N`` agents (arrays
    ``(T, E, N)``; a single ego gives ``E = 1``).

    - ``gap_m``: least box clearance at equal times in the window; NaN where the pair is
      never both recorded in it (and where the ego is not recorded at the frame, and for
      the ego itself);
    - ``pet_s``: post-encroachment time; NaN where the footprints do not meet;
    - ``observed``: steps of the window at which both are recorded (``0 .. H_steps+1``);
    - ``censored``: the window is not recorded enough (see the module docstring);
    - ``label``: 1 interaction, 0 none (window recorded enough), -1 unknown (censored
      without a close approach, or the ego or agent not recorded at the frame, or the
      ego itself, or a flagged track);
    - ``yielded``: the ego braked while the agent was ahead on its path (False where not
      applicable or flagged);
    - ``track_ok``: neither track has an inconsistent step in the window.
    """

    egos: np.ndarray  # (E,) column indices of the egos in the tracks
    gap_m: np.ndarray
    pet_s: np.ndarray
    observed: np.ndarray
    censored: np.ndarray
    label: np.ndarray
    horizon_steps: int
    settings: HindsightSettings
    yielded: np.ndarray | None = None
    track_ok: np.ndarray | None = None


def hindsight_truth(
    tracks: Tracks,
    egos: np.ndarray | Sequence[int] | int,
    *,
    settings: HindsightSettings | None = None,
) -> Truth:
    """The hindsight truth of every frame and agent, seen from each ego column in
    ``egos`` (indices into ``tracks``' agents). See the module docstring."""
    settings = settings or HindsightSettings()
    egos_arr = np.atleast_1d(np.asarray(egos, dtype=np.int64))
    n_t, n = tracks.valid.shape
    if egos_arr.size and (egos_arr.min() < 0 or egos_arr.max() >= n):
        raise RiskError(f"ego index out of range: the tracks hold {n} agents")
    h = settings.horizon_steps(tracks.dt_s)
    shape = (n_t, egos_arr.size, n)
    gap = np.full(shape, np.nan)
    pet = np.full(shape, np.nan)
    observed = np.zeros(shape, dtype=np.int64)
    ahead = np.zeros(shape, dtype=bool)
    speed = track_speeds(tracks)
    slowing = _slowing(tracks, speed)
    per_block = max(1, BLOCK_ELEMENTS // max(1, n_t * n))
    for start in range(0, egos_arr.size, per_block):  # blocks of egos, each vectorised
        block = egos_arr[start : start + per_block]
        sl = slice(start, start + block.size)
        gap[:, sl], pet[:, sl], observed[:, sl] = _block_truth(tracks, block, h)
        ahead[:, sl] = _block_ahead(tracks, block, speed, slowing, h)
    need = settings.coverage * (h + 1) - 1e-9
    censored = observed < need
    close = (gap <= settings.gap_m) | (pet <= settings.pet_s + 1e-9)
    label = np.where(close, LABEL_POSITIVE, np.where(censored, LABEL_UNKNOWN, LABEL_NEGATIVE))
    # Not applicable: the ego itself, or either one not recorded at the frame.
    here = tracks.valid[:, egos_arr][:, :, None] & tracks.valid[:, None, :]
    here &= egos_arr[None, :, None] != np.arange(n)[None, None, :]
    bad = forward_window_sum(inconsistent_steps(tracks, speed).astype(np.int64), h + 1) > 0
    track_ok = ~(bad[:, egos_arr][:, :, None] | bad[:, None, :])
    yielded = here & track_ok & ahead
    label = np.where(here & track_ok, label, LABEL_UNKNOWN).astype(np.int8)
    gap = np.where(here, gap, np.nan)
    pet = np.where(here, pet, np.nan)
    return Truth(
        egos=egos_arr,
        gap_m=gap,
        pet_s=pet,
        observed=observed,
        censored=censored | ~here,
        label=label,
        horizon_steps=h,
        settings=settings,
        yielded=yielded,
        track_ok=track_ok,
    )


# ---------------------------------------------------------------------- yielding, tracks
def _span_steps(dt_s: float) -> int:
    return max(1, round(SPEED_SPAN_S / dt_s))


def track_speeds(tracks: Tracks) -> np.ndarray:
    """Speed ``(T, N)`` m/s of every agent: the distance from frame ``k`` to frame
    ``k + m`` over ``m dt`` (``m`` frames span :data:`SPEED_SPAN_S`); NaN where either end
    is not recorded (or past the end)."""
    m = _span_steps(tracks.dt_s)
    n_t, n = tracks.valid.shape
    v = np.full((n_t, n), np.nan)
    if n_t > m:
        d = np.hypot(*(tracks.xy[m:] - tracks.xy[:-m]).transpose(2, 0, 1))
        ok = tracks.valid[m:] & tracks.valid[:-m]
        v[:-m] = np.where(ok, d / (m * tracks.dt_s), np.nan)
    return v


def _deceleration(speed: np.ndarray, dt_s: float) -> np.ndarray:
    """``(v[k] - v[k + m]) / (m dt)`` ``(T, N)``, NaN where unknown."""
    m = _span_steps(dt_s)
    out = np.full(speed.shape, np.nan)
    if speed.shape[0] > m:
        out[:-m] = (speed[:-m] - speed[m:]) / (m * dt_s)
    return out


def _slowing(tracks: Tracks, speed: np.ndarray) -> np.ndarray:
    """``(T, N)``: the agent is slowing down or standing at frame ``k``."""
    dec = _deceleration(speed, tracks.dt_s)
    return (np.nan_to_num(dec, nan=-np.inf) >= SLOWING_MPS2) | (
        np.nan_to_num(speed, nan=np.inf) <= STANDING_MPS
    )


def _braked(speed: np.ndarray, egos: np.ndarray, h: int) -> np.ndarray:
    """``(T, E)``: within the window of frame ``f`` the ego braked hard or fell to
    :data:`YIELD_SPEED_SHARE` of its speed at ``f`` (from :data:`YIELD_MIN_SPEED_MPS`)."""
    v = speed[:, egos]
    if v.shape[0] == 0:
        return np.zeros(v.shape, dtype=bool)
    low = forward_window_min(np.nan_to_num(v, nan=np.inf), h + 1)
    return (np.nan_to_num(v, nan=0.0) >= YIELD_MIN_SPEED_MPS) & (low <= YIELD_SPEED_SHARE * v)


def _block_ahead(
    tracks: Tracks, egos: np.ndarray, speed: np.ndarray, slowing: np.ndarray, h: int
) -> np.ndarray:
    """``(T, E, N)``: at some step of the window of frame ``f`` the agent was in the
    corridor ahead of the ego while the ego was slowing down or standing, and the ego braked
    (hard, or to half its speed) within that window."""
    x, y, hd = tracks.xy[..., 0], tracks.xy[..., 1], tracks.heading
    ok = tracks.valid
    e_x, e_y, e_h = x[:, egos][:, :, None], y[:, egos][:, :, None], hd[:, egos][:, :, None]
    dx, dy = x[:, None, :] - e_x, y[:, None, :] - e_y
    c, s = np.cos(e_h), np.sin(e_h)
    lon = dx * c + dy * s
    lat = np.abs(-dx * s + dy * c)
    v_e = np.nan_to_num(speed[:, egos], nan=0.0)[:, :, None]
    reach = (
        AHEAD_REACH_M + AHEAD_HEADWAY_S * v_e
        + (tracks.length[:, egos][:, :, None] + tracks.length[:, None, :]) / 2.0
    )  # fmt: skip
    half = (tracks.width[:, egos][:, :, None] + tracks.width[:, None, :]) / 2.0
    now = (lon > 0) & (lon <= reach) & (lat <= half + AHEAD_MARGIN_M)
    now &= ok[:, egos][:, :, None] & ok[:, None, :] & slowing[:, egos][:, :, None]
    now &= egos[None, :, None] != np.arange(tracks.n_agents)[None, None, :]
    ahead = forward_window_sum(now.astype(np.int64), h + 1) > 0
    dec = np.nan_to_num(_deceleration(speed, tracks.dt_s)[:, egos], nan=-np.inf)
    hard = forward_window_min(-dec, h + 1) <= -YIELD_DECEL_MPS2  # max deceleration
    return ahead & (hard | _braked(speed, egos, h))[:, :, None]


def inconsistent_steps(tracks: Tracks, speed: np.ndarray | None = None) -> np.ndarray:
    """``(T, N)`` bool: the frames at which an agent's track does what its kind cannot
    (:data:`KIND_LIMITS`): the speed implied since its previous recorded position (across
    any gap: a teleport) or the acceleration over :data:`SPEED_SPAN_S` is too high."""
    n_t, n = tracks.valid.shape
    bad = np.zeros((n_t, n), dtype=bool)
    if n_t < 2 or n == 0:
        return bad
    limits = np.array([KIND_LIMITS.get(int(k), KIND_LIMITS[0]) for k in tracks.kinds])
    v_max, a_max = limits[:, 0], limits[:, 1]
    frames = np.arange(n_t)[:, None]
    last = np.where(tracks.valid, frames, -1)
    prev = np.maximum.accumulate(np.vstack([np.full((1, n), -1), last[:-1]]), axis=0)
    has = tracks.valid & (prev >= 0)
    t_i, a_i = np.nonzero(has)
    p_i = prev[t_i, a_i]
    jump = np.hypot(*(tracks.xy[t_i, a_i] - tracks.xy[p_i, a_i]).T)
    implied = jump / ((t_i - p_i) * tracks.dt_s)
    bad[t_i[implied > v_max[a_i]], a_i[implied > v_max[a_i]]] = True
    v = track_speeds(tracks) if speed is None else speed
    m = _span_steps(tracks.dt_s)
    if n_t > m:
        acc = np.abs(v[m:] - v[:-m]) / (m * tracks.dt_s)
        bad[m:] |= np.nan_to_num(acc, nan=0.0) > a_max[None, :]
    return bad


def _block_truth(
    tracks: Tracks, egos: np.ndarray, h: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gap, PET and observed steps ``(T, E, N)`` for a block of egos."""
    n_t, n = tracks.valid.shape
    x, y = tracks.xy[..., 0], tracks.xy[..., 1]
    hd, ln, wd, ok = tracks.heading, tracks.length, tracks.width, tracks.valid
    not_self = egos[:, None] != np.arange(n)[None, :]  # (E, N)

    def ego(a: np.ndarray) -> np.ndarray:
        return a[:, egos][:, :, None]  # (T, E, 1)

    def other(a: np.ndarray) -> np.ndarray:
        return a[:, None, :]  # (T, 1, N)

    both = ego(ok) & other(ok) & not_self  # (T, E, N)
    t_i, e_i, a_i = np.nonzero(both)  # only where both are recorded
    c_i = egos[e_i]
    gap_now = np.full(both.shape, np.inf)
    gap_now[t_i, e_i, a_i] = box_gap(
        x[t_i, c_i], y[t_i, c_i], hd[t_i, c_i], ln[t_i, c_i], wd[t_i, c_i],
        x[t_i, a_i], y[t_i, a_i], hd[t_i, a_i], ln[t_i, a_i], wd[t_i, a_i],
    )  # fmt: skip
    gap = forward_window_min(gap_now, h + 1)
    gap[~np.isfinite(gap)] = np.nan
    observed = forward_window_sum(both.astype(np.int64), h + 1)

    pet = np.full((n_t, egos.size, n), np.nan)
    pe, pa = _pet_candidates(tracks, egos)
    if pe.size:
        pet[:, pe, pa] = _pet_pairs(tracks, egos[pe], pa, h)
    return gap, pet, observed


def _pet_candidates(tracks: Tracks, egos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ego position in ``egos``, agent column) of the pairs whose footprints can meet at
    all: the axis-aligned boxes around their whole recorded sweeps intersect."""
    x, y, ok = tracks.xy[..., 0], tracks.xy[..., 1], tracks.valid
    r = np.hypot(tracks.length, tracks.width) / 2.0
    lo_x = np.where(ok, x - r, np.inf).min(axis=0)
    hi_x = np.where(ok, x + r, -np.inf).max(axis=0)
    lo_y = np.where(ok, y - r, np.inf).min(axis=0)
    hi_y = np.where(ok, y + r, -np.inf).max(axis=0)
    e = egos[:, None]
    meet = (lo_x[e] <= hi_x[None, :]) & (lo_x[None, :] <= hi_x[e])
    meet &= (lo_y[e] <= hi_y[None, :]) & (lo_y[None, :] <= hi_y[e])
    meet &= e != np.arange(tracks.n_agents)[None, :]
    ego_pos, agent = np.nonzero(meet)
    return ego_pos, agent


def _pet_pairs(tracks: Tracks, e_col: np.ndarray, a_col: np.ndarray, h: int) -> np.ndarray:
    """PET ``(T, P)`` of the pairs (``e_col``, ``a_col``) over every frame's window.

    One vectorised pass per lag ``d = j - i`` (ego frame ``i``, agent frame ``j``,
    ``|d| <= h``), by increasing ``|d|`` so that the first lag that meets is the least: a
    bounding-circle test, then the separating-axis test on the survivors. An overlap at
    ``(i, j)`` belongs to the window of frame ``f`` when ``max(i, j) - h <= f <= min(i,
    j)``; those frames get ``|d| dt`` unless a smaller lag already gave them a value.
    """
    n_t = tracks.n_frames
    cols = {
        "x": tracks.xy[..., 0], "y": tracks.xy[..., 1], "h": tracks.heading,
        "l": tracks.length, "w": tracks.width, "ok": tracks.valid,
        "r": np.hypot(tracks.length, tracks.width) / 2.0,
    }  # fmt: skip
    ego = {k: v[:, e_col] for k, v in cols.items()}  # (T, P)
    oth = {k: v[:, a_col] for k, v in cols.items()}
    n_p = e_col.size
    pet = np.full((n_t, n_p), np.nan)
    reach_lag = min(h, n_t - 1)  # lags of n_t frames or more pair no frames at all
    for lag in sorted(range(-reach_lag, reach_lag + 1), key=abs):
        k = abs(lag)
        m = n_t - k  # pairs (i, j) indexed by min(i, j) = 0 .. m - 1
        ei = slice(0, m) if lag >= 0 else slice(k, n_t)  # ego frames
        aj = slice(k, n_t) if lag >= 0 else slice(0, m)  # agent frames
        dx = ego["x"][ei] - oth["x"][aj]
        dy = ego["y"][ei] - oth["y"][aj]
        reach = ego["r"][ei] + oth["r"][aj]
        near = ego["ok"][ei] & oth["ok"][aj] & (dx * dx + dy * dy <= reach * reach)
        mi, pi = np.nonzero(near)
        if mi.size == 0:
            continue
        ti, tj = mi + ei.start, mi + aj.start
        meet = boxes_overlap(
            ego["x"][ti, pi], ego["y"][ti, pi], ego["h"][ti, pi], ego["l"][ti, pi], ego["w"][ti, pi],
            oth["x"][tj, pi], oth["y"][tj, pi], oth["h"][tj, pi], oth["l"][tj, pi], oth["w"][tj, pi],
        )  # fmt: skip
        mi, pi = mi[meet], pi[meet]
        if mi.size == 0:
            continue
        # Frames max(0, m + k - h) .. m of pair p get k: +1 / -1 on a difference array
        # over the pairs that meet at this lag, then a cumulative sum over frames.
        up, local = np.unique(pi, return_inverse=True)
        diff = np.zeros((n_t + 1, up.size), dtype=np.int64)
        np.add.at(diff, (np.maximum(mi + k - h, 0), local), 1)
        np.add.at(diff, (mi + 1, local), -1)
        covered = np.cumsum(diff[:n_t], axis=0) > 0
        sub = pet[:, up]
        pet[:, up] = np.where(covered & np.isnan(sub), k * tracks.dt_s, sub)
    return pet


#: (frame, ego, agent) entries of one :func:`hindsight_truth` call in
#: :func:`truth_for_rows` (about 60 bytes each with the temporaries: 0.5 GB).
TRUTH_BLOCK_ELEMENTS = 8_000_000

#: Truths up to this many (frame, ego, agent) entries (about 26 bytes each) are kept
#: with their tracks for the next :func:`truth_for_rows` call on the same egos.
SHARED_TRUTH_MAX = 2_000_000


def _shared_truth(tracks: Tracks, egos: np.ndarray, settings: HindsightSettings) -> Truth:
    """:func:`hindsight_truth`, computed once per tracks, egos and settings when small: a
    replay's recording and table both label their rows from the same tracks (the
    second computation cost the demo's table 40 ms). Tracks are immutable."""
    if tracks.n_frames * egos.size * tracks.n_agents > SHARED_TRUTH_MAX:
        return hindsight_truth(tracks, egos, settings=settings)
    kept: dict[tuple[bytes, HindsightSettings], Truth] = tracks.__dict__.setdefault(
        "_shared_truths", {}
    )
    key = (egos.astype(np.int64).tobytes(), settings)
    if key not in kept:
        kept[key] = hindsight_truth(tracks, egos, settings=settings)
    return kept[key]


@dataclass(frozen=True, eq=False)
class RowTruth:
    """The truth of table rows, each ``(R,)``: ``gap_m``, ``pet_s``, ``label`` (codes),
    ``complete`` (the window is recorded for both: not censored), ``yielded`` and
    ``track_ok`` (see :class:`Truth`); rows outside the tracks: NaN, unknown, False, False,
    True."""

    gap_m: np.ndarray
    pet_s: np.ndarray
    label: np.ndarray
    complete: np.ndarray
    yielded: np.ndarray
    track_ok: np.ndarray


def rows_truth(
    tracks: Tracks,
    t_s: np.ndarray,
    ego_id: np.ndarray,
    agent_id: np.ndarray,
    *,
    settings: HindsightSettings | None = None,
) -> RowTruth:
    """:func:`truth_for_rows` with the complete-window, yielded and track flags."""
    t_s = np.asarray(t_s, dtype=np.float64)
    n = t_s.size
    out = RowTruth(
        np.full(n, np.nan), np.full(n, np.nan), np.full(n, LABEL_UNKNOWN, dtype=np.int8),
        np.zeros(n, dtype=bool), np.zeros(n, dtype=bool), np.ones(n, dtype=bool),
    )  # fmt: skip
    if n == 0:
        return out
    egos, ego_row = np.unique(np.asarray(ego_id, dtype=np.int64), return_inverse=True)
    ego_col = tracks.index_of(egos)
    truth = _shared_truth(tracks, np.maximum(ego_col, 0), settings or HindsightSettings())
    k = tracks.frame_of(t_s)
    a = tracks.index_of(np.asarray(agent_id, dtype=np.int64))
    ok = (k >= 0) & (k < tracks.n_frames) & (a >= 0) & (ego_col[ego_row] >= 0)
    idx = (k[ok], ego_row[ok], a[ok])
    out.gap_m[ok], out.pet_s[ok], out.label[ok] = (
        truth.gap_m[idx],
        truth.pet_s[idx],
        truth.label[idx],
    )
    out.complete[ok] = ~truth.censored[idx]
    if truth.yielded is not None and truth.track_ok is not None:
        out.yielded[ok] = truth.yielded[idx]
        out.track_ok[ok] = truth.track_ok[idx]
    return out


def truth_for_rows(
    tracks: Tracks,
    t_s: np.ndarray,
    ego_id: np.ndarray,
    agent_id: np.ndarray,
    *,
    settings: HindsightSettings | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The truth of arbitrary rows ``(t_s, ego_id, agent_id)`` (each ``(R,)``), as the
    table and the recording need it: ``(gap_m, pet_s, label)``, ``(R,)`` each; NaN gap or
    PET and ``LABEL_UNKNOWN`` for rows outside the tracks (an unknown time, ego or agent).

    The egos of the rows are computed together (one :func:`hindsight_truth` call), in
    blocks of egos whose ``(T, E, N)`` arrays stay within :data:`TRUTH_BLOCK_ELEMENTS`
    (``--ego all`` on a long recording asked for gigabytes at once).
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    n = t_s.size
    gap, pet = np.full(n, np.nan), np.full(n, np.nan)
    label = np.full(n, LABEL_UNKNOWN, dtype=np.int8)
    if n == 0:
        return gap, pet, label
    egos, ego_row = np.unique(np.asarray(ego_id, dtype=np.int64), return_inverse=True)
    ego_col = tracks.index_of(egos)
    settings = settings or HindsightSettings()
    k = tracks.frame_of(t_s)
    a = tracks.index_of(np.asarray(agent_id, dtype=np.int64))
    ok = (k >= 0) & (k < tracks.n_frames) & (a >= 0) & (ego_col[ego_row] >= 0)
    per_ego = max(1, tracks.n_frames * tracks.n_agents)
    if egos.size * per_ego <= TRUTH_BLOCK_ELEMENTS:
        truth = _shared_truth(tracks, np.maximum(ego_col, 0), settings)
        idx = (k[ok], ego_row[ok], a[ok])
        gap[ok], pet[ok], label[ok] = truth.gap_m[idx], truth.pet_s[idx], truth.label[idx]
        return gap, pet, label
    step = max(1, TRUTH_BLOCK_ELEMENTS // per_ego)
    for start in range(0, egos.size, step):  # blocks of egos, each vectorised
        cols = np.maximum(ego_col[start : start + step], 0)
        truth = hindsight_truth(tracks, cols, settings=settings)
        sel = ok & (ego_row >= start) & (ego_row < start + step)
        idx = (k[sel], ego_row[sel] - start, a[sel])
        gap[sel], pet[sel], label[sel] = truth.gap_m[idx], truth.pet_s[idx], truth.label[idx]
    return gap, pet, label
