"""Frames and scenes in structure-of-arrays form.

A :class:`Frame` is one time step: the ego and the other agents, each with a pose, a
speed along its path, a body size, a kind and one or more forward **path candidates**
(polylines that start at the agent's position). Every array is validated once, at
construction, and trusted afterwards; the arrays are made read-only so that no model can
modify its input.

Path storage is flat so that models can vectorise over all candidates at once:

- ``paths``: ``(M, P, 2)`` float64, metres; candidate ``m`` belongs to agent
  ``path_agent[m]``; each row is padded to ``P`` points by repeating its last point
  (padding adds only zero-length segments, which change no distance);
- ``path_points``: ``(M,)`` number of real points of each candidate (>= 1);
- ``path_agent``: ``(M,)`` owning agent index, non-decreasing, every agent owns >= 1 row.

Most agents have exactly one candidate (``M == N``). Where a lane graph forks, a converter
may give an agent several; the models then report the riskiest candidate.

Invalid agents (``valid == False``, e.g. a track that is not observed in this frame) keep
their place in the arrays so that agent indices stay stable within a scene; their fields
are not validated, are sanitised to finite values, and every model returns NaN for them.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from risk.errors import FrameError


class Kind(enum.IntEnum):
    """Agent kind; the integer codes are stored in frames and files."""

    VEHICLE = 0
    PEDESTRIAN = 1
    CYCLIST = 2
    OTHER = 3

    @classmethod
    def parse(cls, value: str | int | Kind) -> Kind:
        if isinstance(value, Kind):
            return value
        if isinstance(value, (int, np.integer)):
            return cls(int(value))
        try:
            return cls[str(value).strip().upper()]
        except KeyError:
            names = ", ".join(k.name.lower() for k in cls)
            raise FrameError("kinds", f"unknown kind {value!r}; expected one of {names}") from None


KIND_NAMES: tuple[str, ...] = tuple(k.name.lower() for k in Kind)
_MAX_KIND = int(max(Kind))

#: Path candidates per agent at most. The models compare every candidate of the ego with
#: every candidate of each agent, so a frame costs about candidates squared: 2,000 per
#: agent ran for hours. Converters keep 3 by default (``--max-candidates``).
MAX_CANDIDATES = 64

#: Path points of one frame once every candidate is padded to the longest (320 MB of
#: float64 pairs): a single 10**6-point path among many agents raised numpy's MemoryError.
MAX_PADDED_POINTS = 20_000_000


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Frame:
    """One situation: the ego and every other agent at one time.

    Shapes: ``N`` agents, ``M >= N`` path candidates of at most ``P`` points.
    Units: metres, radians (heading, counter-clockwise from +x), m/s, seconds.
    """

    ids: np.ndarray  # (N,) int64, unique
    kinds: np.ndarray  # (N,) int8, Kind codes
    xy: np.ndarray  # (N, 2) float64, m
    heading: np.ndarray  # (N,) float64, rad
    speed: np.ndarray  # (N,) float64, m/s along the path, >= 0
    length: np.ndarray  # (N,) float64, m, >= 0
    width: np.ndarray  # (N,) float64, m, >= 0
    valid: np.ndarray  # (N,) bool
    paths: np.ndarray  # (M, P, 2) float64, m
    path_points: np.ndarray  # (M,) int64, >= 1
    path_agent: np.ndarray  # (M,) int64, owner index, non-decreasing
    ego: int  # index of the ego agent
    t: float = 0.0  # frame time, s
    _checked: bool = field(default=False, repr=False)

    def __post_init__(self) -> None:
        if not self._checked:
            raise TypeError("build frames with Frame.from_arrays or Frame.from_padded")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_arrays(
        cls,
        xy: np.ndarray,
        heading: np.ndarray,
        speed: np.ndarray,
        length: np.ndarray,
        width: np.ndarray,
        paths: Sequence[np.ndarray | Sequence[np.ndarray]],
        ego: int,
        *,
        ids: np.ndarray | Sequence[int] | None = None,
        kinds: np.ndarray | Sequence[str | int] | None = None,
        valid: np.ndarray | Sequence[bool] | None = None,
        t: float = 0.0,
    ) -> Frame:
        """Build and validate a frame from plain arrays.

        ``paths`` holds one entry per agent: a ``(P_i, 2)`` polyline starting at the agent's
        position, or a sequence of such polylines (candidates at a fork).
        ``kinds`` are strings (``vehicle``, ``pedestrian``, ``cyclist``, ``other``) or Kind
        codes; default all vehicles. ``ids`` default to ``0..N-1``.
        """
        xy_a = _checked("xy", xy, np.float64)
        if xy_a.ndim != 2 or xy_a.shape[1] != 2:
            raise FrameError("xy", f"expected shape (N, 2), got {xy_a.shape}")
        n = xy_a.shape[0]
        if len(paths) != n:
            raise FrameError("paths", f"expected one path entry per agent ({n}), got {len(paths)}")
        rows: list[np.ndarray] = []
        owner: list[int] = []
        for i, entry in enumerate(paths):
            candidates = [entry] if _is_polyline(entry) else list(entry)
            if not candidates:
                raise FrameError("paths", "no path candidate given", index=i)
            for cand in candidates:
                c = _checked("paths", cand, np.float64)
                if c.ndim != 2 or c.shape[1] != 2:
                    raise FrameError(
                        "paths", f"a path must have shape (P, 2), got {c.shape}", index=i
                    )
                if c.shape[0] < 1:
                    raise FrameError("paths", "a path needs at least one point", index=i)
                rows.append(c)
                owner.append(i)
        max_p = max((r.shape[0] for r in rows), default=1)
        if len(rows) * max_p > MAX_PADDED_POINTS:  # every candidate padded to the longest
            longest = int(np.argmax([r.shape[0] for r in rows]))
            raise FrameError(
                "paths", f"{len(rows)} candidates padded to the longest ({max_p} points) make"
                f" {len(rows) * max_p:.3g} points, more than the {MAX_PADDED_POINTS:.3g}"
                " supported; resample the long paths", index=owner[longest],
            )  # fmt: skip
        padded = np.empty((len(rows), max_p, 2))
        for m, r in enumerate(rows):
            padded[m, : r.shape[0]] = r
            padded[m, r.shape[0] :] = r[-1]
        try:
            kind_codes = (
                np.zeros(n, dtype=np.int8)
                if kinds is None
                else np.array([Kind.parse(k) for k in kinds], dtype=np.int8)
            )
        except (ValueError, TypeError) as exc:
            if isinstance(exc, FrameError):
                raise
            raise FrameError("kinds", f"unknown kind code ({exc})") from None
        return cls.from_padded(
            ids=np.arange(n) if ids is None else ids,
            kinds=kind_codes,
            xy=xy_a,
            heading=heading,
            speed=speed,
            length=length,
            width=width,
            valid=np.ones(n, dtype=bool) if valid is None else valid,
            paths=padded,
            path_points=np.array([r.shape[0] for r in rows], dtype=np.int64),
            path_agent=np.array(owner, dtype=np.int64),
            ego=ego,
            t=t,
        )

    @classmethod
    def from_padded(
        cls,
        *,
        ids: np.ndarray | Sequence[int],
        kinds: np.ndarray | Sequence[int],
        xy: np.ndarray,
        heading: np.ndarray,
        speed: np.ndarray,
        length: np.ndarray,
        width: np.ndarray,
        valid: np.ndarray | Sequence[bool],
        paths: np.ndarray,
        path_points: np.ndarray,
        path_agent: np.ndarray,
        ego: int,
        t: float = 0.0,
    ) -> Frame:
        """Build and validate a frame from the flat, padded form (what readers produce)."""
        xy_a = _checked("xy", xy, np.float64)
        if xy_a.ndim != 2 or xy_a.shape[1] != 2:
            raise FrameError("xy", f"expected shape (N, 2), got {xy_a.shape}")
        n = xy_a.shape[0]
        if n == 0:
            raise FrameError("xy", "a frame needs at least the ego agent; got no agents")
        ids_a = _vector("ids", ids, n, np.int64)
        kinds_a = _vector("kinds", kinds, n, np.int8)
        heading_a = _vector("heading", heading, n, np.float64)
        speed_a = _vector("speed", speed, n, np.float64)
        length_a = _vector("length", length, n, np.float64)
        width_a = _vector("width", width, n, np.float64)
        valid_a = _vector("valid", valid, n, bool)
        paths_a = _checked("paths", paths, np.float64)
        if paths_a.ndim != 3 or paths_a.shape[2] != 2 or paths_a.shape[1] < 1:
            raise FrameError("paths", f"expected shape (M, P, 2) with P >= 1, got {paths_a.shape}")
        m = paths_a.shape[0]
        points_a = _vector("path_points", path_points, m, np.int64)
        agent_a = _vector("path_agent", path_agent, m, np.int64)

        # (array methods rather than np.any / np.unique: this runs on every frame read,
        # and their Python-level dispatch was most of its cost at N = 100)
        sorted_ids = np.sort(ids_a)
        repeated = np.diff(sorted_ids) == 0
        if repeated.any():
            dup = sorted_ids[int(repeated.argmax())]
            raise FrameError("ids", f"agent id {int(dup)} appears more than once")
        bad_kind = np.flatnonzero((kinds_a < 0) | (kinds_a > _MAX_KIND))
        if bad_kind.size:
            i = int(bad_kind[0])
            raise FrameError(
                "kinds", f"unknown kind code {int(kinds_a[i])}", index=i, agent_id=int(ids_a[i])
            )
        if isinstance(ego, (bool, np.bool_)) or not isinstance(ego, (int, np.integer)):
            raise FrameError("ego", f"ego must be an agent index (an integer), got {ego!r:.40}")
        if not 0 <= int(ego) < n:
            raise FrameError("ego", f"ego index {ego!r} is out of range for {n} agents")
        ego = int(ego)
        if not valid_a[ego]:
            raise FrameError(
                "valid", "the ego agent must be valid", index=ego, agent_id=int(ids_a[ego])
            )
        if isinstance(t, (bool, np.bool_)) or not isinstance(
            t, (int, float, np.integer, np.floating)
        ):
            raise FrameError("t", f"frame time must be a number of seconds, got {t!r:.40}")
        try:
            finite = np.isfinite(float(t))
        except OverflowError:  # (an integer beyond any float)
            finite = False
        if not finite:
            raise FrameError("t", f"frame time must be finite, got {t!r:.40}")

        # Path ownership: sorted, in range, every agent has at least one candidate.
        if m < n or agent_a[0] < 0 or agent_a[-1] >= n or (np.diff(agent_a) < 0).any():
            raise FrameError("path_agent", "must be non-decreasing agent indices in [0, N)")
        per_agent = np.bincount(agent_a, minlength=n)
        if per_agent.max(initial=0) > MAX_CANDIDATES:
            i = int(per_agent.argmax())
            raise FrameError(
                "paths", f"{int(per_agent[i])} path candidates, more than the"
                f" {MAX_CANDIDATES} supported per agent (convert with fewer, e.g."
                " --max-candidates)", index=i, agent_id=int(ids_a[i]),
            )  # fmt: skip
        has_path = np.zeros(n, dtype=bool)
        has_path[agent_a] = True
        if not has_path.all():
            i = int(np.flatnonzero(~has_path)[0])
            raise FrameError("paths", "agent has no path", index=i, agent_id=int(ids_a[i]))
        bad_points = (points_a < 1) | (points_a > paths_a.shape[1])
        if bad_points.any():
            r = int(bad_points.argmax())
            i = int(agent_a[r])
            raise FrameError(
                "paths", "a path needs at least one point", index=i, agent_id=int(ids_a[i])
            )

        # Values of valid agents: finite, non-negative where physical.
        checks = (
            ("xy", ~np.isfinite(xy_a).all(axis=1), "position is not finite"),
            ("heading", ~np.isfinite(heading_a), "heading is not finite"),
            ("speed", ~np.isfinite(speed_a), "speed is not finite"),
            ("speed", speed_a < 0, "speed along the path must be >= 0"),
            ("length", ~np.isfinite(length_a) | (length_a < 0), "length must be finite and >= 0"),
            ("width", ~np.isfinite(width_a) | (width_a < 0), "width must be finite and >= 0"),
        )
        for name, bad, problem in checks:
            bad = bad & valid_a
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise FrameError(name, problem, index=i, agent_id=int(ids_a[i]))
        real_point = np.arange(paths_a.shape[1])[None, :] < points_a[:, None]
        # (x and y apart: numpy reduces a length-2 last axis about 15x slower)
        finite_point = np.isfinite(paths_a[..., 0]) & np.isfinite(paths_a[..., 1])
        bad_path = (real_point & ~finite_point).any(axis=1) & valid_a[agent_a]
        if bad_path.any():
            i = int(agent_a[np.flatnonzero(bad_path)[0]])
            raise FrameError(
                "paths", "path has a non-finite point", index=i, agent_id=int(ids_a[i])
            )

        # Re-pad with the last real point so that padding never adds a segment, and
        # sanitise invalid agents so that vectorised maths stays finite.
        last = paths_a[np.arange(m), points_a - 1]
        padded = np.empty_like(paths_a)  # (x and y apart: 4x faster than one broadcast)
        for c in (0, 1):
            padded[..., c] = np.where(real_point, paths_a[..., c], last[:, c, None])
        paths_a = padded
        inv = ~valid_a
        if inv.any():
            xy_a[inv] = 0.0
            for a in (heading_a, speed_a, length_a, width_a):
                a[inv] = 0.0
            inv_rows = inv[agent_a]
            paths_a[inv_rows] = 0.0
            points_a[inv_rows] = 1

        return cls(
            ids=_readonly(ids_a),
            kinds=_readonly(kinds_a),
            xy=_readonly(xy_a),
            heading=_readonly(heading_a),
            speed=_readonly(speed_a),
            length=_readonly(length_a),
            width=_readonly(width_a),
            valid=_readonly(valid_a),
            paths=_readonly(paths_a),
            path_points=_readonly(points_a),
            path_agent=_readonly(agent_a),
            ego=ego,
            t=float(t),
            _checked=True,
        )

    # ------------------------------------------------------------------ views
    @property
    def n_agents(self) -> int:
        return int(self.xy.shape[0])

    @property
    def ego_id(self) -> int:
        return int(self.ids[self.ego])

    @property
    def others(self) -> np.ndarray:
        """Boolean mask ``(N,)`` of the agents that get a risk value: valid and not the ego."""
        mask = self.valid.copy()
        mask[self.ego] = False
        return mask

    def index_of(self, agent_id: int) -> int:
        """Index of the agent with this id; raises FrameError when it is absent."""
        hits = np.flatnonzero(self.ids == agent_id)
        if hits.size == 0:
            raise FrameError("ids", f"no agent with id {agent_id} in the frame at t={self.t:g} s")
        return int(hits[0])

    def agent_paths(self, index: int) -> list[np.ndarray]:
        """The path candidates of one agent, each ``(P_i, 2)`` without padding."""
        rows = np.flatnonzero(self.path_agent == index)
        return [np.array(self.paths[r, : self.path_points[r]]) for r in rows]

    def select(self, indices: np.ndarray | Sequence[int]) -> Frame:
        """A new frame with only these agents (in this order); the ego must be among them.

        Used by the cascade to run later stages on the survivors only.
        """
        idx = np.asarray(indices, dtype=np.int64)
        where_ego = np.flatnonzero(idx == self.ego)
        if where_ego.size != 1:
            raise FrameError("ego", "a selection must contain the ego exactly once")
        new_index = np.full(self.n_agents, -1, dtype=np.int64)
        new_index[idx] = np.arange(idx.size)
        # Keep path rows grouped by their new owner, in the new agent order.
        row_new_owner = new_index[self.path_agent]
        keep_rows = np.flatnonzero(row_new_owner >= 0)
        order = keep_rows[np.argsort(row_new_owner[keep_rows], kind="stable")]
        return Frame(
            ids=_readonly(self.ids[idx]),
            kinds=_readonly(self.kinds[idx]),
            xy=_readonly(self.xy[idx]),
            heading=_readonly(self.heading[idx]),
            speed=_readonly(self.speed[idx]),
            length=_readonly(self.length[idx]),
            width=_readonly(self.width[idx]),
            valid=_readonly(self.valid[idx]),
            paths=_readonly(self.paths[order]),
            path_points=_readonly(self.path_points[order]),
            path_agent=_readonly(row_new_owner[order]),
            ego=int(where_ego[0]),
            t=self.t,
            _checked=True,
        )

    def with_ego(self, index: int) -> Frame:
        """The same frame seen from another agent (which must be valid)."""
        if not 0 <= index < self.n_agents:
            raise FrameError("ego", f"ego index {index} is out of range for {self.n_agents} agents")
        if not self.valid[index]:
            raise FrameError(
                "valid", "the ego agent must be valid", index=index, agent_id=int(self.ids[index])
            )
        return Frame(**{**self._fields(), "ego": int(index)})

    def _fields(self) -> dict:
        return {
            "ids": self.ids,
            "kinds": self.kinds,
            "xy": self.xy,
            "heading": self.heading,
            "speed": self.speed,
            "length": self.length,
            "width": self.width,
            "valid": self.valid,
            "paths": self.paths,
            "path_points": self.path_points,
            "path_agent": self.path_agent,
            "ego": self.ego,
            "t": self.t,
            "_checked": True,
        }


def _is_polyline(entry: object) -> bool:
    """True when ``entry`` is one polyline (array-like of shape (P, 2)), not a list of them."""
    if isinstance(entry, np.ndarray):
        return entry.ndim == 2
    try:
        first = entry[0]  # type: ignore[index]
    except (IndexError, TypeError, KeyError):
        return True  # empty or scalar: let the shape check report it
    return np.ndim(first) == 1


def _checked(name: str, values: object, dtype: type) -> np.ndarray:
    """``values`` as a new array of ``dtype``, refusing what numpy would coerce silently
    (issue 36): text, objects, booleans as numbers, fractions or out-of-range values as
    integers, anything but booleans (or 0/1) as flags. Raises FrameError naming ``name``."""
    try:
        a = np.asarray(values)
    except (ValueError, TypeError, OverflowError) as exc:  # ragged, or not array-like
        raise FrameError(name, f"not an array of numbers ({exc})") from None
    kind, want = a.dtype.kind, np.dtype(dtype)
    if want.kind == "b":
        if kind in "iu" and a.size and ((a != 0) & (a != 1)).any():
            raise FrameError(name, "expected booleans (or 0/1), got other integers")
        if kind not in "biu":
            raise FrameError(name, f"expected booleans, got {_what(a)}")
    elif want.kind in "iu":
        if kind == "f" and a.size and not (np.isfinite(a).all() and (a == np.round(a)).all()):
            raise FrameError(name, "expected integers, got fractions or non-finite numbers")
        if kind not in "iuf":
            raise FrameError(name, f"expected integers, got {_what(a)}")
        info = np.iinfo(want)  # type: ignore[type-var]
        if a.size and (int(a.min()) < info.min or int(a.max()) > info.max):
            raise FrameError(
                name, f"a value lies outside the {want} range [{info.min}, {info.max}]"
            )
    elif kind not in "iuf":
        raise FrameError(name, f"expected numbers, got {_what(a)}")
    return np.array(a, dtype=dtype)


def _what(a: np.ndarray) -> str:
    """What an array holds, in words, for a message."""
    if a.dtype.kind in "US":
        return f"text ({str(a.flat[0])!r:.30})" if a.size else "text"
    if a.dtype.kind == "O":
        return "Python objects (mixed types, or integers beyond 64 bits)"
    return f"{a.dtype} values"


def _vector(name: str, values: object, n: int, dtype: type) -> np.ndarray:
    a = _checked(name, values, dtype)
    if a.shape != (n,):
        raise FrameError(name, f"expected shape ({n},), got {a.shape}")
    return a


# ---------------------------------------------------------------------- scenes
@dataclass(frozen=True, eq=False)
class Lane:
    """One lane centre line with its successor links (ids of other lanes)."""

    id: int
    centerline: np.ndarray  # (P, 2) float64, m, in driving direction
    successors: tuple[int, ...] = ()
    kind: str = "vehicle"  # vehicle, bike, bus, crosswalk, ...


@dataclass(frozen=True, eq=False)
class MapLine:
    """A map line that is not a lane centre: a lane boundary, road edge, crosswalk, ...

    ``kind`` is one of ``lane_boundary``, ``road_edge``, ``crosswalk``, ``stop_line`` or
    ``other``; ``style`` is the source's own type in free text (``solid_white``,
    ``dashed``, ``median``, ...). ``closed``: a polygon whose last point joins its first
    (crosswalks). Drawn as context only; no model uses it.
    """

    id: int
    kind: str
    points: np.ndarray  # (P, 2) float64, m
    closed: bool = False
    style: str = ""


@dataclass(frozen=True, eq=False)
class LaneMap:
    """The static map of a scene: lane centre lines and their successor links, plus the
    lines drawn around them (lane boundaries, road edges, crosswalks; may be empty)."""

    lanes: tuple[Lane, ...] = ()
    lines: tuple[MapLine, ...] = ()

    def by_id(self) -> dict[int, Lane]:
        return {lane.id: lane for lane in self.lanes}


@dataclass(frozen=True, eq=False)
class Scene:
    """A map, a sequence of frames, and what the source says of itself.

    ``ego_id``: the scene's ego. None: every frame's own ego (``frame.ego_id``), the same
    in every frame. Set, it may be absent or invalid in some frames: a recorded scene keeps
    the steps where its ego is not observed (they matter to ``--ego all`` and to the
    hindsight truth), seen there from another valid agent; readers report such frames as
    ego-less for a replay from the scene's ego.

    ``metadata`` holds string facts (dataset, file, scenario id, converter and version,
    parameters); ``labels`` holds named agent-id lists that a dataset provides (Waymo
    ``objects_of_interest``, ``tracks_to_predict``; Argoverse 2 ``focal``, ``scored``).
    """

    map: LaneMap
    frames: Sequence[Frame]
    frame_period_s: float
    metadata: dict[str, str] = field(default_factory=dict)
    labels: dict[str, tuple[int, ...]] = field(default_factory=dict)
    ego_id: int | None = None
