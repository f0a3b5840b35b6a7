"""INTERACTION dataset (and levelX-style) track CSVs with a Lanelet2 OSM map into a scene.

The CSV is read with polars, the OSM map with ``xml.etree.ElementTree`` (no ``lanelet2``
package). Mapping (docs/recorded-data.md has the tables):

- every ``track_id`` is an agent (numeric ids kept; others such as INTERACTION's
  pedestrian ids ``P1`` are numbered after the largest numeric id, see
  ``renamed_tracks`` in the metadata), valid at the frames where it has a row;
- time: ``frame_id`` is the step; the frame period is the median of
  ``diff(timestamp_ms) / diff(frame_id)`` over the frames, rounded to the millisecond;
- pose ``x``/``y`` (m), ``psi_rad`` (rad), speed ``|(vx, vy)|`` (m/s); files without
  ``psi_rad`` (INTERACTION's pedestrian files) get the direction of the velocity, held
  while the agent moves slower than :data:`MOVING_MPS` (and taken from its first moving
  state before that; 0 for an agent that never moves); without ``length``/``width``:
  :data:`DEFAULT_SIZES` per kind;
- kinds: car, truck, bus, van, motorcycle -> vehicle; bicycle -> cyclist; pedestrian and
  INTERACTION's mixed ``pedestrian/bicycle`` -> pedestrian; anything else -> other;
- ego: ``--ego ID``, default the track present in the most frames (ties: lowest id);
- map: each ``type=lanelet`` relation is a lane; its centre line is the mean of its
  left and right bounds, oriented like Lanelet2 does (both bounds made parallel, the
  ``left`` member on the left); a lanelet follows another when they share the end/start
  nodes of both bounds (Lanelet2's ``follows``); a lanelet tagged ``one_way=no`` is also
  added reversed, with id ``-id``; node positions from ``local_x``/``local_y`` tags when
  every node has them, else from ``lat``/``lon`` with INTERACTION's projection: UTM in the
  zone of the origin, minus the origin's UTM position (origin default 0, 0).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import xml.etree.ElementTree as ET

import numpy as np
import polars as pl

from converters.errors import ConversionError
from converters.finite import MAX_STEPS, check_grid
from converters.lanegraph import PathSettings, lanelet_centerline
from converters.tracks import Skipped, TrackTable, build_scene, integer_ids
from risk.frame import Kind, Lane, LaneMap, Scene

CONVERTER = "converters.interaction"
CONVERTER_VERSION = "1"

REQUIRED_COLUMNS = ("track_id", "frame_id", "timestamp_ms", "agent_type", "x", "y", "vx", "vy")
OPTIONAL_COLUMNS = ("psi_rad", "length", "width")

AGENT_KINDS: dict[str, Kind] = {
    "car": Kind.VEHICLE,
    "truck": Kind.VEHICLE,
    "bus": Kind.VEHICLE,
    "van": Kind.VEHICLE,
    "motorcycle": Kind.VEHICLE,
    "bicycle": Kind.CYCLIST,
    "pedestrian": Kind.PEDESTRIAN,
    "pedestrian/bicycle": Kind.PEDESTRIAN,  # INTERACTION does not tell them apart
}
DEFAULT_SIZES: dict[Kind, tuple[float, float]] = {
    Kind.VEHICLE: (4.5, 2.0),
    Kind.PEDESTRIAN: (0.5, 0.5),
    Kind.CYCLIST: (1.8, 0.6),
    Kind.OTHER: (1.0, 1.0),
}
"""(length, width) in metres for files without sizes (our choice of typical values)."""

MOVING_MPS = 0.2
"""Below this speed a heading derived from the velocity is noise: the last one is held."""

LANELET_KINDS: dict[str, str] = {
    "bicycle_lane": "bike",
    "bus_lane": "bus",
    "crosswalk": "crosswalk",
    "walkway": "walkway",
    "stairs": "walkway",
}
"""Lanelet2 ``subtype`` -> lane kind; any other subtype (road, highway, ...) is vehicle."""

# WGS84 ellipsoid and the UTM scale factor.
_A_M = 6_378_137.0
_F = 1 / 298.257223563
_K0 = 0.9996


# ---------------------------------------------------------------------- projection
def utm_xy(lat_deg: np.ndarray, lon_deg: np.ndarray, zone: int) -> tuple[np.ndarray, np.ndarray]:
    """Transverse Mercator (UTM ``zone``, northern form, no false easting/northing).

    Snyder (1987), "Map projections: a working manual", eqs. 8-9 to 8-10: a series in the
    longitude offset; sub-millimetre within a few degrees of the central meridian, which is
    all that differences to a nearby origin need.
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    lon0 = math.radians((zone - 1) * 6 - 180 + 3)
    e2 = _F * (2 - _F)
    ep2 = e2 / (1 - e2)
    sin, cos, tan = np.sin(lat), np.cos(lat), np.tan(lat)
    n = _A_M / np.sqrt(1 - e2 * sin**2)
    t = tan**2
    c = ep2 * cos**2
    a = (lon - lon0) * cos
    m = _A_M * (
        (1 - e2 / 4 - 3 * e2**2 / 64 - 5 * e2**3 / 256) * lat
        - (3 * e2 / 8 + 3 * e2**2 / 32 + 45 * e2**3 / 1024) * np.sin(2 * lat)
        + (15 * e2**2 / 256 + 45 * e2**3 / 1024) * np.sin(4 * lat)
        - (35 * e2**3 / 3072) * np.sin(6 * lat)
    )
    x = (
        _K0
        * n
        * (a + (1 - t + c) * a**3 / 6 + (5 - 18 * t + t**2 + 72 * c - 58 * ep2) * a**5 / 120)
    )
    y = _K0 * (
        m
        + n
        * tan
        * (
            a**2 / 2
            + (5 - t + 9 * c + 4 * c**2) * a**4 / 24
            + (61 - 58 * t + t**2 + 600 * c - 330 * ep2) * a**6 / 720
        )
    )
    return x, y


def project(lat: np.ndarray, lon: np.ndarray, origin: tuple[float, float]) -> np.ndarray:
    """Local metric ``(K, 2)`` positions: UTM in the origin's zone minus the origin's UTM."""
    zone = math.floor((origin[1] + 180.0) / 6.0) + 1
    x, y = utm_xy(lat, lon, zone)
    x0, y0 = utm_xy(np.array([origin[0]]), np.array([origin[1]]), zone)
    return np.stack([x - x0[0], y - y0[0]], axis=1)


# ---------------------------------------------------------------------- map
def read_lane_map(path: str | os.PathLike, origin: tuple[float, float] = (0.0, 0.0)) -> LaneMap:
    """The lanelets of a Lanelet2 OSM file as lanes (see the module docstring)."""
    path = pathlib.Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ConversionError(f"{path}: not well-formed XML ({exc})") from None
    if root.tag != "osm":
        raise ConversionError(f"{path}: not an OSM map (root element <{root.tag}>, expected <osm>)")
    nodes = _node_positions(root, origin, path)
    ways = {
        int(w.get("id", "0")): [int(nd.get("ref", "0")) for nd in w.findall("nd")]
        for w in root.findall("way")
    }
    directed: list[tuple[int, list[int], list[int], str]] = []
    for rel in root.findall("relation"):
        tags = {t.get("k"): t.get("v") for t in rel.findall("tag")}
        if tags.get("type") != "lanelet":
            continue
        lid = int(rel.get("id", "0"))
        roles = {m.get("role"): int(m.get("ref", "0")) for m in rel.findall("member")}
        if "left" not in roles or "right" not in roles:
            raise ConversionError(f"{path}: lanelet {lid} lacks a left or right bound")
        try:
            left, right = ways[roles["left"]], ways[roles["right"]]
            left, right = _align(left, right, nodes)
        except KeyError as exc:
            raise ConversionError(
                f"{path}: lanelet {lid} refers to missing way/node {exc}"
            ) from None
        kind = LANELET_KINDS.get(tags.get("subtype", "road"), "vehicle")
        directed.append((lid, left, right, kind))
        if tags.get("one_way", "yes") == "no":
            directed.append((-lid, right[::-1], left[::-1], kind))
    return LaneMap(tuple(_lanes(directed, nodes)))


def _node_positions(root: ET.Element, origin: tuple[float, float], path: pathlib.Path):
    elems = root.findall("node")
    ids = [int(n.get("id", "0")) for n in elems]
    local = [{t.get("k"): t.get("v") for t in n.findall("tag")} for n in elems]
    try:
        if elems and all("local_x" in t and "local_y" in t for t in local):
            xy = np.array([(float(t["local_x"]), float(t["local_y"])) for t in local])
        else:
            lat = np.array([float(n.get("lat", "nan")) for n in elems])
            lon = np.array([float(n.get("lon", "nan")) for n in elems])
            xy = project(lat, lon, origin) if elems else np.zeros((0, 2))
    except ValueError as exc:
        raise ConversionError(f"{path}: a node has no numeric position ({exc})") from None
    if not np.isfinite(xy).all():
        raise ConversionError(f"{path}: a node has no lat/lon (and no local_x/local_y)")
    return dict(zip(ids, xy, strict=True))


def _align(left: list[int], right: list[int], nodes: dict) -> tuple[list[int], list[int]]:
    """Orient the bounds like Lanelet2: parallel, with ``left`` on the left of the motion."""
    L = np.array([nodes[i] for i in left])
    R = np.array([nodes[i] for i in right])
    same = np.hypot(*(L[0] - R[0])) + np.hypot(*(L[-1] - R[-1]))
    crossed = np.hypot(*(L[0] - R[-1])) + np.hypot(*(L[-1] - R[0]))
    if crossed < same:
        left, L = left[::-1], L[::-1]
    direction = (L[-1] + R[-1]) - (L[0] + R[0])
    offset = L.mean(axis=0) - R.mean(axis=0)
    if direction[0] * offset[1] - direction[1] * offset[0] < 0:  # left bound on the right
        left, right = right[::-1], left[::-1]
    return left, right


def _lanes(directed, nodes) -> list[Lane]:
    start = {}
    for lid, left, right, _ in directed:
        start.setdefault((left[0], right[0]), []).append(lid)
    lanes = []
    for lid, left, right, kind in directed:
        L = np.array([nodes[i] for i in left])
        R = np.array([nodes[i] for i in right])
        centre = lanelet_centerline(L, R)
        successors = tuple(s for s in start.get((left[-1], right[-1]), ()) if s != -lid)
        lanes.append(Lane(id=lid, centerline=centre, successors=successors, kind=kind))
    return lanes


# ---------------------------------------------------------------------- tracks
def read_rows(
    path: str | os.PathLike, *, skip_bad: bool = False, skipped: Skipped | None = None
) -> pl.DataFrame:
    """The CSV rows with numeric columns parsed; a row whose required values do not parse
    raises ConversionError naming its line (or is skipped with ``skip_bad``)."""
    path = pathlib.Path(path)
    try:
        df = pl.read_csv(path, infer_schema=False)  # all strings: parse per column below
    except (pl.exceptions.PolarsError, UnicodeDecodeError) as exc:
        raise ConversionError(f"{path}: not a readable CSV file ({exc})") from None
    df = df.rename({c: c.strip() for c in df.columns})
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise ConversionError(f"{path}: missing column(s) {', '.join(missing)}")
    numeric = [c for c in (*REQUIRED_COLUMNS[1:], *OPTIONAL_COLUMNS) if c in df.columns]
    numeric.remove("agent_type")
    parsed = df.with_columns(
        [pl.col(c).str.strip_chars().cast(pl.Float64, strict=False) for c in numeric]
        + [pl.col("track_id").str.strip_chars(), pl.col("agent_type").str.strip_chars()]
    ).with_row_index("line", offset=2)  # line 1 is the header
    required = [c for c in REQUIRED_COLUMNS if c in numeric]
    bad = parsed.filter(
        # Unparseable values are bad rows; NaN/inf in a state's values (x, y, vx, ...)
        # follow converters.finite's rule later, but the time columns must be finite.
        pl.any_horizontal([pl.col(c).is_null() for c in required])
        | ~pl.col("frame_id").is_finite()
        | ~pl.col("timestamp_ms").is_finite()
        | pl.col("track_id").is_null()
        | (pl.col("track_id") == "")
    )
    if bad.height:
        lines = bad["line"].to_list()
        message = f"{path}: line {lines[0]}: a required value is missing or not a number"
        if not skip_bad:
            raise ConversionError(message)
        if skipped is not None:
            for line in lines:
                skipped.add(f"{path}: line {line}: a required value is missing or not a number")
        parsed = parsed.filter(~pl.col("line").is_in(lines))
    if parsed.height == 0:
        raise ConversionError(f"{path}: no usable rows")
    return parsed


def rows_to_table(df: pl.DataFrame, where: str) -> tuple[TrackTable, list[str], dict, float]:
    """Rows as a :class:`TrackTable`; also the track names, the renamed ids and the period."""
    df = df.sort("track_id", "frame_id")
    raw = df["frame_id"].to_numpy()
    if not (np.abs(raw) <= MAX_STEPS).all():
        raise ConversionError(f"{where}: a frame_id is beyond {MAX_STEPS}; the file is corrupt")
    frame = raw.astype(np.int64)
    first = int(frame.min())
    step = frame - first
    names: list[str] = df["track_id"].unique(maintain_order=True).to_list()
    ids, renamed = integer_ids(names)
    col = {n: i for i, n in enumerate(names)}
    agent = np.array([col[t] for t in df["track_id"].to_list()], dtype=np.int64)
    n_steps, n = int(step.max()) + 1, len(names)
    check_grid(n_steps, n, source=where, what="frames")  # before allocating
    if np.unique(step * n + agent).size != df.height:
        raise ConversionError(f"{where}: a track has two rows for the same frame_id")
    period, t0 = _period(frame, df["timestamp_ms"].to_numpy(), where)
    types = df.group_by("track_id", maintain_order=True).agg(pl.col("agent_type").first())
    type_of = dict(zip(types["track_id"].to_list(), types["agent_type"].to_list(), strict=True))
    kinds = np.array(
        [AGENT_KINDS.get((type_of[t] or "").lower(), Kind.OTHER) for t in names], np.int8
    )
    vx, vy = df["vx"].to_numpy(), df["vy"].to_numpy()
    speed = np.hypot(vx, vy)
    if "psi_rad" in df.columns:
        heading = df["psi_rad"].to_numpy()
        heading = np.where(np.isnan(heading), _velocity_heading(agent, vx, vy, speed), heading)
    else:
        heading = _velocity_heading(agent, vx, vy, speed)
    defaults = np.array([DEFAULT_SIZES[Kind(k)] for k in kinds])[agent]
    length = _column_or(df, "length", defaults[:, 0])
    width = _column_or(df, "width", defaults[:, 1])
    shape = (n_steps, n)
    grid = {name: np.full(shape, np.nan) for name in ("heading", "speed", "length", "width")}
    xy = np.full((*shape, 2), np.nan)
    valid = np.zeros(shape, dtype=bool)
    xy[step, agent] = df.select("x", "y").to_numpy()
    for name, values in (
        ("heading", heading),
        ("speed", speed),
        ("length", length),
        ("width", width),
    ):
        grid[name][step, agent] = values
    valid[step, agent] = True
    table = TrackTable(
        ids=ids,
        kinds=kinds,
        t_s=t0 + np.arange(n_steps) * period,
        xy=xy,
        valid=valid,
        **grid,
    )
    return table, names, renamed, period


def _column_or(df: pl.DataFrame, name: str, default: np.ndarray) -> np.ndarray:
    if name not in df.columns:
        return default
    values = df[name].to_numpy()
    return np.where(np.isnan(values), default, values)


def _period(frame: np.ndarray, stamp_ms: np.ndarray, where: str) -> tuple[float, float]:
    """Frame period (s, rounded to the millisecond) and the time of step 0 (s)."""
    frames, first_row = np.unique(frame, return_index=True)
    stamps = stamp_ms[first_row] / 1000.0
    if frames.size < 2:
        return 0.1, float(stamps[0])
    ratio = np.diff(stamps) / np.diff(frames)
    if not np.all(ratio > 0):
        raise ConversionError(f"{where}: timestamp_ms does not increase with frame_id")
    period = round(float(np.median(ratio)), 3) or float(np.median(ratio))
    return period, float(stamps[0])


def _velocity_heading(
    agent: np.ndarray, vx: np.ndarray, vy: np.ndarray, speed: np.ndarray
) -> np.ndarray:
    """Direction of the velocity per row (rows sorted by agent, then time), held over rows
    slower than MOVING_MPS: forward-filled within each agent, back-filled before its first
    moving row; 0 for an agent that never moves. Vectorised over all rows."""
    n = len(agent)
    pos = np.arange(n)
    new_group = np.concatenate(([True], agent[1:] != agent[:-1]))
    group_start = np.maximum.accumulate(np.where(new_group, pos, 0))
    group_end = np.minimum.accumulate(
        np.where(np.concatenate((agent[1:] != agent[:-1], [True])), pos, n)[::-1]
    )[::-1]
    moving = speed >= MOVING_MPS
    forward = np.maximum.accumulate(np.where(moving, pos, -1))
    backward = np.minimum.accumulate(np.where(moving, pos, n)[::-1])[::-1]
    source = np.where(
        forward >= group_start, forward, np.where(backward <= group_end, backward, -1)
    )
    direction = np.arctan2(vy, vx)
    return np.where(source >= 0, direction[np.maximum(source, 0)], 0.0)


def default_ego(table: TrackTable) -> int:
    """Index of the track present in the most frames (ties: the lowest id)."""
    counts = table.valid.sum(axis=0)
    order = np.lexsort((table.ids, -counts))
    return int(order[0])


def read_scene(
    tracks_csv: str | os.PathLike,
    map_osm: str | os.PathLike,
    *,
    ego: int | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    paths: str = "map",
    settings: PathSettings | None = None,
    skip_bad: bool = False,
    skipped: Skipped | None = None,
    progress: bool = False,
) -> Scene:
    """A track CSV and its Lanelet2 map as a scene; ``ego`` is a track id (default: the
    track present in the most frames)."""
    tracks_csv = pathlib.Path(tracks_csv)
    settings = settings or PathSettings()
    lane_map = read_lane_map(map_osm, origin)
    df = read_rows(tracks_csv, skip_bad=skip_bad, skipped=skipped)
    table, names, renamed, period = rows_to_table(df, str(tracks_csv))
    if ego is None:
        ego_index, choice = default_ego(table), "most frames"
    else:
        hits = np.flatnonzero(table.ids == ego)
        if hits.size == 0:
            listed = ", ".join(str(i) for i in sorted(table.ids.tolist())[:10])
            more = " ..." if table.n_tracks > 10 else ""
            raise ConversionError(f"{tracks_csv}: no track with id {ego} (ids: {listed}{more})")
        ego_index, choice = int(hits[0]), "--ego"
    metadata = {
        "dataset": "interaction",
        "source_file": tracks_csv.name,
        "map_file": pathlib.Path(map_osm).name,
        "scenario_id": tracks_csv.stem,
        "converter": CONVERTER,
        "converter_version": CONVERTER_VERSION,
        "ego_track": names[ego_index],
        "ego_choice": choice,
        "renamed_tracks": json.dumps(renamed, sort_keys=True),
        "map_origin_lat_lon": f"{origin[0]:g},{origin[1]:g}",
    }
    return build_scene(
        table,
        ego_index,
        lane_map,
        paths=paths,
        settings=settings,
        frame_period_s=period,
        metadata=metadata,
        source=str(tracks_csv),
        progress=progress,
        skip_bad=skip_bad,
        skipped=skipped,
    )
