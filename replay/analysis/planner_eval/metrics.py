"""Closed-loop metrics in nuPlan's spirit: collisions classified, at fault or not,
drivable area, driving direction, progress along the recorded route, least
time-to-collision, comfort, and one score per run.

Pure numpy over a run's history: the ego's states ``(T,)`` (:class:`EgoHistory`) and the
others' boxes ``(T, K)`` (:class:`OthersHistory`); every test is a ``(T, K)`` boolean mask,
with no Python loop over objects. The rules and thresholds are nuPlan's
(nuplan-devkit ``planning/metrics``: ``no_ego_at_fault_collisions``,
``drivable_area_compliance``, ``driving_direction_compliance``,
``ego_progress_along_expert_route``, ``time_to_collision_within_bound``,
``ego_is_comfortable``; the weights of ``closed_loop_reactive_agents_weighted_average``),
written here anew; where our scenes lack what nuPlan's map has, the approximation is
named where it is made. docs/planners.md ("Closed-loop metrics and score") states them.

Reference point: nuPlan classifies "behind" and "ahead" from the ego's rear axle; our
``EgoHistory.xy`` is the box centre, and :attr:`EgoHistory.rear_axle_xy` is the one
converted value (the axle :data:`REAR_AXLE_SHARE` of the length behind the centre).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from risk import geometry
from risk.frame import Kind
from risk.hindsight import box_corners, boxes_overlap

#: At or below this speed (m/s) the ego or a track is stopped (nuPlan: 5e-2).
STOPPED_MPS = 0.05
#: A track whose centre lies more than this off the ego's heading, seen from the rear
#: axle, is behind (nuPlan: 150 degrees); within AHEAD_RAD it is ahead (30 degrees).
BEHIND_RAD = math.radians(150.0)
AHEAD_RAD = math.radians(30.0)
#: The rear axle lies this share of the length behind the box centre (nuPlan's car:
#: 1.461 m behind the centre of a 5.176 m box).
REAR_AXLE_SHARE = 1.461 / 5.176
#: A corner this far (m) outside every drivable lane fails drivable-area compliance.
DRIVABLE_TOLERANCE_M = 0.3
#: Driving direction: negative progress along the lane over DIRECTION_WINDOW_S up to
#: DIRECTION_OK_M is fine (1), up to DIRECTION_BAD_M half (0.5), beyond it 0.
DIRECTION_OK_M = 2.0
DIRECTION_BAD_M = 6.0
DIRECTION_WINDOW_S = 1.0
#: Progress: ratio min(1, max(ego, P)/max(expert, P)) with P this (m); 0 when the ego
#: went back by more than P; "making progress" needs a ratio of at least MIN_PROGRESS_RATIO.
PROGRESS_THRESHOLD_M = 2.0
MIN_PROGRESS_RATIO = 0.2
#: Time-to-collision: constant velocity, steps of TTC_STEP_S up to TTC_HORIZON_S
#: (exclusive, as nuPlan's arange); within bound when the least is >= LEAST_TTC_S; not
#: computed while the ego is below TTC_STOPPED_MPS.
TTC_STEP_S = 0.1
TTC_HORIZON_S = 3.0
LEAST_TTC_S = 0.95
TTC_STOPPED_MPS = 0.005
#: Comfort bounds (nuPlan's): longitudinal acceleration (m/s²), |lateral acceleration|,
#: |jerk| and |longitudinal jerk| (m/s³), |yaw rate| (rad/s), |yaw acceleration| (rad/s²).
MIN_LON_ACCEL_MPS2 = -4.05
MAX_LON_ACCEL_MPS2 = 2.40
MAX_LAT_ACCEL_MPS2 = 4.89
MAX_JERK_MPS3 = 8.37
MAX_LON_JERK_MPS3 = 4.13
MAX_YAW_RATE_RPS = 0.95
MAX_YAW_ACCEL_RPS2 = 1.93
#: Score weights (nuPlan's closed-loop weighted average; its speed-limit term, weight 4,
#: is left out: our maps carry no speed limits).
WEIGHT_PROGRESS = 5.0
WEIGHT_TTC = 5.0
WEIGHT_COMFORT = 2.0
#: At-fault collisions allowed per class before the factor reaches 0: VRUs, vehicles,
#: objects (factor max(0, 1 - n / (allowed + 1)) per class, multiplied).
ALLOWED_AT_FAULT = {"vru": 0, "vehicle": 0, "object": 1}


class CollisionType(enum.IntEnum):
    """nuPlan's collision classes, decided in this order at a track's first overlap."""

    STOPPED_EGO = 0
    STOPPED_TRACK = 1
    ACTIVE_FRONT = 2
    ACTIVE_REAR = 3
    ACTIVE_LATERAL = 4


@dataclass(frozen=True, eq=False)
class EgoHistory:
    """The simulated ego at ``T`` steps: ``times_s`` (T,) s, box centre ``xy`` (T, 2) m,
    ``heading_rad`` (T,), ``speed_mps`` (T,), box ``length_m`` and ``width_m``."""

    times_s: np.ndarray
    xy: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    length_m: float
    width_m: float

    @property
    def rear_axle_xy(self) -> np.ndarray:
        """The rear axle (T, 2) m: REAR_AXLE_SHARE of the length behind the centre."""
        back = REAR_AXLE_SHARE * self.length_m
        return self.xy - back * np.stack([np.cos(self.heading_rad), np.sin(self.heading_rad)], 1)

    def corners(self) -> np.ndarray:
        """The box corners (T, 4, 2): front-left, rear-left, rear-right, front-right."""
        length, width = self.size()
        return box_corners(self.xy[:, 0], self.xy[:, 1], self.heading_rad, length, width)

    def rows(self, which: np.ndarray) -> EgoHistory:
        """The steps selected by a mask or index array (T,)."""
        return EgoHistory(
            times_s=self.times_s[which], xy=self.xy[which], heading_rad=self.heading_rad[which],
            speed_mps=self.speed_mps[which], length_m=self.length_m, width_m=self.width_m,
        )  # fmt: skip

    def size(self) -> tuple[np.ndarray, np.ndarray]:
        """Length and width as arrays (the box functions broadcast them)."""
        return np.asarray(self.length_m, dtype=np.float64), np.asarray(
            self.width_m, dtype=np.float64
        )


@dataclass(frozen=True, eq=False)
class OthersHistory:
    """The other objects at the same ``T`` steps: ``ids``, ``kinds`` (K,) (risk.Kind
    codes); ``xy`` (T, K, 2) m, ``heading_rad``, ``speed_mps``, ``length_m``, ``width_m``,
    ``valid`` (T, K) (present at that step)."""

    ids: np.ndarray
    kinds: np.ndarray
    xy: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    length_m: np.ndarray
    width_m: np.ndarray
    valid: np.ndarray


@dataclass(frozen=True, eq=False)
class Collisions:
    """``overlap`` (T, K): the boxes touch; ``first_step`` (K,): each track's first
    overlap (-1: none); ``kind`` (K,): its :class:`CollisionType` there (-1: none);
    ``at_fault`` (K,)."""

    overlap: np.ndarray
    first_step: np.ndarray
    kind: np.ndarray
    at_fault: np.ndarray

    def count(self, kind: CollisionType) -> int:
        return int((self.kind == kind).sum())

    @property
    def n(self) -> int:
        return int((self.first_step >= 0).sum())


def _heading_unit(heading: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(heading), np.sin(heading)], axis=-1)


def angle_from_heading(origin: np.ndarray, heading: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Angle (rad, in [0, pi]) between ``heading`` (T,) and the direction from ``origin``
    (T, 2) to ``points`` (T, K, 2)."""
    rel = points - origin[:, None, :]
    along = (rel * _heading_unit(heading)[:, None, :]).sum(axis=-1)
    norm = np.hypot(rel[..., 0], rel[..., 1])
    return np.arccos(np.clip(along / np.where(norm > 0, norm, 1.0), -1.0, 1.0))


def box_overlaps(ego: EgoHistory, others: OthersHistory) -> np.ndarray:
    """(T, K): the ego's box touches the other's, where the other is present."""
    length, width = ego.size()
    hit = boxes_overlap(
        ego.xy[:, None, 0], ego.xy[:, None, 1], ego.heading_rad[:, None], length, width,
        others.xy[..., 0], others.xy[..., 1], others.heading_rad, others.length_m,
        others.width_m,
    )  # fmt: skip
    return hit & others.valid


#: nuPlan simulates and judges at 0.1 s; a history sampled more coarsely (SinD's logs at
#: 2 Hz, inD's at 5 Hz) is interpolated at this step between the samples around a first
#: overlap, to classify the contact where nuPlan would first see it.
CONTACT_STEP_S = 0.1


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _first_contact(
    ego: EgoHistory, others: OthersHistory, first: np.ndarray, cols: np.ndarray
) -> dict[str, np.ndarray]:
    """The ego's and each track's states ``(C,)`` at the track's first contact: at its
    first overlapping step ``first`` ``(C,)`` (> 0), or, where the steps are longer than
    CONTACT_STEP_S and the track was present the step before, at the first CONTACT_STEP_S
    sub-step between the two at which the boxes, both interpolated linearly (positions,
    headings the short way round, speeds), overlap. nuPlan samples every 0.1 s: a coarse
    history first sees a contact deeper in, where a side contact already looks like one
    of the ego's front edge."""
    t1 = first
    t0 = np.maximum(first - 1, 0)
    dt = ego.times_s[t1] - ego.times_s[t0] if ego.times_s.size > 1 else np.zeros(first.size)
    n_sub = np.where((first > 0) & others.valid[t0, cols], np.ceil(dt / CONTACT_STEP_S - 1e-6), 1)
    n_sub = np.maximum(n_sub, 1).astype(np.int64)
    n_max = int(n_sub.max(initial=1))
    # sub-step fractions (C, S): 1/n, 2/n, ..., 1 then held at 1
    u = np.minimum(np.arange(1, n_max + 1)[None, :] / n_sub[:, None], 1.0)

    def lerp(a0: np.ndarray, a1: np.ndarray) -> np.ndarray:  # (C, 2) -> (C, S, 2)
        return np.asarray(a0[:, None] + u[..., None] * (a1 - a0)[:, None])

    e_xy = lerp(ego.xy[t0], ego.xy[t1])
    e_h = (
        ego.heading_rad[t0][:, None] + u * _wrap(ego.heading_rad[t1] - ego.heading_rad[t0])[:, None]
    )
    o_xy = lerp(others.xy[t0, cols], others.xy[t1, cols])
    o_h = (
        others.heading_rad[t0, cols][:, None]
        + u * _wrap(others.heading_rad[t1, cols] - others.heading_rad[t0, cols])[:, None]
    )
    length, width = ego.size()
    hit = boxes_overlap(
        e_xy[..., 0], e_xy[..., 1], e_h, length, width, o_xy[..., 0], o_xy[..., 1], o_h,
        others.length_m[t1, cols][:, None], others.width_m[t1, cols][:, None],
    )  # fmt: skip
    hit[:, -1] = True  # the step itself overlaps
    j = np.argmax(hit, axis=1)
    rows = np.arange(first.size)
    w = u[rows, j]
    return {
        "ego_xy": e_xy[rows, j], "ego_heading": e_h[rows, j],
        "ego_speed": ego.speed_mps[t0] + w * (ego.speed_mps[t1] - ego.speed_mps[t0]),
        "xy": o_xy[rows, j], "heading": o_h[rows, j],
        "speed": others.speed_mps[t0, cols] + w * (
            others.speed_mps[t1, cols] - others.speed_mps[t0, cols]
        ),
        "step": np.where(w < 0.5, t0, t1),
    }  # fmt: skip


def classify_collisions(
    ego: EgoHistory, others: OthersHistory, ego_in_lane: np.ndarray
) -> Collisions:
    """Each track's first overlap with the ego, classified in nuPlan's order: ego stopped
    (not at fault); track stopped (at fault); track centre more than 150 degrees off the
    ego's heading from its rear axle, i.e. behind (not at fault); the ego's front edge
    touches the track (at fault); else lateral, at fault only when the ego was not in its
    lane (``ego_in_lane`` (T,); nuPlan: the ego's corners not on common or connected
    lanes, a lane change). A track that already overlaps the ego at the first step (the
    logged start: overlapping boxes in the recording itself), or at its own first step
    (a track that begins inside the ego's box: a recording's track starts where the
    sensor first saw it, a MONA car 0.3 m ahead of the ego's bumper), is counted but never
    at fault: the planner had no say in it. With steps longer than nuPlan's 0.1 s the
    contact is classified at its first 0.1 s sub-step (:func:`_first_contact`)."""
    overlap = box_overlaps(ego, others)
    k = overlap.shape[1]
    any_hit = overlap.any(axis=0)
    first = np.where(any_hit, np.argmax(overlap, axis=0), -1)
    t = np.maximum(first, 0)
    cols = np.arange(k)
    at = _first_contact(ego, others, t, cols)
    h = at["ego_heading"]
    ego_stopped = at["ego_speed"] <= STOPPED_MPS
    track_stopped = at["speed"] <= STOPPED_MPS
    rear_axle = at["ego_xy"] - REAR_AXLE_SHARE * ego.length_m * _heading_unit(h)
    behind = angle_from_heading(rear_axle, h, at["xy"][:, None, :])[:, 0] > BEHIND_RAD
    front_centre = at["ego_xy"] + 0.5 * ego.length_m * _heading_unit(h)
    front = boxes_overlap(
        front_centre[:, 0], front_centre[:, 1], h, np.zeros(1), ego.size()[1],
        at["xy"][:, 0], at["xy"][:, 1], at["heading"],
        others.length_m[t, cols], others.width_m[t, cols],
    )  # fmt: skip
    kind = np.select(
        [ego_stopped, track_stopped, behind, front],
        [CollisionType.STOPPED_EGO, CollisionType.STOPPED_TRACK, CollisionType.ACTIVE_REAR,
         CollisionType.ACTIVE_FRONT],
        default=CollisionType.ACTIVE_LATERAL,
    ).astype(np.int64)  # fmt: skip
    kind = np.where(any_hit, kind, -1)
    at_fault = (
        (kind == CollisionType.STOPPED_TRACK)
        | (kind == CollisionType.ACTIVE_FRONT)
        | ((kind == CollisionType.ACTIVE_LATERAL) & ~np.asarray(ego_in_lane, bool)[at["step"]])
    ) & (first > np.argmax(others.valid, axis=0))  # not at the track's own first step
    return Collisions(overlap=overlap, first_step=first, kind=kind, at_fault=at_fault)


def at_fault_factor(collisions: Collisions, kinds: np.ndarray) -> float:
    """nuPlan's collision factor: per class (VRUs, vehicles, objects) max(0, 1 - n /
    (allowed + 1)), multiplied."""
    vru = np.isin(kinds, (Kind.PEDESTRIAN, Kind.CYCLIST))
    vehicle = kinds == Kind.VEHICLE
    factor = 1.0
    for name, members in (("vru", vru), ("vehicle", vehicle), ("object", ~(vru | vehicle))):
        n = int((collisions.at_fault & members).sum())
        factor *= max(0.0, 1.0 - n / (ALLOWED_AT_FAULT[name] + 1))
    return factor


def in_lane(ego: EgoHistory, reference: np.ndarray, lane_width_m: float) -> np.ndarray:
    """(T,): all four corners lie within half a lane width of the reference path.

    Approximates nuPlan's "the ego's corners are on common or connected lanes" with the
    ego's reference lane (our maps have centre lines but no lane polygons)."""
    corners = ego.corners().reshape(-1, 2)
    dist, _ = geometry.project_points(
        corners, reference, geometry.cumulative_lengths(reference[None])[0]
    )
    return np.asarray((dist.reshape(-1, 4) <= 0.5 * lane_width_m).all(axis=1), dtype=bool)


def _segments(
    lanes: list[np.ndarray], near: np.ndarray, margin_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Start points and vectors (S, 2) of the lane segments whose box comes within
    ``margin_m`` of the points ``near`` (n, 2)."""
    if not lanes:
        return np.zeros((0, 2)), np.zeros((0, 2))
    starts = np.concatenate([c[:-1] for c in lanes])
    ends = np.concatenate([c[1:] for c in lanes])
    lo, hi = near.min(axis=0) - margin_m, near.max(axis=0) + margin_m
    keep = (np.maximum(starts, ends) >= lo).all(axis=1) & (np.minimum(starts, ends) <= hi).all(
        axis=1
    )
    keep &= np.any(ends != starts, axis=1)
    return starts[keep], ends[keep] - starts[keep]


def _nearest_segment(
    points: np.ndarray, a: np.ndarray, ab: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distance (n,) from each point to the nearest segment, and that segment's index."""
    rel = points[:, None, :] - a[None]
    len2 = (ab**2).sum(axis=1)
    t = np.clip((rel * ab[None]).sum(axis=-1) / len2[None], 0.0, 1.0)
    d2 = ((rel - t[..., None] * ab[None]) ** 2).sum(axis=-1)
    best = np.argmin(d2, axis=1)
    return np.sqrt(d2[np.arange(points.shape[0]), best]), best


#: Lane segments farther than this (m) from every corner are not looked at.
CORRIDOR_SEARCH_M = 20.0


def corridor_excursion_m(
    ego: EgoHistory, lanes: list[np.ndarray], lane_width_m: float
) -> np.ndarray:
    """How far (m) the ego's farthest corner lies outside the drivable corridor at each
    step (T,) (<= 0: inside; inf: no lane within CORRIDOR_SEARCH_M). The corridor is
    every drivable lane centre line (``lanes``, (P, 2) each) widened to ``lane_width_m``;
    nuPlan uses the map's lane polygons and drivable layer, which our scenes lack."""
    corners = ego.corners().reshape(-1, 2)
    a, ab = _segments(lanes, corners, CORRIDOR_SEARCH_M)
    if a.shape[0] == 0:
        return np.full(ego.xy.shape[0], np.inf)
    dist, _ = _nearest_segment(corners, a, ab)
    return np.asarray((dist - 0.5 * lane_width_m).reshape(-1, 4).max(axis=1), dtype=np.float64)


def drivable_area_ok(
    ego: EgoHistory, lanes: list[np.ndarray], lane_width_m: float, *, allowance_m: float = 0.0
) -> tuple[bool | None, np.ndarray]:
    """Whether no corner ever lay DRIVABLE_TOLERANCE_M (plus ``allowance_m``) or more
    outside the drivable corridor (:func:`corridor_excursion_m`), and the per-step flags
    (T,). None (and all True) without lanes.

    ``allowance_m``: where the corridor is too narrow for the road (a lane wider than
    ``lane_width_m``, a gore without a centre line) the recorded driver leaves it too; the
    closed loop passes the logged ego's own worst excursion here, so that the expert
    always complies, as nuPlan's expert does on its map."""
    if not lanes:
        return None, np.ones(ego.xy.shape[0], dtype=bool)
    excursion = corridor_excursion_m(ego, lanes, lane_width_m)
    ok = np.asarray(excursion < DRIVABLE_TOLERANCE_M + max(allowance_m, 0.0), dtype=bool)
    return bool(ok.all()), ok


def driving_direction(
    ego: EgoHistory, lanes: list[np.ndarray], lane_width_m: float
) -> tuple[float, float]:
    """nuPlan's driving-direction score (1, 0.5 or 0) and the worst progress (m, <= 0)
    along the lane direction over any DIRECTION_WINDOW_S.

    Each step's displacement is projected on the direction of the nearest drivable lane
    (within half a lane width of the centre; none: 0, as nuPlan off its lanes)."""
    n = ego.xy.shape[0]
    if n < 2 or not lanes:
        return 1.0, 0.0
    a, ab = _segments(lanes, ego.xy, lane_width_m)
    if a.shape[0] == 0:
        return 1.0, 0.0
    dist, seg = _nearest_segment(ego.xy[:-1], a, ab)
    unit = ab[seg] / np.linalg.norm(ab[seg], axis=1, keepdims=True)
    step = ((ego.xy[1:] - ego.xy[:-1]) * unit).sum(axis=1)
    step = np.where(dist <= 0.5 * lane_width_m, step, 0.0)
    dt = float(np.mean(np.diff(ego.times_s)))
    window = max(1, round(DIRECTION_WINDOW_S / dt)) if dt > 0 else 1
    cum = np.r_[0.0, np.cumsum(step)]
    over = cum[window:] - cum[:-window] if cum.size > window else cum[-1:] - cum[:1]
    worst = float(min(0.0, over.min(initial=0.0)))
    score = 1.0 if -worst < DIRECTION_OK_M else 0.5 if -worst < DIRECTION_BAD_M else 0.0
    return score, worst


def progress_ratio(ego_progress_m: float, expert_progress_m: float) -> float:
    """nuPlan's ego-to-expert progress ratio: 0 when the ego went back by more than
    PROGRESS_THRESHOLD_M, else min(1, max(ego, P) / max(expert, P))."""
    if ego_progress_m < -PROGRESS_THRESHOLD_M:
        return 0.0
    p = PROGRESS_THRESHOLD_M
    return min(1.0, max(ego_progress_m, p) / max(expert_progress_m, p))


def time_to_collision(
    ego: EgoHistory, others: OthersHistory, collisions: Collisions, ego_in_lane: np.ndarray
) -> np.ndarray:
    """Least time-to-collision (T,) s, inf where none within TTC_HORIZON_S.

    At every step the ego and each track move on at constant velocity along their
    headings; the first TTC_STEP_S multiple at which the boxes touch is the TTC. Tracks
    counted: present, not yet collided with (from their first overlap on), and ahead
    (within 30 degrees of the ego's heading, from the rear axle) or, when the ego is
    not in its lane, not behind. 0 at the step of an at-fault collision; inf while the
    ego stands (nuPlan's rules; its intersection clause is left out: no intersection
    layer)."""
    steps = np.arange(1, round(TTC_HORIZON_S / TTC_STEP_S)) * TTC_STEP_S  # (S,)
    n_t = others.valid.shape[0]
    ttc = np.full(n_t, np.inf)
    t_idx = np.arange(n_t)[:, None]
    collided = (collisions.first_step[None, :] >= 0) & (t_idx >= collisions.first_step[None, :])
    angle = angle_from_heading(ego.rear_axle_xy, ego.heading_rad, others.xy)  # (T, K)
    counted = (angle < AHEAD_RAD) | (
        ~np.asarray(ego_in_lane, bool)[:, None] & (angle <= BEHIND_RAD)
    )
    moving = ego.speed_mps > TTC_STOPPED_MPS
    counted &= others.valid & ~collided & moving[:, None]
    # Only pairs that can meet within the horizon (centres within travel plus diagonals).
    reach = (ego.speed_mps[:, None] + others.speed_mps) * TTC_HORIZON_S + 0.5 * (
        math.hypot(ego.length_m, ego.width_m) + np.hypot(others.length_m, others.width_m)
    )
    gap = np.hypot(*(others.xy - ego.xy[:, None, :]).transpose(2, 0, 1))
    ti, ki = np.nonzero(counted & (gap <= reach))
    if ti.size:
        ego_v = (ego.speed_mps[ti, None] * _heading_unit(ego.heading_rad[ti]))[:, None, :]
        other_v = (others.speed_mps[ti, ki, None] * _heading_unit(others.heading_rad[ti, ki]))[
            :, None, :
        ]
        ego_xy = ego.xy[ti, None, :] + ego_v * steps[None, :, None]  # (C, S, 2)
        other_xy = others.xy[ti, ki, None, :] + other_v * steps[None, :, None]
        hit = boxes_overlap(
            ego_xy[..., 0], ego_xy[..., 1], ego.heading_rad[ti, None], *ego.size(),
            other_xy[..., 0], other_xy[..., 1], others.heading_rad[ti, ki, None],
            others.length_m[ti, ki, None], others.width_m[ti, ki, None],
        )  # (C, S)  # fmt: skip
        first = np.where(hit.any(axis=1), steps[np.argmax(hit, axis=1)], np.inf)
        np.minimum.at(ttc, ti, first)
    fault_steps = collisions.first_step[collisions.at_fault]
    ttc[fault_steps] = 0.0
    return ttc


def _savgol_derivative(
    y: np.ndarray, dt: float, *, window: int, order: int, deriv: int
) -> np.ndarray:
    """Savitzky-Golay derivative of ``y`` (n,) on a grid of step ``dt``: a polynomial of
    ``order`` fitted over ``window`` samples (shrunk to fit ``n``, odd), differentiated
    ``deriv`` times; at the ends the edge window's polynomial (scipy's ``mode='interp'``)."""
    n = y.size
    w = min(window, n if n % 2 else n - 1)
    if w <= order:
        return np.full(n, np.nan)
    h = w // 2
    x = np.arange(w) - h
    pinv = np.linalg.pinv(np.vander(x, order + 1, increasing=True))  # (order+1, w)
    # Derivative of the fitted polynomial at each offset z of the window: (w, w) rows.
    powers = np.arange(order + 1)
    factor = np.array([math.perm(p, deriv) if p >= deriv else 0 for p in powers], float)
    z = np.arange(w) - h
    basis = factor[None, :] * np.where(
        powers[None, :] >= deriv, z[:, None] ** np.maximum(powers - deriv, 0)[None, :], 0.0
    )
    rows = basis @ pinv / dt**deriv  # (w, w)
    start = np.clip(np.arange(n) - h, 0, n - w)
    windows = y[start[:, None] + np.arange(w)[None, :]]  # (n, w)
    return (rows[np.arange(n) - start] * windows).sum(axis=1)


@dataclass(frozen=True)
class Comfort:
    """The extremes of the ego's motion and whether all lie within nuPlan's bounds."""

    min_lon_accel_mps2: float
    max_lon_accel_mps2: float
    max_abs_lat_accel_mps2: float
    max_abs_jerk_mps3: float
    max_abs_lon_jerk_mps3: float
    max_abs_yaw_rate_rps: float
    max_abs_yaw_accel_rps2: float
    comfortable: bool


def comfort(ego: EgoHistory) -> Comfort:
    """Accelerations, jerks and yaw rates of the run (Savitzky-Golay derivatives as
    nuPlan: quadratic, 7 samples for the acceleration, 15 for jerk and yaw rate, cubic
    for the yaw acceleration), within nuPlan's comfort bounds. Fewer than 4 steps: NaN
    extremes, comfortable (nothing to judge)."""
    n = ego.speed_mps.size
    dt = float(np.mean(np.diff(ego.times_s))) if n > 1 else 0.0
    if n < 4 or dt <= 0:
        nan = math.nan
        return Comfort(nan, nan, nan, nan, nan, nan, nan, True)
    lon = _savgol_derivative(ego.speed_mps, dt, window=7, order=2, deriv=1)
    heading = np.unwrap(ego.heading_rad)
    yaw_rate = _savgol_derivative(heading, dt, window=15, order=2, deriv=1)
    yaw_accel = _savgol_derivative(heading, dt, window=15, order=3, deriv=2)
    lat = ego.speed_mps * yaw_rate
    jerk = _savgol_derivative(np.hypot(lon, lat), dt, window=15, order=2, deriv=1)
    lon_jerk = _savgol_derivative(lon, dt, window=15, order=2, deriv=1)

    def peak(a: np.ndarray) -> float:
        return float(np.nanmax(np.abs(a))) if np.isfinite(a).any() else 0.0

    out = Comfort(
        min_lon_accel_mps2=float(np.nanmin(lon)),
        max_lon_accel_mps2=float(np.nanmax(lon)),
        max_abs_lat_accel_mps2=peak(lat),
        max_abs_jerk_mps3=peak(jerk),
        max_abs_lon_jerk_mps3=peak(lon_jerk),
        max_abs_yaw_rate_rps=peak(yaw_rate),
        max_abs_yaw_accel_rps2=peak(yaw_accel),
        comfortable=True,
    )
    ok = (
        out.min_lon_accel_mps2 >= MIN_LON_ACCEL_MPS2
        and out.max_lon_accel_mps2 <= MAX_LON_ACCEL_MPS2
        and out.max_abs_lat_accel_mps2 <= MAX_LAT_ACCEL_MPS2
        and out.max_abs_jerk_mps3 <= MAX_JERK_MPS3
        and out.max_abs_lon_jerk_mps3 <= MAX_LON_JERK_MPS3
        and out.max_abs_yaw_rate_rps <= MAX_YAW_RATE_RPS
        and out.max_abs_yaw_accel_rps2 <= MAX_YAW_ACCEL_RPS2
    )
    return Comfort(**{**out.__dict__, "comfortable": bool(ok)})


def run_score(
    *,
    fault_factor: float,
    drivable_ok: bool | None,
    direction_score: float,
    progress: float,
    min_ttc_s: float,
    comfortable: bool,
) -> float:
    """nuPlan's closed-loop score shape: (at-fault factor x drivable area x making
    progress x driving direction) x the weighted mean of progress ratio (5), TTC within
    bound (5) and comfort (2). Unknown drivable area (no lanes) counts as compliant."""
    making_progress = 1.0 if progress >= MIN_PROGRESS_RATIO else 0.0
    drivable = 0.0 if drivable_ok is False else 1.0
    multiplier = fault_factor * drivable * making_progress * direction_score
    ttc_ok = 1.0 if min_ttc_s >= LEAST_TTC_S else 0.0
    weighted = (
        WEIGHT_PROGRESS * progress + WEIGHT_TTC * ttc_ok + WEIGHT_COMFORT * float(comfortable)
    ) / (WEIGHT_PROGRESS + WEIGHT_TTC + WEIGHT_COMFORT)
    return multiplier * weighted
