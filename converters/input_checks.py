"""The one rule for bad values in recorded input, and the size bounds of a conversion.

**Bad states.** A state (one track at one time step) that the source marks as observed
but whose position, heading, speed, length or width is NaN, infinite or negative (speeds
and sizes), or whose position is beyond the scene format's exact range (2**53 mm), is
*bad*. Every converter applies :func:`apply_bad_rule` to its bad states (and the CSV
reader to its bad rows), so they are treated alike:

- by default the conversion stops with one error naming the file and the first bad
  record (track and time, or CSV line) and saying what to do;
- with ``--skip-bad`` the bad states are dropped, their count is printed with the other
  skipped records and stored in the scene's metadata (``bad_states_dropped``).

Nothing is ever dropped silently. Documented in docs/recorded-data.md.

**Bounds.** :func:`check_grid` refuses a time grid whose dense arrays would not fit in
memory (e.g. an AV2 ``timestep`` of 1e12), before anything is allocated.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from converters.errors import ConversionError
from outputs.memory import available_bytes

MAX_ABS_POSITION_M = 2.0**53 / 1000.0  # the scene format stores millimetres exactly up to 2**53
MAX_STEPS = 1_000_000  # time steps of one scenario (at 10 Hz: 28 hours)
BYTES_PER_STATE = 64  # xy, heading, speed, length, width, valid and the frames built from them
# Each step also becomes a frame (objects, messages): measured 4.2 kB and 0.47 ms per step
# (a ScenarioNet scenario of 100,000 steps and 2 tracks: 420 MB peak, 47 s). 10**7 steps
# passed the old bound and ran out of memory after minutes (issue 36).
BYTES_PER_STEP = 4096
SHOWN = 5  # bad records named in a --skip-bad note
MAX_GAP_STEPS = 10_000  # a gap inside one recording (at 10 Hz: 17 minutes)


@dataclass
class Skipped:
    """What a ``skip_bad`` conversion left out, one line per record, and why."""

    what: list[str] = field(default_factory=list)

    def add(self, message: str) -> None:
        self.what.append(message)

    def __len__(self) -> int:
        return len(self.what)


def apply_bad_rule(
    bad: np.ndarray,
    describe: Callable[[int], str],
    *,
    source: str,
    skip_bad: bool,
    skipped: Skipped | None,
    what: str = "state",
) -> int:
    """Apply the bad-value rule to the records flagged in the 1-D mask ``bad``.

    ``describe(i)`` names record ``i`` (e.g. ``"track 7 at t=1.2 s: x is inf"``).
    Raises :class:`ConversionError` on the first bad record unless ``skip_bad``; then
    notes the count in ``skipped`` and returns it (the caller drops those records and
    stores the count in the scene's metadata).
    """
    where = np.flatnonzero(np.asarray(bad, dtype=bool).ravel())
    if where.size == 0:
        return 0
    if not skip_bad:
        raise ConversionError(
            f"{source}: {describe(int(where[0]))} (a non-finite or out-of-range value);"
            f" fix the input, or convert with --skip-bad to drop every such {what}"
            " (the count is printed and stored in the scene's metadata)"
        )
    if skipped is not None:
        named = "; ".join(describe(int(i)) for i in where[:SHOWN])
        more = f"; and {where.size - SHOWN} more" if where.size > SHOWN else ""
        skipped.add(
            f"{source}: dropped {where.size} {what}(s) with non-finite or out-of-range"
            f" values: {named}{more}"
        )
    return int(where.size)


def bad_states(
    xy: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    length: np.ndarray,
    width: np.ndarray,
    valid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(bad, reason)`` over a ``(T, N)`` grid: valid states with a bad value, and an
    index into :data:`REASONS` for each (the first bad field)."""
    checks = [
        ~np.isfinite(xy).all(axis=-1),
        np.isfinite(xy).all(axis=-1) & ~(np.abs(xy) < MAX_ABS_POSITION_M).all(axis=-1),
        ~np.isfinite(heading),
        ~(np.isfinite(speed) & (speed >= 0)),
        ~(np.isfinite(length) & (length >= 0)),
        ~(np.isfinite(width) & (width >= 0)),
    ]
    stacked = np.stack(checks) & valid[None]
    bad = stacked.any(axis=0)
    reason = np.argmax(stacked, axis=0)
    return bad, reason


REASONS = (
    "position is not finite",
    "position is beyond the 2**53 mm the scene format holds",
    "heading is not finite",
    "speed is not a finite number >= 0",
    "length is not a finite number >= 0",
    "width is not a finite number >= 0",
)


def available_memory_bytes() -> int | None:
    """Memory the system can still give (:func:`outputs.memory.available_bytes`)."""
    return available_bytes()


def check_gaps(steps: np.ndarray, *, source: str, what: str = "frame_id") -> None:
    """Refuse time steps with a gap far larger than the recording itself (one
    ``frame_id`` of 9,000,000 among frames 1-5): the dense grid would span the gap, so
    one corrupt value sized it (a 9-million-frame grid) and the file still converted."""
    distinct = np.unique(np.asarray(steps))
    if distinct.size < 2:
        return
    gaps = np.diff(distinct)
    worst = int(gaps.argmax())
    if gaps[worst] > max(MAX_GAP_STEPS, 10 * distinct.size):
        raise ConversionError(
            f"{source}: {what} jumps from {distinct[worst]:g} to {distinct[worst + 1]:g}, a"
            f" gap of {gaps[worst]:g} steps in a recording of {distinct.size} steps; a value"
            " is corrupt"
        )


def check_grid(n_steps: float, n_tracks: int, *, source: str, what: str = "time steps") -> None:
    """Refuse a ``n_steps x n_tracks`` state grid that is absurd or would not fit in
    memory, before it is allocated (the estimate is :data:`BYTES_PER_STATE` per state)."""
    if not (n_steps >= 1 and n_steps <= MAX_STEPS):
        raise ConversionError(
            f"{source}: the scenario spans {n_steps:g} {what} (at most {MAX_STEPS} are"
            " supported); a time value is corrupt or in the wrong unit"
        )
    need = float(n_steps) * (max(n_tracks, 1) * BYTES_PER_STATE + BYTES_PER_STEP)
    free = available_memory_bytes()
    if free is not None and need > free:
        raise ConversionError(
            f"{source}: converting it needs about {need / 2**30:.1f} GiB ({int(n_steps)}"
            f" {what} x {n_tracks} tracks) but {free / 2**30:.1f} GiB is available; a time"
            " value is probably corrupt"
        )


def check_points(points: np.ndarray, where: str) -> None:
    """Refuse map points (lane bounds, centerlines, nodes) that are not finite or lie
    beyond the scene format's range, naming ``where`` (file and element): a NaN bound
    otherwise vanished into a converted lane, and 2**62 mm failed only when writing."""
    pts = np.asarray(points, dtype=np.float64)
    if not pts.size:
        return
    if not np.isfinite(pts).all():
        raise ConversionError(f"{where}: a point is not finite (NaN or infinite); fix the map")
    if np.abs(pts).max() > MAX_ABS_POSITION_M:
        raise ConversionError(
            f"{where}: a point lies {np.abs(pts).max():.3g} m from the origin, beyond the"
            f" scene format's {MAX_ABS_POSITION_M:.3g} m; fix the map"
        )


def integer_id(text: object, where: str, what: str = "id") -> int:
    """``text`` as an integer id, or a ConversionError saying which element has which
    value (rather than ``invalid literal for int() with base 10``)."""
    try:
        return int(str(text).strip())
    except (ValueError, TypeError):
        raise ConversionError(f"{where}: {what} must be an integer, got {text!r}") from None
