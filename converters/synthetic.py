"""Synthetic intersection traffic: situations and short scenes, like the paper's dataset.

The paper's experiment (Puphal et al. 2022, Sec. V) sampled about 500 situations at a
crowded four-way intersection from the authors' own simulator, which is not public:
30 to 100 agents, 5 to 100 m between agents, speeds 0 to 25 m/s. This module rebuilds
that: :func:`generate_situation` draws one situation (a one-frame scene) and
:func:`generate_scene` lets it evolve for ``duration_s`` with a car-following model.

Choices the paper leaves open (each a field of :class:`SyntheticSettings`):

- **Agent count** includes the ego; drawn uniformly from ``agents_range`` unless
  ``n_agents`` is set. All agents are vehicles: the paper's experiment has vehicles only
  (pedestrians and cyclists come with the real-data converters).
- **Gaps** are bumper-to-bumper distances between consecutive agents on one lane, drawn
  uniformly from ``gap_range_m``; when a lane's share of agents does not fit, the part of
  each gap above the minimum shrinks by a common factor, so every gap stays in range.
  Where two lanes join (the stop line, the ends of the box) only the minimum gap is
  enforced, and agents on different lanes never overlap at spawn (oriented boxes).
- **Placement**: agents are spread over every lane (incoming, inside the box, outgoing)
  in proportion to lane length; each gets a random route through its lane. The ego is
  on an incoming lane, its centre ``ego_distance_range_m`` before the box.
- **Speeds** are drawn uniformly from ``speed_range_mps``; the desired (IDM) speed from
  ``desired_speed_range_mps``. Turning speeds are not limited (as in the paper, whose
  models predict constant speed along the path anyway).
- **Motion**: the Intelligent Driver Model (Treiber et al. 2000) follows the nearest
  agent ahead on the agent's own route (the lanes it will drive). Agents on crossing or
  merging routes do not yield to each other (the paper's generator does not either).
  A follower never passes through its leader: its position is clamped to touching.
  Integration is ballistic with the frame period as step, a standard choice for IDM.
- **Leaving**: an agent whose centre passes its route's end becomes invalid (it keeps
  its index, so agent indices are stable over the scene). No new agents enter. If the
  ego reaches its route's end, the scene ends at the last frame that still has it.
- **Frames**: ``round(duration_s / frame_period_s)`` frames at ``t = 0, dt, 2 dt, ...``
  (10 s at 10 Hz: 100 frames). Every frame carries every valid agent's forward path:
  its route from its current position to the route's end.
- **Ids**: the ego is id 0, the others 1..N-1.

Determinism: the same settings and seed give the same scene, bit for bit on one machine
(numpy's ``sin`` and ``cos`` may be other code on another CPU).
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import math
from dataclasses import dataclass, field

import numpy as np

from converters.errors import ConversionError
from converters.intersection import (
    Intersection,
    IntersectionSettings,
    build_intersection,
    forward_paths,
    lane_at,
    pose,
)
from risk.frame import Frame, Kind, Scene

CONVERTER = "synthetic-intersection"


@dataclass(frozen=True)
class IdmSettings:
    """Intelligent Driver Model parameters (Treiber, Hennecke, Helbing 2000); SI units.

    Defaults are the usual urban values; ``max_decel_mps2`` caps IDM's unbounded braking
    at what tyres can deliver, for agents spawned too fast too close to a leader.
    """

    time_headway_s: float = 1.5
    jam_gap_m: float = 2.0
    max_accel_mps2: float = 1.5
    comfort_decel_mps2: float = 2.0
    max_decel_mps2: float = 9.0
    exponent: float = 4.0


@dataclass(frozen=True)
class SyntheticSettings:
    """Every parameter of the synthetic intersection traffic (see the module docstring)."""

    intersection: IntersectionSettings = field(default_factory=IntersectionSettings)
    n_agents: int | None = None  # ego included; None: drawn from agents_range
    agents_range: tuple[int, int] = (30, 100)
    gap_range_m: tuple[float, float] = (5.0, 100.0)
    speed_range_mps: tuple[float, float] = (0.0, 25.0)
    desired_speed_range_mps: tuple[float, float] = (10.0, 25.0)
    length_range_m: tuple[float, float] = (4.0, 5.0)
    width_range_m: tuple[float, float] = (1.7, 2.0)
    ego_distance_range_m: tuple[float, float] = (10.0, 60.0)  # ego centre before the box
    duration_s: float = 10.0
    frame_period_s: float = 0.1
    idm: IdmSettings = field(default_factory=IdmSettings)

    def __post_init__(self) -> None:
        lo, hi = self.agents_range
        if not (1 <= lo <= hi):
            raise ConversionError(
                f"agents range must satisfy 1 <= min <= max, got {self.agents_range}"
            )
        if self.n_agents is not None and self.n_agents < 1:
            raise ConversionError(
                f"the number of agents must be >= 1 (the ego), got {self.n_agents}"
            )
        for name in (
            "gap_range_m",
            "speed_range_mps",
            "desired_speed_range_mps",
            "length_range_m",
            "width_range_m",
            "ego_distance_range_m",
        ):
            lo_v, hi_v = getattr(self, name)
            if not (math.isfinite(lo_v) and math.isfinite(hi_v) and 0 <= lo_v <= hi_v):
                raise ConversionError(f"{name} must satisfy 0 <= min <= max, got {(lo_v, hi_v)}")
        if self.gap_range_m[0] <= 0:
            raise ConversionError(f"the minimum gap must be > 0 m, got {self.gap_range_m[0]}")
        if self.length_range_m[0] <= 0 or self.width_range_m[0] <= 0:
            raise ConversionError("vehicle lengths and widths must be > 0 m")
        if not (math.isfinite(self.frame_period_s) and self.frame_period_s > 0):
            raise ConversionError(f"frame period must be > 0 s, got {self.frame_period_s}")
        if not (math.isfinite(self.duration_s) and self.duration_s >= self.frame_period_s):
            raise ConversionError(
                f"duration must be at least one frame period ({self.frame_period_s} s), got {self.duration_s}"
            )
        arm = self.intersection.arm_length_m
        if self.ego_distance_range_m[1] + self.length_range_m[1] > arm:
            raise ConversionError(
                f"the ego must start on its incoming lane: ego distance up to"
                f" {self.ego_distance_range_m[1]} m does not fit on {arm} m arms"
            )

    @property
    def n_frames(self) -> int:
        return max(1, round(self.duration_s / self.frame_period_s))

    def to_json(self) -> str:
        """All settings as JSON (stored in each scene's metadata, for reproduction)."""
        return json.dumps(dataclasses.asdict(self), sort_keys=True)


@dataclass(frozen=True, eq=False)
class Traffic:
    """The state of every agent on its route (``N`` agents; index 0 is the ego)."""

    route: np.ndarray  # (N,) route index
    s_m: np.ndarray  # (N,) arc length of the centre along the route, m
    speed_mps: np.ndarray  # (N,)
    desired_mps: np.ndarray  # (N,)
    length_m: np.ndarray  # (N,)
    width_m: np.ndarray  # (N,)
    active: np.ndarray  # (N,) bool, still on its route


# ---------------------------------------------------------------------- public API
def generate_situation(settings: SyntheticSettings | None = None, seed: int = 0) -> Scene:
    """One situation: a scene with a single frame at ``t = 0`` (paper Sec. V sampling)."""
    s = settings or SyntheticSettings()
    world = build_intersection(s.intersection)
    rng = np.random.default_rng(seed)
    traffic = spawn(world, s, rng)
    return _scene(world, s, seed, traffic, [_frame(world, traffic, 0.0)])


def generate_scene(settings: SyntheticSettings | None = None, seed: int = 0) -> Scene:
    """A situation evolved with IDM car following for ``settings.duration_s``."""
    s = settings or SyntheticSettings()
    world = build_intersection(s.intersection)
    rng = np.random.default_rng(seed)
    traffic = spawn(world, s, rng)
    frames = [_frame(world, traffic, 0.0)]
    for k in range(1, s.n_frames):
        traffic = step(world, traffic, s.idm, s.frame_period_s)
        if not traffic.active[0]:
            break  # the ego has left: the scene ends with it
        frames.append(_frame(world, traffic, k * s.frame_period_s))
    return _scene(world, s, seed, traffic, frames)


def _scene(
    world: Intersection, s: SyntheticSettings, seed: int, traffic: Traffic, frames: list[Frame]
) -> Scene:
    try:
        version = importlib.metadata.version("riskreplay")
    except importlib.metadata.PackageNotFoundError:
        version = "0.0.0+unknown"
    metadata = {
        "source": "synthetic four-way intersection",
        "converter": CONVERTER,
        "converter_version": version,
        "seed": str(seed),
        "n_agents": str(traffic.route.size),
        "lanes_per_direction": str(s.intersection.lanes_per_direction),
        "settings": s.to_json(),
    }
    return Scene(world.lane_map, tuple(frames), s.frame_period_s, metadata)


# ---------------------------------------------------------------------- frames
def _frame(world: Intersection, traffic: Traffic, t: float) -> Frame:
    """The frame of the current traffic state (vectorised over agents)."""
    xy, heading = pose(world.routes, traffic.route, traffic.s_m)
    paths, points = forward_paths(world.routes, traffic.route, traffic.s_m, xy)
    n = traffic.route.size
    return Frame.from_padded(
        ids=np.arange(n),
        kinds=np.full(n, Kind.VEHICLE, dtype=np.int8),
        xy=xy,
        heading=heading,
        speed=traffic.speed_mps,
        length=traffic.length_m,
        width=traffic.width_m,
        valid=traffic.active,
        paths=paths,
        path_points=points,
        path_agent=np.arange(n),
        ego=0,
        t=t,
    )


# ---------------------------------------------------------------------- car following
def route_gaps(world: Intersection, traffic: Traffic) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's leader on its own route: ``(leader index (N,), gap m (N,))``.

    Agent ``b`` is on ``a``'s route when ``b``'s current lane is one of the lanes ``a``
    will drive; its position in ``a``'s arc length is that lane's start on ``a``'s route
    plus ``b``'s distance into the lane. The gap is bumper to bumper. No leader: index
    ``-1``, gap ``inf``. Computed for all pairs at once, ``(N, N)``.
    """
    routes = world.routes
    lane, into = lane_at(routes, traffic.route, traffic.s_m)
    pos = routes.lane_offset_m[traffic.route[:, None], lane[None, :]] + into[None, :]  # (a, b)
    half = 0.5 * traffic.length_m
    gap = pos - traffic.s_m[:, None] - half[:, None] - half[None, :]
    ahead = (pos > traffic.s_m[:, None]) & traffic.active[None, :] & traffic.active[:, None]
    np.fill_diagonal(ahead, False)
    gap = np.where(ahead, gap, np.inf)
    leader = np.argmin(gap, axis=1)
    best = gap[np.arange(gap.shape[0]), leader]
    return np.where(np.isfinite(best), leader, -1), best


def idm_accel(
    v: np.ndarray, v0: np.ndarray, gap: np.ndarray, dv: np.ndarray, p: IdmSettings
) -> np.ndarray:
    """IDM acceleration ``(N,)`` m/s^2; ``gap`` bumper to bumper (inf: free road), ``dv = v - v_leader``."""
    free = 1.0 - (v / np.maximum(v0, 1e-9)) ** p.exponent
    desired_gap = p.jam_gap_m + np.maximum(
        0.0,
        v * p.time_headway_s + v * dv / (2.0 * math.sqrt(p.max_accel_mps2 * p.comfort_decel_mps2)),
    )
    with np.errstate(divide="ignore"):
        interaction = np.where(np.isfinite(gap), (desired_gap / np.maximum(gap, 1e-3)) ** 2, 0.0)
    return np.maximum(p.max_accel_mps2 * (free - interaction), -p.max_decel_mps2)


def step(world: Intersection, traffic: Traffic, p: IdmSettings, dt: float) -> Traffic:
    """Advance every active agent by ``dt`` seconds (ballistic IDM update)."""
    leader, gap = route_gaps(world, traffic)
    v = traffic.speed_mps
    dv = np.where(leader >= 0, v - v[np.maximum(leader, 0)], 0.0)
    a = idm_accel(v, traffic.desired_mps, gap, dv, p)
    v_new = v + a * dt
    # Ballistic step; an agent that would reverse stops where its speed reaches zero.
    stops = v_new < 0
    ds = np.where(stops, v * v / np.maximum(-2.0 * a, 1e-9), (v + v_new) * 0.5 * dt)
    v_new = np.where(stops, 0.0, v_new)
    active = traffic.active
    s_new = np.where(active, traffic.s_m + ds, traffic.s_m)
    v_new = np.where(active, v_new, 0.0)
    # Never pass through the leader: at most touching (its movement this step included).
    has = (leader >= 0) & active
    leader_ds = np.where(has, ds[np.maximum(leader, 0)], 0.0)
    limit = traffic.s_m + gap + leader_ds
    hit = has & (s_new > limit)
    s_new = np.where(hit, limit, s_new)
    v_new = np.where(hit, np.minimum(v_new, v_new[np.maximum(leader, 0)]), v_new)
    still = active & (s_new < world.routes.length_m[traffic.route])
    return dataclasses.replace(
        traffic, s_m=s_new, speed_mps=np.where(still, v_new, 0.0), active=still
    )


# ---------------------------------------------------------------------- spawning
def spawn(world: Intersection, s: SyntheticSettings, rng: np.random.Generator) -> Traffic:
    """Draw one situation: the ego on an incoming lane, the others spread over all lanes."""
    n = (
        s.n_agents
        if s.n_agents is not None
        else int(rng.integers(s.agents_range[0], s.agents_range[1] + 1))
    )
    length = rng.uniform(*s.length_range_m, size=n)
    width = rng.uniform(*s.width_range_m, size=n)
    speed = rng.uniform(*s.speed_range_mps, size=n)
    desired = rng.uniform(*s.desired_speed_range_mps, size=n)

    # The ego: an incoming lane, any route from it, its centre some distance before the box.
    incoming = [k for k, role in enumerate(world.lane_role) if role == "incoming"]
    ego_lane = int(rng.choice(incoming))
    ego_route = int(rng.choice(world.routes_through(ego_lane)))
    ego_s = s.intersection.arm_length_m - rng.uniform(*s.ego_distance_range_m)
    ego_s = max(ego_s, 0.5 * length[0])

    lane, s_lane = _place_on_lanes(world, s, rng, length, ego_lane, ego_s)
    route = np.array(
        [ego_route] + [int(rng.choice(world.routes_through(int(k)))) for k in lane[1:]]
    )
    s_route = world.routes.lane_offset_m[route, lane] + s_lane
    traffic = Traffic(route, s_route, speed, desired, length, width, np.ones(n, dtype=bool))
    return _resolve_conflicts(world, s, rng, traffic)


def _place_on_lanes(
    world: Intersection,
    s: SyntheticSettings,
    rng: np.random.Generator,
    length: np.ndarray,
    ego_lane: int,
    ego_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Lane ``(N,)`` and arc length in the lane ``(N,)`` of every agent (ego first)."""
    n = length.size
    gap_min = s.gap_range_m[0]
    lane_len = world.lane_length_m
    capacity = np.floor((lane_len + gap_min) / (s.length_range_m[1] + gap_min)).astype(int)
    capacity[ego_lane] = max(0, capacity[ego_lane] - 2)  # the ego and its gaps need room
    counts = _allocate(n - 1, lane_len, capacity, rng)
    lanes = [np.array([ego_lane])]
    positions = [np.array([ego_s])]
    cursor = 1
    for k in np.flatnonzero(counts):
        m = int(counts[k])
        lens = length[cursor : cursor + m]
        if k == ego_lane:
            # Split the lane at the ego: the agents behind and ahead of it, by room.
            behind_room = ego_s - 0.5 * length[0]
            ahead_room = lane_len[k] - ego_s - 0.5 * length[0]
            m_behind = int(rng.binomial(m, behind_room / max(behind_room + ahead_room, 1e-9)))
            m_behind = int(np.clip(m_behind, m - _fits(ahead_room, s), _fits(behind_room, s)))
            pos_b = _chain(lens[:m_behind], 0.0, behind_room, "end", s, rng)
            pos_a = _chain(lens[m_behind:], lane_len[k] - ahead_room, lane_len[k], "start", s, rng)
            pos = np.concatenate((pos_b, pos_a))
        else:
            pos = _chain(lens, 0.0, lane_len[k], None, s, rng)
        lanes.append(np.full(m, k))
        positions.append(pos)
        cursor += m
    return np.concatenate(lanes), np.concatenate(positions)


def _fits(room: float, s: SyntheticSettings) -> int:
    """How many agents fit beside an anchored neighbour in ``room`` metres (worst case)."""
    per = s.length_range_m[1] + s.gap_range_m[0]
    return max(0, math.floor(room / per))


def _allocate(
    n: int, weight: np.ndarray, capacity: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Spread ``n`` agents over lanes in proportion to ``weight`` without exceeding capacity."""
    if n > capacity.sum():
        raise ConversionError(
            f"{n + 1} agents do not fit on this intersection (room for about {capacity.sum() + 1});"
            " use fewer agents, longer arms or more lanes"
        )
    counts = np.zeros(weight.size, dtype=int)
    left = n
    while left:
        room = capacity - counts
        p = np.where(room > 0, weight, 0.0)
        draw = rng.multinomial(left, p / p.sum())
        add = np.minimum(draw, room)
        counts += add
        left -= int(add.sum())
    return counts


def _chain(
    lengths: np.ndarray,
    start: float,
    end: float,
    anchor: str | None,
    s: SyntheticSettings,
    rng: np.random.Generator,
) -> np.ndarray:
    """Centres ``(m,)`` of ``m = len(lengths)`` agents in ``[start, end]``, in order.

    Consecutive bumper gaps are drawn from ``gap_range_m``. ``anchor`` "start" / "end"
    means an agent (the ego) touches that end from outside, so the chain's first / last
    agent also keeps a gap in range to it; otherwise the chain sits at a random offset.
    """
    m = lengths.size
    if m == 0:
        return np.zeros(0)
    gap_min, gap_max = s.gap_range_m
    n_gaps = m if anchor is not None else m - 1
    room = end - start - lengths.sum()
    gaps = rng.uniform(gap_min, gap_max, size=n_gaps)
    excess = gaps.sum() - room
    if excess > 0:  # shrink the part above the minimum, so every gap stays in range
        spare = gaps - gap_min
        gaps = gap_min + spare * max(0.0, 1.0 - excess / max(spare.sum(), 1e-12))
    slack = max(0.0, room - gaps.sum())
    if anchor == "start":
        lead, before = 0.0, gaps
    else:
        lead = slack if anchor == "end" else rng.uniform(0.0, slack)
        before = np.concatenate(([0.0], gaps[: m - 1]))
    rear = start + lead + np.cumsum(before) + np.concatenate(([0.0], np.cumsum(lengths[:-1])))
    return rear + 0.5 * lengths


# ---------------------------------------------------------------------- conflicts
OVERLAP_MARGIN_M = 0.5
"""Clearance required between bodies on different lanes at spawn; below the 1.5 m that
3.5 m lanes leave between 2 m wide vehicles, so neighbours on parallel lanes are fine."""


def conflicts(
    world: Intersection, s: SyntheticSettings, traffic: Traffic, rows: np.ndarray | None = None
) -> np.ndarray:
    """``(A, N)`` bool for the agents ``rows`` (default all, then symmetric ``(N, N)``)
    against every agent: closer than the minimum gap on a shared route (either agent's),
    or bodies (oriented rectangles plus ``OVERLAP_MARGIN_M``) overlapping. An agent never
    conflicts with itself."""
    n = traffic.route.size
    rows = np.arange(n) if rows is None else np.asarray(rows)
    routes = world.routes
    lane, into = lane_at(routes, traffic.route, traffic.s_m)
    half = 0.5 * traffic.length_m
    # b's position along a's route, and a's along b's (NaN: not on that route).
    b_on_a = routes.lane_offset_m[traffic.route[rows][:, None], lane[None, :]] + into[None, :]
    a_on_b = routes.lane_offset_m[traffic.route[None, :], lane[rows][:, None]] + into[rows][:, None]
    with np.errstate(invalid="ignore"):
        limit = half[rows][:, None] + half[None, :] + s.gap_range_m[0]
        close = (np.abs(b_on_a - traffic.s_m[rows][:, None]) < limit) | (
            np.abs(a_on_b - traffic.s_m[None, :]) < limit
        )
    xy, heading = pose(routes, traffic.route, traffic.s_m)
    over = boxes_overlap(
        xy[rows], heading[rows], traffic.length_m[rows], traffic.width_m[rows],
        xy, heading, traffic.length_m, traffic.width_m, OVERLAP_MARGIN_M,
    )  # fmt: skip
    c = close | over
    c[np.arange(rows.size), rows] = False
    return c


def boxes_overlap(
    xy_a: np.ndarray,
    heading_a: np.ndarray,
    length_a: np.ndarray,
    width_a: np.ndarray,
    xy_b: np.ndarray,
    heading_b: np.ndarray,
    length_b: np.ndarray,
    width_b: np.ndarray,
    margin_m: float = 0.0,
) -> np.ndarray:
    """``(A, B)`` bool: rectangles ``a`` and ``b`` are closer than ``margin_m`` (or overlap).

    Separating axis test on the four body axes; metres and radians, centres ``(.., 2)``.
    """
    da = np.stack((np.cos(heading_a), np.sin(heading_a)), axis=1)[:, None]  # (A, 1, 2)
    db = np.stack((np.cos(heading_b), np.sin(heading_b)), axis=1)[None]  # (1, B, 2)
    na, nb = da[..., ::-1] * [-1, 1], db[..., ::-1] * [-1, 1]
    delta = xy_b[None] - xy_a[:, None]  # (A, B, 2)
    cos = np.abs((da * db).sum(-1))  # |cos| of the angle between the bodies
    sin = np.abs((da * nb).sum(-1))
    la, wa = 0.5 * length_a[:, None], 0.5 * width_a[:, None]
    lb, wb = 0.5 * length_b[None], 0.5 * width_b[None]
    gaps = (
        np.abs((delta * da).sum(-1)) - la - lb * cos - wb * sin,  # along a's length
        np.abs((delta * na).sum(-1)) - wa - lb * sin - wb * cos,  # along a's width
        np.abs((delta * db).sum(-1)) - lb - la * cos - wa * sin,
        np.abs((delta * nb).sum(-1)) - wb - la * sin - wa * cos,
    )
    return ~np.logical_or.reduce([g > margin_m for g in gaps])


def _resolve_conflicts(
    world: Intersection, s: SyntheticSettings, rng: np.random.Generator, traffic: Traffic
) -> Traffic:
    """Keep a conflict-free set (ego first, others in random order); re-place the rest.

    A re-placed agent gets a random lane (by length), position and route, and is kept
    when it conflicts with no kept agent; only the minimum gap applies to it.
    """
    n = traffic.route.size
    c = conflicts(world, s, traffic)
    kept = np.zeros(n, dtype=bool)
    for i in np.concatenate(([0], 1 + rng.permutation(n - 1))):
        kept[i] = not (c[i] & kept).any()
    route, s_m = traffic.route.copy(), traffic.s_m.copy()
    weights = world.lane_length_m / world.lane_length_m.sum()
    for i in np.flatnonzero(~kept):
        for _ in range(_MAX_TRIES):
            lane = int(rng.choice(world.n_lanes, p=weights))
            route[i] = int(rng.choice(world.routes_through(lane)))
            half = 0.5 * traffic.length_m[i]
            into = rng.uniform(half, max(half, world.lane_length_m[lane] - half))
            s_m[i] = world.routes.lane_offset_m[route[i], lane] + into
            trial = dataclasses.replace(traffic, route=route, s_m=s_m)
            if not (conflicts(world, s, trial, rows=np.array([i]))[0] & kept).any():
                kept[i] = True
                break
        else:
            raise ConversionError(
                f"could not place {n} agents without overlaps after {_MAX_TRIES} tries per agent;"
                " use fewer agents, longer arms or more lanes"
            )
    return dataclasses.replace(traffic, route=route, s_m=s_m)


_MAX_TRIES = 200
