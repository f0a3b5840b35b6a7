"""INTERACTION dataset (and levelX-style) track CSVs with a Lanelet2 OSM map into a scene.

The CSV is read with polars, the OSM map with the ``lanelet2`` package (its self-contained
PyPI wheel: the projector, the bounds and ``follows``, measured against the hand-written
parser it replaced in docs/recorded-data.md). Mapping (docs/recorded-data.md has the tables):

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
- several track CSVs of one recording (INTERACTION's ``vehicle_tracks_000.csv`` and
  ``pedestrian_tracks_000.csv``) form one scene: their rows share the recording's
  ``frame_id``/``timestamp_ms`` clock; a track id in two files is an error;
- ego: ``--ego ID``, default the moving-ego rule of :func:`converters.tracks.moving_ego`
  (the vehicle that travels farthest);
- map: each lanelet is a lane whose centre line is the mean of its left and right
  bounds (see :func:`read_lane_map`).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import re
from collections.abc import Sequence
from typing import Any

import lanelet2
import numpy as np
import polars as pl
from lanelet2.projection import UtmProjector

from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.input_checks import MAX_STEPS, check_gaps, check_grid
from converters.lanegraph import PathSettings, lanelet_centerline
from converters.tracks import Skipped, TrackTable, build_scene, integer_ids, moving_ego
from risk.frame import Kind, Lane, LaneMap, Scene

CONVERTER = "converters.interaction"
CONVERTER_VERSION = "2"

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

_LANELET_ERROR = re.compile(r"primitive (?:with id )?(-?\d+)")


# ---------------------------------------------------------------------- map
def read_lane_map(path: str | os.PathLike, origin: tuple[float, float] = (0.0, 0.0)) -> LaneMap:
    """The lanelets of a Lanelet2 OSM file as lanes, read with the ``lanelet2`` package.

    Node positions: ``local_x``/``local_y`` tags when every node has them, else
    ``lat``/``lon`` projected by Lanelet2's ``UtmProjector`` at ``origin`` (UTM in the
    origin's zone minus the origin's UTM position, as the INTERACTION tools do). Bounds as
    the file gives them (Lanelet2 orients each way along the lanelet; the ``left`` member is
    the left bound). Successors: Lanelet2's ``follows`` (A's bounds end at the points
    where B's start). ``one_way=no`` adds the inverted lanelet as lane ``-id``. Errors
    Lanelet2 reports about other primitives (areas, regulatory elements) are ignored; one
    about a lanelet is an error.
    """
    path = pathlib.Path(path)
    with open(path, "rb") as fh:
        head = fh.read(4096).decode("utf-8", "replace")
    found = re.search(r"<([A-Za-z_][\w.-]*)[\s/>]", re.sub(r"<\?.*?\?>|<!--.*?-->", "", head))
    root = found.group(1) if found else "?"
    if root != "osm":
        raise ConversionError(f"{path}: not an OSM map (root element <{root}>, expected <osm>)")
    _check_node_coordinates(path)
    projector = UtmProjector(lanelet2.io.Origin(*origin))
    try:
        lmap, errors = lanelet2.io.loadRobust(str(path), projector)
    except RuntimeError as exc:
        raise ConversionError(f"{path}: Lanelet2 cannot read it ({exc})") from None
    lanelet_ids = {ll.id for ll in lmap.laneletLayer}
    for message in errors:
        hit = _LANELET_ERROR.search(message)
        if hit and int(hit.group(1)) in lanelet_ids:
            what = message.strip(" -\t")
            raise ConversionError(f"{path}: lanelet {hit.group(1)}: {what}")
    local = _local_positions(lmap)
    directed = []
    for ll in lmap.laneletLayer:
        attrs = dict(ll.attributes)  # a Lanelet2 AttributeMap has no .get
        subtype = attrs.get("subtype", "road")
        kind = LANELET_KINDS.get(subtype, "vehicle")
        directed.append((ll.id, ll, kind))
        if attrs.get("one_way") == "no":
            directed.append((-ll.id, ll.invert(), kind))
    return LaneMap(tuple(_lanes(directed, local)))


_NODE = re.compile(rb"<node\b[^>]*>")
_COORDINATE = re.compile(rb'\b(lat|lon)\s*=\s*["\']([^"\']*)["\']')
_RANGES = {b"lat": 90.0, b"lon": 180.0}


def _check_node_coordinates(path: pathlib.Path) -> None:
    """Every node's ``lat``/``lon`` is a number in range (Lanelet2 reads ``lat='north'``
    as 0 and projects 1e300 to infinity, and the map then converted without a word)."""
    with open(path, "rb") as fh:
        data = fh.read()
    for node in _NODE.finditer(data):
        for name, text in _COORDINATE.findall(node.group(0)):
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and abs(value) <= _RANGES[name]):
                shown = node.group(0)[:80].decode("utf-8", "replace")
                raise ConversionError(
                    f"{path}: {shown}: {name.decode()}={text.decode('utf-8', 'replace')!r} is"
                    f" not a {'latitude' if name == b'lat' else 'longitude'} in degrees"
                )


def _local_positions(lmap: Any) -> dict[int, tuple[float, float]] | None:
    """Point id -> (local_x, local_y) when every point carries those tags, else None."""
    out = {}
    for p in lmap.pointLayer:
        a = p.attributes
        if "local_x" not in a or "local_y" not in a:
            return None
        try:
            out[p.id] = (float(a["local_x"]), float(a["local_y"]))
        except ValueError:
            return None
    return out


def _xy(bound: Any, local: dict[int, tuple[float, float]] | None) -> np.ndarray:
    if local is not None:
        return np.array([local[p.id] for p in bound], dtype=np.float64).reshape(-1, 2)
    return np.array([(p.x, p.y) for p in bound], dtype=np.float64).reshape(-1, 2)


def _lanes(directed: list, local: dict | None) -> list[Lane]:
    start: dict[tuple[int, int], list[int]] = {}
    for lid, ll, _ in directed:
        if len(ll.leftBound) and len(ll.rightBound):
            start.setdefault((ll.leftBound[0].id, ll.rightBound[0].id), []).append(lid)
    lanes = []
    for lid, ll, kind in directed:
        if len(ll.leftBound) < 2 or len(ll.rightBound) < 2:
            continue
        centre = lanelet_centerline(_xy(ll.leftBound, local), _xy(ll.rightBound, local))
        end = (ll.leftBound[len(ll.leftBound) - 1].id, ll.rightBound[len(ll.rightBound) - 1].id)
        successors = tuple(s for s in start.get(end, ()) if s != -lid)
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
        # follow converters.input_checks's rule later, but the time columns must be finite.
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
    broken = parsed.filter(
        pl.any_horizontal([pl.col(c).str.contains(r"[\r\n]") for c in ("track_id", "agent_type")])
    )
    if broken.height:  # a quoted field across lines: the file is damaged or foreign
        raise ConversionError(
            f"{path}: line {broken['line'][0]}: a quoted field holds a line break; track"
            " files have one record per line (the file is damaged)"
        )
    return parsed


def rows_to_table(df: pl.DataFrame, where: str) -> tuple[TrackTable, list[str], dict, float]:
    """Rows as a :class:`TrackTable`; also the track names, the renamed ids and the period."""
    df = df.sort("track_id", "frame_id")
    raw = df["frame_id"].to_numpy()
    if not (np.abs(raw) <= MAX_STEPS).all():
        raise ConversionError(f"{where}: a frame_id is beyond {MAX_STEPS}; the file is corrupt")
    whole = raw == np.floor(raw)
    if not whole.all():
        at = int(np.argmin(whole))
        line = f"line {df['line'][at]}: " if "line" in df.columns else ""
        raise ConversionError(
            f"{where}: {line}frame_id {raw[at]:g} is not a whole number; frame ids count frames"
        )
    check_gaps(raw, source=where)
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


def read_track_files(
    tracks_csv: Sequence[pathlib.Path], *, skip_bad: bool = False, skipped: Skipped | None = None
) -> pl.DataFrame:
    """The rows of one recording's track CSVs together (columns a file lacks are null);
    ConversionError when a track id appears in two files."""
    frames = []
    owner: dict[str, pathlib.Path] = {}
    for path in tracks_csv:
        df = read_rows(path, skip_bad=skip_bad, skipped=skipped)
        for track in df["track_id"].unique(maintain_order=True).to_list():
            if track in owner:
                raise ConversionError(
                    f"{path}: track {track} is also in {owner[track]}; give the track files "
                    "of one recording (e.g. vehicle_tracks_000.csv pedestrian_tracks_000.csv)"
                )
            owner[track] = path
        frames.append(df.drop("line"))
    return pl.concat(frames, how="diagonal_relaxed")


def read_scene(
    tracks_csv: str | os.PathLike | Sequence[str | os.PathLike],
    map_osm: str | os.PathLike,
    *,
    ego: int | None = None,
    origin: tuple[float, float] = (0.0, 0.0),
    paths: str = "map",
    settings: PathSettings | None = None,
    skip_bad: bool = False,
    skipped: Skipped | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
) -> Scene:
    """One recording's track CSV(s) and its Lanelet2 map as a scene; ``ego`` is a track id
    (default: :func:`converters.tracks.moving_ego`)."""
    files = (
        [pathlib.Path(tracks_csv)]
        if isinstance(tracks_csv, str | os.PathLike)
        else [pathlib.Path(p) for p in tracks_csv]
    )
    if not files:
        raise ConversionError("no track CSV given")
    tracks_csv = files[0]
    where = ", ".join(str(p) for p in files)
    settings = settings or PathSettings()
    lane_map = read_lane_map(map_osm, origin)
    df = read_track_files(files, skip_bad=skip_bad, skipped=skipped)
    table, names, renamed, period = rows_to_table(df, where)
    if ego is None:
        ego_index, choice = moving_ego(table)
    else:
        hits = np.flatnonzero(table.ids == ego)
        if hits.size == 0:
            listed = ", ".join(str(i) for i in sorted(table.ids.tolist())[:10])
            more = " ..." if table.n_tracks > 10 else ""
            raise ConversionError(f"{where}: no track with id {ego} (ids: {listed}{more})")
        ego_index, choice = int(hits[0]), "--ego"
    metadata = {
        "dataset": "interaction",
        "source_file": ",".join(p.name for p in files),
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
        source=where,
        progress=progress,
        time_step=time_step,
        skip_bad=skip_bad,
        skipped=skipped,
    )
