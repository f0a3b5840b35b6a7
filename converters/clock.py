"""Check a scene's clock against its motion, and correct a clean factor in its time step.

Some recorded files carry a wrong time step: the SinD files of the corpus are labelled
0.1 s while their positions move as if 0.5 s passed between steps, and most highD files
0.1 s for 0.2 s. The recorded speeds are the plausible ones, so the label is wrong. Every
converter runs the check of this module on its track table before the scene is built
(:func:`converters.tracks.build_scene`), so one implementation serves every source.

The figures (all vectorised over time x agents; no loop over agents):

- **clock ratio**: over windows in which a track is valid throughout and its recorded
  speed averages above :data:`MOVING_SPEED_MS`, the distance between the window's end
  positions over the distance the recorded speeds cover in it (their trapezoid integral).
  A window is as many steps as moving agents need to cover :data:`WINDOW_M` (from the
  median step of the scene's moving agents): long enough that centimetre position noise
  does not inflate the distance, short enough that a turn barely shortens the chord, and
  the same whatever the time step says. The ratio is then the factor by which the true
  step exceeds the labelled one. Per agent: the median over its windows;
  per scene: the median over agents with at least :data:`MIN_WINDOWS` windows. Needs
  recorded speeds: where a source derives speeds from positions (Argoverse 2 Sensor, a
  CommonRoad state without ``velocity``) the ratio is 1 by construction and is not
  measured;
- **heading**: share of moving windows of vehicles and cyclists whose direction of motion
  is more than :data:`HEADING_TOLERANCE_RAD` from the circular mean of the headings at
  the window's ends (pedestrians are left out: datasets give their body orientation, or
  derive it from the velocity);
- **bounds per kind** (:data:`BOUNDS`): rows whose speed (recorded, or derived from the
  positions over a window) or acceleration (speed change over a window) exceeds what the
  kind can do;
- **teleports**: steps between consecutive valid states that move farther than the kind's
  top speed allows (plus :data:`TELEPORT_SLACK_M` for position noise).

A row (one valid state) is **bad** when it starts a moving window whose own ratio is more
than :data:`WINDOW_RATIO_TOLERANCE` off 1 at the time step used, starts a heading mismatch, breaks
a bound, or ends a teleport. A scene **fails** the check (``replay inspect --check``)
when its clock ratio is measured and more than :data:`RATIO_TOLERANCE` off 1 (after any
correction), or when more than :data:`BAD_ROW_LIMIT` of its rows are bad.

Correction (``--time-step auto``): when the ratio is more than :data:`RATIO_TOLERANCE` off
1 but within :data:`RATIO_TOLERANCE` of a clean factor (:data:`CLEAN_FACTORS`: 2, 2.5, 3,
4, 5, 10 or their inverses), measured on at least :data:`MIN_AGENTS` agents of which at
least :data:`MIN_AGREEING` agree with the factor to :data:`AGENT_TOLERANCE`, the time step
becomes the file's times the factor. ``file`` keeps the file's step (and still warns), a
number forces a step.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from converters.errors import ConversionError
from risk.frame import Frame, Kind

TimeStep = str | float
"""``"auto"``, ``"file"`` or a time step in seconds (``--time-step``)."""
TIME_STEP_MODES: tuple[str, ...] = ("auto", "file")

MOVING_SPEED_MS = 2.0
"""Windows whose recorded speed averages above this (m/s) measure the clock ratio."""
WINDOW_M = 2.0
"""Windows of the clock ratio and the heading check span about this much travel (m)."""
ACCEL_WINDOW_S = 0.4
"""Accelerations are speed changes over at least this long (s, at the step used): the
recorded speeds' noise over one 0.04 s step would read as metres per second squared."""
MIN_WINDOWS = 3
"""An agent with fewer moving windows gives no ratio of its own."""
MIN_AGENTS = 2
"""A correction needs the ratios of at least this many agents."""
RATIO_TOLERANCE = 0.05
"""The clock ratio is consistent within this of 1; a factor is detected within this."""
AGENT_TOLERANCE = 0.10
"""An agent agrees with a factor when its ratio is within this of it."""
MIN_AGREEING = 0.7
"""A factor is corrected when at least this share of the measured agents agrees."""
WINDOW_RATIO_TOLERANCE = 0.25
"""A moving window whose own ratio is this far off 1 marks a bad row."""
HEADING_TOLERANCE_RAD = math.pi / 4
"""Heading and direction of motion further apart than this (45 deg) mark a bad row."""
TELEPORT_SLACK_M = 1.0
"""Position noise allowed on top of the top speed between two consecutive states."""
BAD_ROW_LIMIT = 0.05
"""A scene with more than this share of bad rows fails the check (and is warned about)."""

BASE_FACTORS: tuple[float, ...] = (2.0, 2.5, 3.0, 4.0, 5.0, 10.0)
CLEAN_FACTORS: tuple[float, ...] = tuple(sorted({*BASE_FACTORS, *(1.0 / f for f in BASE_FACTORS)}))
"""Factors a time step is plausibly off by: frame rates of 5, 10, 12.5, 25, 30, 50 Hz and
a step label off by one such ratio."""


@dataclass(frozen=True)
class Bounds:
    """What an agent of one kind can do: top speed (m/s) and acceleration (m/s^2)."""

    speed_ms: float
    accel_ms2: float


BOUNDS: Mapping[int, Bounds] = {
    # Cars, trucks, buses and motorcycles: 250 km/h; a hard stop or a sporty start with
    # drone-track noise on top.
    int(Kind.VEHICLE): Bounds(70.0, 15.0),
    # A racing bicycle downhill; a hard brake.
    int(Kind.CYCLIST): Bounds(20.0, 8.0),
    # A sprinter (and INTERACTION's "pedestrian/bicycle", which mixes cyclists in).
    int(Kind.PEDESTRIAN): Bounds(12.0, 8.0),
    int(Kind.OTHER): Bounds(70.0, 15.0),
}


@dataclass(frozen=True)
class ClockCheck:
    """The figures of one scene's check (JSON-able; ``None`` where not measurable)."""

    file_step_s: float  # the time step the file gives
    step_s: float  # the time step used (the scene's)
    choice: str  # "auto", "file" or "forced"
    corrected: bool  # step_s differs from the file's
    factor: float | None  # the clean factor found (auto), else None
    speeds_recorded: bool  # the source records speeds (the ratio is measurable)
    ratio_file: float | None  # clock ratio at the file's step
    ratio: float | None  # clock ratio at the step used
    agents_measured: int  # agents with a ratio of their own
    agents_agreeing: float | None  # share of them within AGENT_TOLERANCE of ratio_file
    moving_windows: int
    heading_windows: int
    heading_mismatch_share: float | None
    speed_violations: int
    accel_violations: int
    teleports: int
    rows: int
    bad_rows: int
    bad_row_share: float
    fails: bool
    reasons: tuple[str, ...]

    def to_json(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))


@dataclass(frozen=True)
class Motion:
    """The arrays a check reads: ``T`` steps x ``N`` agents (a :class:`TrackTable`'s, or
    a scene's frames)."""

    t_s: np.ndarray  # (T,) increasing
    xy: np.ndarray  # (T, N, 2)
    heading: np.ndarray  # (T, N)
    speed: np.ndarray  # (T, N)
    valid: np.ndarray  # (T, N) bool, values finite where valid
    kinds: np.ndarray  # (N,)
    speed_measured: np.ndarray  # (T, N) bool: the source's own speed (not derived)


@dataclass(frozen=True)
class _Figures:
    ratio: float | None
    agent_ratios: np.ndarray  # (A,) ratios of the measured agents
    moving_windows: int
    heading_windows: int
    heading_mismatches: int
    speed_violations: int
    accel_violations: int
    teleports: int
    rows: int
    bad_rows: int


def parse_time_step(value: str | float) -> TimeStep:
    """``auto``, ``file`` or a positive number of seconds; ConversionError otherwise."""
    if isinstance(value, str) and value.strip().lower() in TIME_STEP_MODES:
        return value.strip().lower()
    try:
        seconds = float(value)
    except (TypeError, ValueError):
        raise ConversionError(
            f"time step must be 'auto', 'file' or seconds, got {value!r}"
        ) from None
    if not (math.isfinite(seconds) and 0 < seconds <= 3600):
        raise ConversionError(f"time step must be > 0 and at most 3600 s, got {value!r}")
    return seconds


def window_steps(motion: Motion) -> int:
    """Steps per window of the clock ratio: enough for the median step of the moving
    agents (recorded speed above :data:`MOVING_SPEED_MS` at both ends, or any moving pair
    where no speed is recorded) to add up to :data:`WINDOW_M`; at most a quarter of the
    scene. Independent of the time step's value."""
    valid = motion.valid
    n_steps = valid.shape[0]
    if n_steps < 2:
        return 1
    pair = valid[1:] & valid[:-1]
    step = np.linalg.norm(motion.xy[1:] - motion.xy[:-1], axis=2)
    fast = motion.speed > MOVING_SPEED_MS
    recorded = motion.speed_measured[1:] & motion.speed_measured[:-1]
    moving = pair & (step > 0) & np.where(recorded, fast[1:] & fast[:-1], True)
    if not moving.any():
        return 1
    typical = float(np.median(step[moving]))
    return int(np.clip(math.ceil(WINDOW_M / typical - 1e-9), 1, max(1, n_steps // 4)))


def accel_steps(t_s: np.ndarray) -> int:
    """Steps over which accelerations are measured at the times ``t_s``."""
    if t_s.size < 2:
        return 1
    step = float(np.median(np.diff(t_s)))
    return max(1, math.ceil(ACCEL_WINDOW_S / step - 1e-9)) if step > 0 else 1


def clean_factor(ratio: float) -> float | None:
    """The clean factor within :data:`RATIO_TOLERANCE` of ``ratio``, or None."""
    if not (math.isfinite(ratio) and ratio > 0):  # positions that stand still: no factor
        return None
    best = min(CLEAN_FACTORS, key=lambda f: abs(math.log(ratio / f)))
    return best if abs(ratio / best - 1.0) <= RATIO_TOLERANCE else None


def check_motion(
    motion: Motion,
    file_step_s: float,
    time_step: TimeStep = "auto",
    *,
    window: int | None = None,
) -> ClockCheck:
    """Measure ``motion`` at the file's step, choose the step (``time_step``) and measure
    again at it. ``motion.t_s`` is on the file's time base; ``window`` (steps) defaults to
    :func:`window_steps`."""
    window = window or window_steps(motion)
    at_file = _measure(motion, 1.0, window)
    factor: float | None = None
    if time_step == "auto":
        if at_file.ratio is not None and abs(at_file.ratio - 1.0) > RATIO_TOLERANCE:
            found = clean_factor(at_file.ratio)
            if (
                found is not None
                and at_file.agent_ratios.size >= MIN_AGENTS
                and _agreeing(at_file.agent_ratios, found) >= MIN_AGREEING
            ):
                factor = found
        scale, choice = (factor or 1.0), "auto"
    elif time_step == "file":
        scale, choice = 1.0, "file"
    else:
        scale, choice = float(time_step) / file_step_s, "forced"
    step_s = file_step_s * scale if choice != "forced" else float(time_step)
    used = at_file if scale == 1.0 else _measure(motion, scale, window)
    reasons = _failures(used)
    return ClockCheck(
        file_step_s=float(file_step_s),
        step_s=float(round(step_s, 12)),
        choice=choice,
        corrected=not math.isclose(step_s, file_step_s, rel_tol=1e-9),
        factor=factor,
        speeds_recorded=bool(motion.speed_measured[motion.valid].any()),
        ratio_file=at_file.ratio,
        ratio=used.ratio,
        agents_measured=int(at_file.agent_ratios.size),
        agents_agreeing=(
            _agreeing(at_file.agent_ratios, at_file.ratio) if at_file.ratio is not None else None
        ),
        moving_windows=used.moving_windows,
        heading_windows=used.heading_windows,
        heading_mismatch_share=(
            used.heading_mismatches / used.heading_windows if used.heading_windows else None
        ),
        speed_violations=used.speed_violations,
        accel_violations=used.accel_violations,
        teleports=used.teleports,
        rows=used.rows,
        bad_rows=used.bad_rows,
        bad_row_share=used.bad_rows / used.rows if used.rows else 0.0,
        fails=bool(reasons),
        reasons=reasons,
    )


def _failures(f: _Figures) -> tuple[str, ...]:
    reasons = []
    if f.ratio is not None and abs(f.ratio - 1.0) > RATIO_TOLERANCE:
        reasons.append(
            f"positions move {f.ratio:.2f}x the recorded speeds (more than"
            f" {RATIO_TOLERANCE:.0%} off)"
        )
    if f.rows and f.bad_rows / f.rows > BAD_ROW_LIMIT:
        reasons.append(f"{f.bad_rows / f.rows:.1%} of rows bad (limit {BAD_ROW_LIMIT:.0%})")
    return tuple(reasons)


def _agreeing(agent_ratios: np.ndarray, factor: float) -> float:
    if agent_ratios.size == 0:
        return 0.0
    return float((np.abs(agent_ratios / factor - 1.0) <= AGENT_TOLERANCE).mean())


BLOCK_CELLS = 1 << 20
"""Agents are measured in blocks of about this many (step, agent) cells, so that a long
scenario's check needs a bounded amount of memory on top of its track table."""


def _measure(motion: Motion, scale: float, k: int) -> _Figures:
    """Figures of ``motion`` with its times multiplied by ``scale``; speeds derived from
    positions (not measured) scale by ``1 / scale`` with them. A moving window whose own
    ratio is off 1 (the clock of these times) marks its first row bad. Agents are
    independent, so blocks of them are measured apart and the counts added."""
    n_steps, n_agents = motion.valid.shape
    width = max(1, BLOCK_CELLS // max(n_steps, 1))
    parts = [
        _measure_block(motion, slice(lo, lo + width), scale, k)
        for lo in range(0, max(n_agents, 1), width)
    ]
    ratios = np.concatenate([p.agent_ratios for p in parts])
    counts = {name: sum(getattr(p, name) for p in parts) for name in _COUNTS}
    return _Figures(
        ratio=float(np.median(ratios)) if ratios.size else None, agent_ratios=ratios, **counts
    )


_COUNTS = ("moving_windows", "heading_windows", "heading_mismatches", "speed_violations",
           "accel_violations", "teleports", "rows", "bad_rows")  # fmt: skip


def _bound_table(field: str) -> np.ndarray:
    """A bound per kind code (0..3); codes beyond it read as ``other``."""
    return np.array([getattr(BOUNDS[int(kind)], field) for kind in Kind], dtype=np.float64)


def _measure_block(motion: Motion, cols: slice, scale: float, k: int) -> _Figures:
    """:func:`_measure` of the agents ``cols``."""
    motion = Motion(
        motion.t_s, motion.xy[:, cols], motion.heading[:, cols], motion.speed[:, cols],
        motion.valid[:, cols], np.asarray(motion.kinds)[cols], motion.speed_measured[:, cols],
    )  # fmt: skip
    valid = motion.valid
    n_steps, n_agents = valid.shape
    t = motion.t_s * scale
    measured = motion.speed_measured & valid
    speed = np.where(valid, np.where(measured, motion.speed, motion.speed / scale), 0.0)
    xy = np.where(valid[:, :, None], motion.xy, 0.0)
    heading = np.where(valid, motion.heading, 0.0)
    kinds = np.asarray(motion.kinds, dtype=np.int64)
    code = np.where((kinds >= 0) & (kinds < len(Kind)), kinds, int(Kind.OTHER))
    top_speed = _bound_table("speed_ms")[code]
    top_accel = _bound_table("accel_ms2")[code]
    bad = np.zeros((n_steps, n_agents), dtype=bool)
    # Teleports: consecutive steps, both valid.
    pair = valid[1:] & valid[:-1]
    dt1 = np.diff(t)[:, None]
    step_dist = np.linalg.norm(xy[1:] - xy[:-1], axis=2)
    teleport = pair & (step_dist > top_speed[None, :] * dt1 + TELEPORT_SLACK_M)
    bad[1:] |= teleport
    # Speed bound on the recorded (or derived) speed of every row.
    over_speed = valid & (speed > top_speed[None, :])
    # Runs of valid pairs: window [i, i + k] is whole when its k pairs are all valid.
    runs = np.concatenate([np.zeros((1, n_agents), np.int64), np.cumsum(pair, axis=0)])
    # Acceleration: the speed change over ACCEL_WINDOW_S at these times.
    ka = accel_steps(t)
    n_accel = 0
    if n_steps > ka:
        accel = np.abs(speed[ka:] - speed[:-ka]) / (t[ka:] - t[:-ka])[:, None]
        over_accel = ((runs[ka:] - runs[:-ka]) == ka) & (accel > top_accel[None, :])
        bad[:-ka] |= over_accel
        n_accel = int(over_accel.sum())
    if n_steps <= k:
        bad |= over_speed
        return _Figures(
            None, np.empty(0), 0, 0, 0, int(over_speed.sum()), n_accel, int(teleport.sum()),
            int(valid.sum()), int((bad & valid).sum()),
        )  # fmt: skip
    whole = (runs[k:] - runs[:-k]) == k  # (W, N)
    span = (t[k:] - t[:-k])[:, None]  # (W, 1)
    trapezoid = np.where(pair, 0.5 * (speed[1:] + speed[:-1]) * dt1, 0.0)
    covered_cum = np.concatenate([np.zeros((1, n_agents)), np.cumsum(trapezoid, axis=0)])
    covered = covered_cum[k:] - covered_cum[:-k]  # distance the speeds cover (W, N)
    m_pair = measured[1:] & measured[:-1]
    m_runs = np.concatenate([np.zeros((1, n_agents), np.int64), np.cumsum(m_pair, axis=0)])
    all_measured = (m_runs[k:] - m_runs[:-k]) == k
    chord = xy[k:] - xy[:-k]
    distance = np.linalg.norm(chord, axis=2)
    mean_speed = covered / span
    moving = whole & all_measured & (mean_speed > MOVING_SPEED_MS)
    ratio_w = np.where(moving, distance / np.where(moving, covered, 1.0), np.nan)
    enough = (~np.isnan(ratio_w)).sum(axis=0) >= MIN_WINDOWS
    agent_ratios = _column_medians(ratio_w)[enough]
    ratio = float(np.median(agent_ratios)) if agent_ratios.size else None
    bad[:-k] |= moving & (np.abs(ratio_w - 1.0) > WINDOW_RATIO_TOLERANCE)
    # Heading against the direction of motion (vehicles and cyclists moving by position).
    steers = (kinds == int(Kind.VEHICLE)) | (kinds == int(Kind.CYCLIST))
    in_motion = whole & (distance / span > MOVING_SPEED_MS) & steers[None, :]
    mean_heading = np.arctan2(
        np.sin(heading[k:]) + np.sin(heading[:-k]), np.cos(heading[k:]) + np.cos(heading[:-k])
    )
    direction = np.arctan2(chord[..., 1], chord[..., 0])
    off = np.abs(np.angle(np.exp(1j * (direction - mean_heading))))
    mismatch = in_motion & (off > HEADING_TOLERANCE_RAD)
    bad[:-k] |= mismatch
    # Where no speed is recorded, the speed the positions give over a window.
    over_speed[:-k] |= whole & ~all_measured & (distance / span > top_speed[None, :])
    bad |= over_speed
    return _Figures(
        ratio=ratio,
        agent_ratios=agent_ratios,
        moving_windows=int(moving.sum()),
        heading_windows=int(in_motion.sum()),
        heading_mismatches=int(mismatch.sum()),
        speed_violations=int(over_speed.sum()),
        accel_violations=n_accel,
        teleports=int(teleport.sum()),
        rows=int(valid.sum()),
        bad_rows=int((bad & valid).sum()),
    )


def _column_medians(values: np.ndarray) -> np.ndarray:
    """Median of each column over its non-NaN entries (NaN for an empty column)."""
    count = (~np.isnan(values)).sum(axis=0)
    ordered = np.sort(values, axis=0)  # NaN sorts last
    cols = np.arange(values.shape[1])
    lo = ordered[np.maximum(count - 1, 0) // 2, cols]
    hi = ordered[np.minimum(count // 2, values.shape[0] - 1), cols]
    return np.where(count > 0, 0.5 * (lo + hi), np.nan)


def warning_line(source: str, check: ClockCheck) -> str | None:
    """The one-line warning for stderr, or None when the clock agrees with the motion."""
    what = (
        f"positions move {check.ratio_file:.2f}x the recorded speeds"
        f" (median over {check.agents_measured} agents above {MOVING_SPEED_MS:g} m/s,"
        f" {check.agents_agreeing:.0%} of them within {AGENT_TOLERANCE:.0%} of it)"
        if check.ratio_file is not None
        else ""
    )
    bad = f"{check.bad_row_share:.1%} of rows bad ({_bad_kinds(check)})"
    if check.corrected and check.choice == "auto":
        return (
            f"warning: {source}: time step {check.file_step_s:g} s -> {check.step_s:g} s:"
            f" {what}; corrected (--time-step file keeps {check.file_step_s:g} s)"
        )
    if check.choice == "forced" and check.corrected:
        tail = f"; clock check: {'; '.join(check.reasons)}" if check.fails else ""
        return (
            f"warning: {source}: time step {check.file_step_s:g} s -> {check.step_s:g} s"
            f" (--time-step {check.step_s:g}){tail}"
        )
    if not check.fails:
        return None
    if check.choice == "file" and check.ratio_file is not None:
        factor = clean_factor(check.ratio_file)
        hint = f" (a clean factor {factor:g}: --time-step auto corrects it)" if factor else ""
        return (
            f"warning: {source}: clock check: {what}{hint}; kept the file's"
            f" {check.file_step_s:g} s (--time-step file); {bad}"
        )
    clock = f"{what}, no clean factor; " if what and check.ratio is not None else ""
    if check.ratio is not None and abs(check.ratio - 1.0) <= RATIO_TOLERANCE:
        clock = ""
    return (
        f"warning: {source}: clock check: {clock}{bad}; converted with the time step"
        f" {check.step_s:g} s"
    )


def _bad_kinds(check: ClockCheck) -> str:
    share = check.heading_mismatch_share
    heading = f"{share:.1%} heading mismatches" if share is not None else "no heading check"
    return (
        f"{heading}, {check.speed_violations} over the speed bound,"
        f" {check.accel_violations} over the acceleration bound, {check.teleports} teleports"
    )


def motion_from_frames(frames: Sequence[Frame], *, speeds_recorded: bool = True) -> Motion:
    """A scene's frames as the arrays of a check (agents matched by id across frames;
    one pass over the frames, none over agents)."""
    ids = np.unique(np.concatenate([f.ids for f in frames])) if frames else np.empty(0, np.int64)
    shape = (len(frames), ids.size)
    xy, heading, speed = np.zeros((*shape, 2)), np.zeros(shape), np.zeros(shape)
    valid = np.zeros(shape, dtype=bool)
    kinds = np.full(ids.size, int(Kind.OTHER), dtype=np.int64)
    for k, frame in enumerate(frames):
        col = np.searchsorted(ids, frame.ids)
        xy[k, col] = frame.xy
        heading[k, col] = frame.heading
        speed[k, col] = frame.speed
        valid[k, col] = frame.valid
        kinds[col[frame.valid]] = frame.kinds[frame.valid]
    return Motion(
        t_s=np.array([f.t for f in frames], dtype=np.float64),
        xy=xy,
        heading=heading,
        speed=speed,
        valid=valid,
        kinds=kinds,
        speed_measured=np.full(shape, speeds_recorded),
    )
