"""From per-track arrays to a :class:`risk.Scene`: shared by every recorded-data converter.

A source reader fills a :class:`TrackTable` (time steps x tracks); :func:`build_scene`
adds the agent paths (``map`` or ``hindsight``) and cuts the frames.

Frame layout (documented in docs/recorded-data.md): every frame holds **every track of
the scene** in the same order, with ``valid`` saying whether the track was observed at
that step, so that agent indices are stable over the scene and every agent that is valid
in a frame gets a risk value there. Every step at which any track is valid becomes a
frame; where the scene's ego is not valid the frame is seen from the first valid track
(a :class:`risk.Frame` needs a valid ego) and the scene's ``ego_id`` still names the real
ego, so a replay from it skips those frames while ``--ego all`` and the hindsight truth
use them. Their number is recorded in the metadata as ``steps_without_ego``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from tqdm import tqdm

from converters.clock import Motion, TimeStep, check_motion, warning_line
from converters.errors import ConversionError
from converters.hindsight_paths import Hindsight
from converters.input_checks import REASONS, Skipped, apply_bad_rule, bad_states
from converters.lanegraph import LaneGraph, PathRows, PathSettings, straight_rows
from risk.frame import Frame, Kind, LaneMap, Scene
from risk.motion import MIN_TRAVEL_M, track_extents

PATH_MODES: tuple[str, ...] = ("map", "hindsight")
OFF_LANE_MODES: tuple[str, ...] = ("straight", "hindsight")

LANE_GRAPH, RECORDED, STRAIGHT = 0, 1, 2
PATH_SOURCE_NAMES: tuple[str, ...] = ("lane_graph", "recorded_future", "straight")
"""Where an agent's path in a frame came from (codes 0, 1, 2)."""
PATH_SOURCE_LABELS: tuple[str, ...] = tuple(f"paths_{n}" for n in PATH_SOURCE_NAMES)
"""Label names of :func:`build_scene`'s ``path_source_labels``, in code order."""

MOVING_EGO_MIN_M = MIN_TRAVEL_M
"""A default ego must move at least this far (m; risk.motion's threshold for "moves")."""

_INTEGER = re.compile(r"[+-]?\d{1,18}")


def integer_ids(names: Sequence[str]) -> tuple[np.ndarray, dict[str, int]]:
    """Integer agent ids for a source's track names, ``(N,)`` int64, in input order.

    Names that are integers keep their value; the others (Argoverse's ``AV``, INTERACTION's
    ``P1``) get the integers after the largest numeric id (or from 0), in sorted name
    order, so the choice is stable. Returns the ids and the mapping of the renamed ones.
    """
    numeric = {n: int(n) for n in names if _INTEGER.fullmatch(n.strip())}
    others = sorted(n for n in set(names) if n not in numeric)
    start = max(numeric.values(), default=-1) + 1
    renamed = {n: start + i for i, n in enumerate(others)}
    ids = np.array([numeric.get(n, renamed.get(n, 0)) for n in names], dtype=np.int64)
    return ids, renamed


@dataclass(frozen=True, eq=False)
class TrackTable:
    """All tracks of one scenario on a common time grid.

    Shapes: ``T`` time steps, ``N`` tracks. Units: metres, radians, m/s, seconds.
    ``speed`` is the magnitude of the velocity vector. Entries where ``valid`` is False
    are ignored (they may hold anything, NaN included).
    """

    ids: np.ndarray  # (N,) int64, unique
    kinds: np.ndarray  # (N,) int8, risk.Kind codes
    t_s: np.ndarray  # (T,) float64, increasing
    xy: np.ndarray  # (T, N, 2) float64
    heading: np.ndarray  # (T, N) float64
    speed: np.ndarray  # (T, N) float64, >= 0
    length: np.ndarray  # (T, N) float64, >= 0
    width: np.ndarray  # (T, N) float64, >= 0
    valid: np.ndarray  # (T, N) bool
    #: (T, N) bool: the speed is the source's own (a recorded velocity), not derived from
    #: the positions; None: every speed is recorded. The clock check needs recorded ones.
    speed_measured: np.ndarray | None = None

    @property
    def n_steps(self) -> int:
        return int(self.valid.shape[0])

    @property
    def n_tracks(self) -> int:
        return int(self.valid.shape[1])

    def usable(self) -> np.ndarray:
        """``(T, N)``: valid entries whose values are all finite and physical."""
        ok = self.valid & np.isfinite(self.xy).all(axis=2) & np.isfinite(self.heading)
        ok &= np.isfinite(self.speed) & (self.speed >= 0)
        ok &= np.isfinite(self.length) & (self.length >= 0)
        ok &= np.isfinite(self.width) & (self.width >= 0)
        return ok


def moving_ego(table: TrackTable) -> tuple[int, str]:
    """The default ego of a recording without one, and why it was chosen.

    The rule (docs/recorded-data.md): the **vehicle that travels farthest**, measured as
    the travel extent of :func:`risk.motion.track_extents` (the largest distance of its
    usable positions from its first one; ties: the lowest id) — the same measure that
    ``--ego all`` uses for "moves". The extent favours an agent that is present for long
    (only the steps at which the ego is valid become frames) and moving, and does not grow
    with position jitter, so a parked car, however many states it has, is never chosen
    while some vehicle moves. When no vehicle moves :data:`MOVING_EGO_MIN_M`, the agent of
    any kind that moves farthest; when nothing moves that far, the track with the most
    usable states. Returns the track index and a one-line reason.
    """
    usable = table.usable()
    dist = track_extents(np.where(usable[:, :, None], table.xy, 0.0), usable)
    vehicle = table.kinds == Kind.VEHICLE
    counts = usable.sum(axis=0)
    n_frames = int(usable.any(axis=1).sum())
    # Present for at least half of the frames first: an ego seen in 27 of 76 frames made
    # every other frame's negatives censored (issue 31).
    long = counts >= EGO_MIN_COVERAGE * n_frames
    anyone = np.ones_like(vehicle)
    pools = ((vehicle & long, "vehicle", True), (vehicle, "vehicle", False),
             (anyone & long, "agent", True), (anyone, "agent", False))  # fmt: skip
    for pool, what, present in pools:
        candidates = np.flatnonzero(pool & (dist >= MOVING_EGO_MIN_M))
        if candidates.size:
            best = candidates[np.lexsort((table.ids[candidates], -dist[candidates]))[0]]
            among = " of those present in at least half of the frames" if present else ""
            why = f"the {what} that travels farthest ({dist[best]:.1f} m){among}"
            return int(best), why + _coverage_warning(int(counts[best]), n_frames)
    best = int(np.lexsort((table.ids, -counts))[0])
    return best, (
        f"no agent travels {MOVING_EGO_MIN_M:g} m: the one with the most states ({counts[best]})"
    ) + _coverage_warning(int(counts[best]), n_frames)


#: An ego present in fewer than this share of the frames is chosen only when no agent is
#: present longer, and with a warning.
EGO_MIN_COVERAGE = 0.5


def _coverage_warning(present: int, n_frames: int) -> str:
    if n_frames == 0 or present >= EGO_MIN_COVERAGE * n_frames:
        return ""
    return (
        f"; warning: it is present in only {present} of {n_frames} frames, so the rest of"
        " the scene has no ego view and its negatives are censored: choose another with --ego"
    )


def build_scene(
    table: TrackTable,
    ego: int,
    lane_map: LaneMap,
    *,
    paths: str,
    settings: PathSettings,
    frame_period_s: float,
    metadata: Mapping[str, str],
    labels: Mapping[str, tuple[int, ...]] | None = None,
    source: str = "input",
    progress: bool = False,
    skip_bad: bool = False,
    skipped: Skipped | None = None,
    off_lane: str = "straight",
    path_source_labels: bool = False,
    time_step: TimeStep = "auto",
) -> Scene:
    """Frames with paths for every step at which any track is valid; the scene's ego is
    track index ``ego``.

    A step where the ego is not valid is kept (other agents' motion there matters to
    ``--ego all`` and to the hindsight truth), seen from the first valid track; the
    scene's ``ego_id`` names the real ego, so a replay from it skips such frames.

    ``paths`` is ``map`` (lane graph of ``lane_map``) or ``hindsight`` (recorded future).
    With ``map``, ``off_lane`` says what a vehicle or cyclist that matches no lane gets:
    ``straight`` (along its heading) or ``hindsight`` (its recorded future, for maps
    that cover only part of the roads); with ``path_source_labels`` the scene's labels
    say, per agent, where its paths came from (:data:`PATH_SOURCE_LABELS`: an agent is in
    every list whose source gave it a path in at least one frame) and the metadata
    ``path_source_agent_frames`` counts the (frame, agent) paths of each source.
    ``source`` names the input in error messages. Raises ConversionError when the ego is
    never valid or a track id repeats. Valid states with non-finite or out-of-range
    values follow the rule of :mod:`converters.input_checks`: an error, or with ``skip_bad``
    dropped, noted in ``skipped`` and counted in the metadata (``bad_states_dropped``).

    The scene's clock is checked against its motion (:mod:`converters.clock`) with
    ``frame_period_s`` as the file's time step; ``time_step`` (``auto``, ``file`` or
    seconds) chooses the step used. A changed step scales the times (and the speeds
    derived from positions, ``table.speed_measured`` False) and is recorded in the
    metadata as ``time_step_corrected_from``; the figures go to ``clock_check`` (JSON) and
    a warning line, when there is one, to ``clock_warning``.
    """
    if paths not in PATH_MODES:
        raise ConversionError(f"unknown path mode {paths!r}; expected one of {PATH_MODES}")
    if off_lane not in OFF_LANE_MODES:
        raise ConversionError(f"unknown off-lane mode {off_lane!r}; expected {OFF_LANE_MODES}")
    if len(np.unique(table.ids)) != table.n_tracks:
        raise ConversionError(f"{source}: a track id appears more than once")
    bad, reason = bad_states(
        table.xy, table.heading, table.speed, table.length, table.width, table.valid
    )
    n_bad = apply_bad_rule(
        bad.ravel(),
        lambda i: _describe_state(table, reason, *divmod(i, table.n_tracks)),
        source=source,
        skip_bad=skip_bad,
        skipped=skipped,
    )
    valid = table.usable() & ~bad
    dropped = int((table.valid & ~valid).sum())
    table, clock_facts, frame_period_s = _checked_clock(
        table, valid, frame_period_s, time_step, source
    )
    if not valid[:, ego].any():
        raise ConversionError(
            f"{source}: the ego (track {int(table.ids[ego])}) is valid at no time step"
        )
    steps = np.flatnonzero(valid.any(axis=1))
    frame_of_step = np.full(table.n_steps, -1, dtype=np.int64)
    frame_of_step[steps] = np.arange(steps.size)
    rows, path_source = _path_rows(
        table, valid, steps, frame_of_step, lane_map, paths, settings, off_lane
    )
    frames = _frames(table, valid, steps, ego, rows, progress, source)
    facts = {
        **metadata,
        "paths": paths,
        "horizon_s": f"{settings.horizon_s:g}",
        "margin_m": f"{settings.margin_m:g}",
        "frame_period_s": f"{frame_period_s:g}",
        "steps_without_ego": str(int((~valid[steps, ego]).sum())),
        "steps_without_agents": str(table.n_steps - steps.size),
        "invalid_states_dropped": str(dropped),
        "bad_states_dropped": str(n_bad),
        **clock_facts,
    }
    labels = dict(labels or {})
    if path_source_labels:
        for code, name in enumerate(PATH_SOURCE_LABELS):
            labels[name] = tuple(int(i) for i in table.ids[(path_source == code).any(axis=0)])
        counts = {n: int((path_source == c).sum()) for c, n in enumerate(PATH_SOURCE_NAMES)}
        facts["path_source_agent_frames"] = json.dumps(counts)
    if paths == "map":
        facts.update(
            map_path_m=f"{settings.map_path_m:g}",
            max_lateral_m=f"{settings.max_lateral_m:g}",
            max_heading_rad=f"{settings.max_heading_rad:g}",
            max_candidates=str(settings.max_candidates),
        )
    return Scene(
        map=lane_map,
        frames=frames,
        frame_period_s=float(frame_period_s),
        metadata=facts,
        labels=labels,
        ego_id=int(table.ids[ego]),
    )


def _checked_clock(
    table: TrackTable, valid: np.ndarray, file_step_s: float, time_step: TimeStep, source: str
) -> tuple[TrackTable, dict[str, str], float]:
    """The table on the time step chosen by the clock check, its metadata facts, and the
    frame period."""
    measured = np.ones_like(valid) if table.speed_measured is None else table.speed_measured
    motion = Motion(table.t_s, table.xy, table.heading, table.speed, valid, table.kinds, measured)
    check = check_motion(motion, file_step_s, time_step)
    facts = {"clock_check": check.to_json()}
    warning = warning_line(source, check)
    if warning:
        facts["clock_warning"] = warning
    if not check.corrected:
        return table, facts, file_step_s
    scale = check.step_s / file_step_s
    facts["time_step_corrected_from"] = f"{file_step_s:g}"
    speed = np.where(measured, table.speed, table.speed / scale)
    return replace(table, t_s=table.t_s * scale, speed=speed), facts, check.step_s


def _describe_state(table: TrackTable, reason: np.ndarray, step: int, track: int) -> str:
    return (
        f"track {int(table.ids[track])} at t={float(table.t_s[step]):g} s:"
        f" {REASONS[int(reason[step, track])]}"
    )


def _path_rows(
    table: TrackTable,
    valid: np.ndarray,
    steps: np.ndarray,
    frame_of_step: np.ndarray,
    lane_map: LaneMap,
    paths: str,
    settings: PathSettings,
    off_lane: str = "straight",
) -> tuple[PathRows, np.ndarray]:
    """Path candidates of every valid (frame, agent), plus a one-point row per invalid one;
    also ``(F, N)`` int8 codes of where each valid agent's path came from (an index of
    :data:`PATH_SOURCE_NAMES`; -1 where the agent is not valid)."""
    in_scene = np.zeros(table.n_steps, dtype=bool)
    in_scene[steps] = True
    q_step, q_agent = np.nonzero(valid & in_scene[:, None])
    q_frame = frame_of_step[q_step]
    q_xy = table.xy[q_step, q_agent]
    q_heading = table.heading[q_step, q_agent]
    q_speed = table.speed[q_step, q_agent]
    q_kind = table.kinds[q_agent]
    parts: list[PathRows] = []
    q_source = np.full(q_step.size, RECORDED, dtype=np.int8)
    if paths == "hindsight":
        hindsight = Hindsight(table.xy, table.heading, valid, settings)
        parts.append(hindsight.rows(q_step, q_frame, q_agent, q_xy, q_speed))
    else:
        follows_lanes = (q_kind == Kind.VEHICLE) | (q_kind == Kind.CYCLIST)
        straight = ~follows_lanes
        off = np.zeros(q_step.size, dtype=bool)
        graph = LaneGraph(lane_map, settings)
        if graph.n_lanes and follows_lanes.any():
            sel = np.flatnonzero(follows_lanes)
            lane_rows, unmatched = graph.map_rows(
                q_frame[sel], q_agent[sel], q_xy[sel], q_heading[sel], q_speed[sel], q_kind[sel]
            )
            parts.append(lane_rows)
            off[sel[unmatched]] = True
        else:
            off = follows_lanes.copy()
        q_source[:] = LANE_GRAPH
        if off_lane == "hindsight" and off.any():
            hindsight = Hindsight(table.xy, table.heading, valid, settings)
            parts.append(
                hindsight.rows(q_step[off], q_frame[off], q_agent[off], q_xy[off], q_speed[off])
            )
            q_source[off] = RECORDED
        else:
            straight |= off
        q_source[straight] = STRAIGHT
        parts.append(
            straight_rows(
                q_frame[straight],
                q_agent[straight],
                q_xy[straight],
                q_heading[straight],
                settings.required_length_m(q_speed[straight]),
            )
        )
    i_step, i_agent = np.nonzero(~valid & in_scene[:, None])
    parts.append(
        PathRows(
            frame_of_step[i_step],
            i_agent.astype(np.int64),
            np.zeros((i_step.size, 1, 2)),
            np.ones(i_step.size, dtype=np.int64),
        )
    )
    rows = PathRows.concat(parts)
    order = np.lexsort((rows.agent, rows.frame))  # stable: keeps candidate order
    source = np.full((steps.size, table.n_tracks), -1, dtype=np.int8)
    source[q_frame, q_agent] = q_source
    rows = PathRows(rows.frame[order], rows.agent[order], rows.points[order], rows.count[order])
    return rows, source


def _frames(
    table: TrackTable,
    valid: np.ndarray,
    steps: np.ndarray,
    ego: int,
    rows: PathRows,
    progress: bool,
    source: str,
) -> list[Frame]:
    bounds = np.searchsorted(rows.frame, np.arange(steps.size + 1))
    frames: list[Frame] = []
    for f, step in enumerate(
        tqdm(steps, desc="frames", unit="frame", disable=None if progress else True, leave=False)
    ):
        lo, hi = bounds[f], bounds[f + 1]
        count = rows.count[lo:hi]
        ok = valid[step]
        frames.append(
            Frame.from_padded(
                ids=table.ids,
                kinds=table.kinds,
                xy=np.where(ok[:, None], table.xy[step], 0.0),
                heading=np.where(ok, table.heading[step], 0.0),
                speed=np.where(ok, table.speed[step], 0.0),
                length=np.where(ok, table.length[step], 0.0),
                width=np.where(ok, table.width[step], 0.0),
                valid=ok,
                paths=rows.points[lo:hi, : int(count.max())],
                path_points=count,
                path_agent=rows.agent[lo:hi],
                ego=ego if ok[ego] else int(np.argmax(ok)),
                t=float(table.t_s[step]),
            )
        )
    return frames
