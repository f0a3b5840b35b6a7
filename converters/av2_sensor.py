"""Argoverse 2 Sensor logs: cuboid annotations, the vehicle's poses and the map into a scene.

Read with polars (no ``av2`` package). A log folder holds (docs/recorded-data.md has the
tables):

- ``annotations.feather`` (or ``annotations_with_ego.feather``): one row per cuboid per
  lidar sweep (10 Hz): ``timestamp_ns``, ``track_uuid``, ``category``, ``length_m``,
  ``width_m``, the rotation ``qw, qx, qy, qz`` and the centre ``tx_m, ty_m, tz_m`` **in the
  vehicle's frame at that timestamp**;
- ``city_SE3_egovehicle.feather``: the vehicle's pose in the city frame (same columns),
  at a higher rate than the sweeps;
- ``map/log_map_archive_*.json``: the vector map, the layout of the motion-forecasting
  map (:func:`converters.av2.read_lane_map`).

Mapping:

- frames: the annotation timestamps; each cuboid goes to the city frame with the pose of
  **the same timestamp** (``p_city = R_pose p_vehicle + t_pose``, rotation
  ``R_pose R_cuboid``; heading = the yaw of that rotation). A timestamp without a pose is
  an error naming it (no interpolation);
- the ego is the autonomous vehicle itself, built from the poses at those timestamps
  (an ``EGO_VEHICLE`` track in ``annotations_with_ego.feather`` is that same vehicle and
  is replaced by it; its size is used when present, else :data:`EGO_SIZE`);
- speed: finite differences of each track's city positions over time (the annotations
  have no velocity); a track seen once has speed 0;
- kinds: :data:`CATEGORY_KINDS`; the static categories :data:`STATIC_CATEGORIES`
  (bollards, cones, barrels, signs) are **left out** (counted in the metadata
  ``static_tracks_left_out``): they never move and a planner already treats them as map
  obstacles; any other category is ``other``.
"""

from __future__ import annotations

import json
import os
import pathlib

import numpy as np
import polars as pl

from converters.av2 import read_lane_map
from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.lanegraph import PathSettings
from converters.tracks import Skipped, TrackTable, build_scene, integer_ids
from risk.frame import Kind, Scene

CONVERTER = "converters.av2_sensor"
CONVERTER_VERSION = "1"
POSES_FILE = "city_SE3_egovehicle.feather"
ANNOTATION_FILES = ("annotations.feather", "annotations_with_ego.feather")
EGO_CATEGORY = "EGO_VEHICLE"
EGO_TRACK = "EGO"
EGO_SIZE = (4.877, 2.0)
"""(length, width) m of the Argoverse 2 vehicle, as its ``EGO_VEHICLE`` cuboids give it."""

POSE_COLUMNS = ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
ANNOTATION_COLUMNS = (
    *POSE_COLUMNS[:1], "track_uuid", "category", "length_m", "width_m", *POSE_COLUMNS[1:]
)  # fmt: skip

_VEHICLES = (
    "REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "BOX_TRUCK", "TRUCK", "TRUCK_CAB",
    "VEHICULAR_TRAILER", "SCHOOL_BUS", "ARTICULATED_BUS", "MOTORCYCLE", "MOTORCYCLIST",
    "RAILED_VEHICLE",
)  # fmt: skip
_PEDESTRIANS = ("PEDESTRIAN", "WHEELED_RIDER", "WHEELCHAIR", "STROLLER", "OFFICIAL_SIGNALER")
CATEGORY_KINDS: dict[str, Kind] = {
    **{c: Kind.VEHICLE for c in _VEHICLES},
    **{c: Kind.PEDESTRIAN for c in _PEDESTRIANS},
    "BICYCLE": Kind.CYCLIST,
    "BICYCLIST": Kind.CYCLIST,
    "WHEELED_DEVICE": Kind.OTHER,  # a scooter or skateboard, ridden or parked
    "DOG": Kind.OTHER,
    "ANIMAL": Kind.OTHER,
}
"""Argoverse 2 Sensor ``category`` -> kind; an unlisted category is ``other``."""

STATIC_CATEGORIES = frozenset(
    {
        "BOLLARD", "CONSTRUCTION_CONE", "CONSTRUCTION_BARREL", "SIGN", "STOP_SIGN",
        "MOBILE_PEDESTRIAN_CROSSING_SIGN", "MESSAGE_BOARD_TRAILER", "TRAFFIC_LIGHT_TRAILER",
    }
)  # fmt: skip
"""Categories of things that do not move: left out of the scene."""


def is_log_dir(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an Argoverse 2 Sensor log folder (poses and annotations)."""
    path = pathlib.Path(path)
    return (path / POSES_FILE).is_file() and any((path / n).is_file() for n in ANNOTATION_FILES)


def find_logs(path: str | os.PathLike) -> list[pathlib.Path]:
    """The log folders named by ``path``: the folder itself, or its sub-folders that are
    logs (a split folder), sorted."""
    path = pathlib.Path(path)
    if not path.is_dir():
        raise ConversionError(f"{path}: not a folder; give an Argoverse 2 Sensor log folder")
    if is_log_dir(path):
        return [path]
    found = sorted(p for p in path.iterdir() if is_log_dir(p))
    if not found:
        raise ConversionError(
            f"{path}: no {POSES_FILE} with annotations.feather in it or its sub-folders"
        )
    return found


def quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` rotation matrices of unit quaternions ``(K, 4)`` in (w, x, y, z) order."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def to_city(
    pose_q: np.ndarray, pose_t: np.ndarray, box_q: np.ndarray, box_t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cuboids from the vehicle frame to the city frame: ``(K, 2)`` centres (m) and ``(K,)``
    headings (rad, the yaw of ``R_pose R_box``). Quaternions ``(K, 4)`` (w, x, y, z),
    translations ``(K, 3)``; row k of the pose belongs to row k of the box."""
    r_pose = quaternion_matrices(pose_q)
    r_city = r_pose @ quaternion_matrices(box_q)
    centre = np.einsum("kij,kj->ki", r_pose, box_t) + pose_t
    return centre[:, :2], np.arctan2(r_city[:, 1, 0], r_city[:, 0, 0])


def _read(path: pathlib.Path, columns: tuple[str, ...]) -> pl.DataFrame:
    try:
        df = pl.read_ipc(path)
    except (pl.exceptions.PolarsError, OSError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConversionError(f"{path}: not a readable Feather file ({first})") from None
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ConversionError(f"{path}: missing column(s) {', '.join(missing)}")
    if df.height == 0:
        raise ConversionError(f"{path}: no rows")
    return df


def annotations_file(log: pathlib.Path) -> pathlib.Path:
    for name in ANNOTATION_FILES:
        if (log / name).is_file():
            return log / name
    raise ConversionError(f"{log}: no {' or '.join(ANNOTATION_FILES)}")


def map_file(log: pathlib.Path) -> pathlib.Path | None:
    """The log's map JSON (``map/log_map_archive_*.json``, or beside the annotations)."""
    found = sorted(log.glob("map/log_map_archive_*.json")) or sorted(
        log.glob("log_map_archive_*.json")
    )
    return found[0] if found else None


def log_tracks(log: pathlib.Path) -> tuple[TrackTable, list[str], dict[str, int], int, float]:
    """The log's tracks in the city frame; also the track names, the renamed ids, the
    number of static tracks left out and the frame period (s). The ego is the last track."""
    ann_path = annotations_file(log)
    ann = _read(ann_path, ANNOTATION_COLUMNS)
    poses = _read(log / POSES_FILE, POSE_COLUMNS).unique("timestamp_ns", keep="first")
    stamps = np.unique(ann["timestamp_ns"].to_numpy())
    pose_stamps = poses["timestamp_ns"].to_numpy()
    missing = stamps[~np.isin(stamps, pose_stamps)]
    if missing.size:
        shown = ", ".join(str(int(t)) for t in missing[:5])
        more = f" and {missing.size - 5} more" if missing.size > 5 else ""
        raise ConversionError(
            f"{log}: {POSES_FILE} has no pose for {missing.size} annotation timestamp(s): "
            f"{shown}{more}; use the poses file of the same log"
        )
    ego_rows = ann.filter(pl.col("category") == EGO_CATEGORY)
    ego_size = (
        (float(ego_rows["length_m"][0]), float(ego_rows["width_m"][0]))
        if ego_rows.height
        else EGO_SIZE
    )
    static = ann.filter(pl.col("category").is_in(sorted(STATIC_CATEGORIES)))
    n_static = static["track_uuid"].n_unique()
    ann = ann.filter(
        ~pl.col("category").is_in(sorted(STATIC_CATEGORIES)) & (pl.col("category") != EGO_CATEGORY)
    )
    pose_at = poses.filter(pl.col("timestamp_ns").is_in(stamps)).sort("timestamp_ns")
    step_of = {int(t): k for k, t in enumerate(stamps)}
    names: list[str] = sorted(ann["track_uuid"].unique().to_list())
    n, n_steps = len(names) + 1, stamps.size
    col = {name: i for i, name in enumerate(names)}
    ann = ann.join(pose_at, on="timestamp_ns", suffix="_pose")
    step = np.array([step_of[int(t)] for t in ann["timestamp_ns"].to_list()], dtype=np.int64)
    agent = np.array([col[u] for u in ann["track_uuid"].to_list()], dtype=np.int64)
    if np.unique(step * n + agent).size != ann.height:
        raise ConversionError(f"{ann_path}: a track has two cuboids at one timestamp")
    xy_box, heading_box = to_city(
        ann.select("qw_pose", "qx_pose", "qy_pose", "qz_pose").to_numpy(),
        ann.select("tx_m_pose", "ty_m_pose", "tz_m_pose").to_numpy(),
        ann.select("qw", "qx", "qy", "qz").to_numpy(),
        ann.select("tx_m", "ty_m", "tz_m").to_numpy(),
    )
    ego_xy, ego_heading = to_city(
        pose_at.select("qw", "qx", "qy", "qz").to_numpy(),
        pose_at.select("tx_m", "ty_m", "tz_m").to_numpy(),
        np.tile([1.0, 0.0, 0.0, 0.0], (n_steps, 1)),
        np.zeros((n_steps, 3)),
    )
    shape = (n_steps, n)
    xy = np.full((*shape, 2), np.nan)
    heading = np.full(shape, np.nan)
    length = np.full(shape, np.nan)
    width = np.full(shape, np.nan)
    valid = np.zeros(shape, dtype=bool)
    xy[step, agent], heading[step, agent] = xy_box, heading_box
    length[step, agent] = ann["length_m"].to_numpy()
    width[step, agent] = ann["width_m"].to_numpy()
    valid[step, agent] = True
    xy[:, -1], heading[:, -1] = ego_xy, ego_heading
    length[:, -1], width[:, -1] = ego_size
    valid[:, -1] = True
    t_s = (stamps - stamps[0]) / 1e9
    categories = ann.group_by("track_uuid").agg(pl.col("category").first()).to_dict(as_series=False)
    cat_of = dict(zip(categories["track_uuid"], categories["category"], strict=True))
    kinds = np.array(
        [CATEGORY_KINDS.get(cat_of[u], Kind.OTHER) for u in names] + [Kind.VEHICLE], np.int8
    )
    ids, renamed = integer_ids([*names, EGO_TRACK])
    period = round(float(np.median(np.diff(t_s))), 3) if n_steps > 1 else 0.1
    table = TrackTable(
        ids=ids,
        kinds=kinds,
        t_s=t_s,
        xy=xy,
        heading=heading,
        speed=track_speeds(xy, valid, t_s),
        length=length,
        width=width,
        valid=valid,
        speed_measured=np.zeros_like(valid),  # derived: the clock check has no ratio here
    )
    return table, [*names, EGO_TRACK], renamed, n_static, period


def track_speeds(xy: np.ndarray, valid: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """``(T, N)`` speeds (m/s) from finite differences of each track's valid positions:
    the mean of the backward and forward difference where both exist (one of them at a
    track's ends or gaps), 0 for a lone state. Vectorised over tracks."""
    T, N = valid.shape
    step = np.arange(T)[:, None]
    cols = np.broadcast_to(np.arange(N), (T, N))
    prev = np.maximum.accumulate(np.where(valid, step, -1), axis=0)
    prev = np.concatenate([np.full((1, N), -1), prev[:-1]])
    nxt = np.minimum.accumulate(np.where(valid, step, T)[::-1], axis=0)[::-1]
    nxt = np.concatenate([nxt[1:], np.full((1, N), T)])
    has_p, has_n = valid & (prev >= 0), valid & (nxt < T)
    p, q = np.maximum(prev, 0), np.minimum(nxt, T - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        back = np.hypot(*(xy - xy[p, cols]).transpose(2, 0, 1)) / (t_s[:, None] - t_s[p])
        fwd = np.hypot(*(xy[q, cols] - xy).transpose(2, 0, 1)) / (t_s[q] - t_s[:, None])
    total = np.where(has_p, back, 0.0) + np.where(has_n, fwd, 0.0)
    count = has_p.astype(int) + has_n.astype(int)
    return np.where(valid, total / np.maximum(count, 1), np.nan)


def read_scene(
    log: str | os.PathLike,
    *,
    paths: str = "map",
    settings: PathSettings | None = None,
    skip_bad: bool = False,
    skipped: Skipped | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
) -> Scene:
    """One Argoverse 2 Sensor log folder as a scene, the autonomous vehicle as the ego.

    ``skip_bad`` and ``skipped`` are accepted for the registry's uniform call: a log is
    one record, so a bad log always fails."""
    del skip_bad, skipped
    log = pathlib.Path(log)
    settings = settings or PathSettings()
    table, names, renamed, n_static, period = log_tracks(log)
    map_json = map_file(log)
    metadata = {
        "dataset": "argoverse2_sensor",
        "source_file": f"{log.name}/{annotations_file(log).name}",
        "map_file": map_json.name if map_json else "",
        "scenario_id": log.name,
        "converter": CONVERTER,
        "converter_version": CONVERTER_VERSION,
        "ego_track": EGO_TRACK,
        "ego_choice": "the autonomous vehicle (its poses)",
        "static_tracks_left_out": str(n_static),
        "renamed_tracks": json.dumps(renamed, sort_keys=True),
    }
    return build_scene(
        table,
        len(names) - 1,
        read_lane_map(map_json),
        paths=paths,
        settings=settings,
        frame_period_s=period,
        metadata=metadata,
        source=str(log),
        progress=progress,
        time_step=time_step,
    )
