"""Argoverse 2 motion forecasting: a scenario parquet and its map JSON into a scene.

Read with polars (no ``av2`` package). Mapping (docs/recorded-data.md has the tables):

- one scene per scenario parquet (one row per track and time step); every track is an
  agent, valid at the time steps where it has a row (``observed`` is *not* validity: in
  Argoverse 2 it only marks the first 5 s, the history given to forecasting models);
- ids: numeric ``track_id`` values are kept; the others (the ego ``AV``) are numbered
  after the largest numeric id (recorded in the metadata as ``renamed_tracks``);
- ego: the ``AV`` track; time: ``timestep`` times the period
  ``(end_timestamp - start_timestamp) / (num_timestamps - 1)`` (ns);
- pose ``position_x/y`` (m), ``heading`` (rad), speed ``|(velocity_x, velocity_y)|`` (m/s);
- sizes: Argoverse 2 has none, so :data:`DEFAULT_SIZES` per ``object_type``;
- map ``log_map_archive_*.json``: every lane segment (``centerline``, or the mean of
  its two boundaries when a log map leaves it out, ``successors``,
  ``lane_type`` VEHICLE/BIKE/BUS -> kind vehicle/bike/bus);
- labels: ``focal`` = tracks with ``object_category`` 3 (it equals ``focal_track_id``),
  ``scored`` = ``object_category`` 2 (0 is a track fragment, 1 an unscored track).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import polars as pl

from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.input_checks import check_grid
from converters.lanegraph import PathSettings, lanelet_centerline
from converters.map_lines import av2_lines
from converters.tracks import Skipped, TrackTable, build_scene, integer_ids
from risk.frame import Kind, Lane, LaneMap, Scene

CONVERTER = "converters.av2"
CONVERTER_VERSION = "1"
EGO_TRACK = "AV"
FOCAL_CATEGORY = 3
SCORED_CATEGORY = 2

OBJECT_KINDS: dict[str, Kind] = {
    "vehicle": Kind.VEHICLE,
    "bus": Kind.VEHICLE,
    "motorcyclist": Kind.VEHICLE,  # moves and uses lanes like a vehicle
    "pedestrian": Kind.PEDESTRIAN,
    "cyclist": Kind.CYCLIST,
    "riderless_bicycle": Kind.OTHER,
    "static": Kind.OTHER,
    "background": Kind.OTHER,
    "construction": Kind.OTHER,
    "unknown": Kind.OTHER,
}
"""``object_type`` -> kind; any other type is ``other``."""

DEFAULT_SIZES: dict[str, tuple[float, float]] = {
    "vehicle": (4.5, 2.0),  # a mid-size passenger car
    "bus": (12.0, 2.5),
    "motorcyclist": (2.2, 0.8),
    "pedestrian": (0.5, 0.5),
    "cyclist": (1.8, 0.6),
    "riderless_bicycle": (1.8, 0.6),
    "static": (1.0, 1.0),
    "background": (1.0, 1.0),
    "construction": (1.0, 1.0),
    "unknown": (1.0, 1.0),
}
"""``object_type`` -> (length, width) in metres; Argoverse 2 gives no sizes. Our choice
of typical values; an unlisted type gets ``unknown``'s."""

LANE_KINDS = {"VEHICLE": "vehicle", "BIKE": "bike", "BUS": "bus"}

REQUIRED_COLUMNS = (
    "track_id", "object_type", "object_category", "timestep", "position_x", "position_y",
    "heading", "velocity_x", "velocity_y", "scenario_id",
)  # fmt: skip


def find_scenarios(path: str | os.PathLike) -> list[pathlib.Path]:
    """The scenario parquet files named by ``path``: the file itself, the
    ``scenario_*.parquet`` files of a scenario folder, or those of its sub-folders (an
    Argoverse 2 split folder), sorted."""
    path = pathlib.Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise FileNotFoundError(2, "no such file or folder", str(path))
    found = sorted(path.glob("scenario_*.parquet")) or sorted(path.glob("*/scenario_*.parquet"))
    if not found:
        raise ConversionError(f"{path}: no scenario_*.parquet file in it or its sub-folders")
    return found


def map_path_for(parquet: pathlib.Path, scenario_id: str) -> pathlib.Path | None:
    """The map JSON beside a scenario parquet: ``log_map_archive_<id>.json``, else the only
    ``log_map_archive_*.json`` there; None when there is none."""
    exact = parquet.with_name(f"log_map_archive_{scenario_id}.json")
    if exact.is_file():
        return exact
    others = sorted(parquet.parent.glob("log_map_archive_*.json"))
    return others[0] if len(others) == 1 else None


def read_table(parquet: pathlib.Path) -> pl.DataFrame:
    """The scenario rows; raises ConversionError for an unreadable or incomplete file."""
    try:
        df = pl.read_parquet(parquet)
    except pl.exceptions.PolarsError as exc:  # ComputeError for truncated or damaged files
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConversionError(f"{parquet}: not a readable parquet file ({first_line})") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in df.columns]
    if missing:
        raise ConversionError(f"{parquet}: missing column(s) {', '.join(missing)}")
    if df.height == 0:
        raise ConversionError(f"{parquet}: no rows")
    _check_types(df, parquet)
    return df


#: Columns that must hold numbers (integers for the first group): a position of 'abc',
#: a text timestamp or a timestep stored as text are a damaged or foreign file.
_INTEGER_COLUMNS = ("timestep", "num_timestamps")
_NUMBER_COLUMNS = (
    "position_x", "position_y", "heading", "velocity_x", "velocity_y", "start_timestamp",
    "end_timestamp",
)  # fmt: skip


def _check_types(df: pl.DataFrame, parquet: pathlib.Path) -> None:
    def wrong(column: str, what: str) -> ConversionError:
        return ConversionError(
            f"{parquet}: column {column} holds {df.schema[column]} values, not {what}; not an"
            " Argoverse 2 scenario file (or a damaged one)"
        )

    for column in _INTEGER_COLUMNS:
        if column in df.columns and not df.schema[column].is_integer():
            raise wrong(column, "integers")
    for column in _NUMBER_COLUMNS:
        if column in df.columns and not df.schema[column].is_numeric():
            raise wrong(column, "numbers")
    nulls = df.select(pl.col("track_id", "timestep").null_count()).row(0)
    for column, count in zip(("track_id", "timestep"), nulls, strict=True):
        if count:
            raise ConversionError(
                f"{parquet}: column {column} is empty (null) in {count} row(s); every row needs one"
            )


def scenario_tracks(df: pl.DataFrame, where: str) -> tuple[TrackTable, list[str], dict]:
    """The rows as a :class:`TrackTable`; also the track names (in table order) and the
    ids given to non-numeric names."""
    df = df.with_columns(pl.col("track_id").cast(pl.String))
    names: list[str] = df["track_id"].unique(maintain_order=True).to_list()
    ids, renamed = integer_ids(names)
    col = {name: i for i, name in enumerate(names)}
    step = df["timestep"].to_numpy().astype(np.int64)
    if step.min() < 0:
        raise ConversionError(f"{where}: negative timestep")
    n_steps = int(step.max()) + 1
    if "num_timestamps" in df.columns:
        n_steps = max(n_steps, int(df["num_timestamps"].to_numpy().max()))
    check_grid(n_steps, len(names), source=where, what="timesteps")  # before allocating
    agent = np.array([col[t] for t in df["track_id"].to_list()], dtype=np.int64)
    if np.unique(step * len(names) + agent).size != df.height:
        raise ConversionError(f"{where}: a track has two rows for the same timestep")
    types = (
        df.group_by("track_id", maintain_order=True)
        .agg(pl.col("object_type").first())
        .to_dict(as_series=False)
    )
    type_of = dict(zip(types["track_id"], types["object_type"], strict=True))
    kinds = np.array([OBJECT_KINDS.get(type_of[n], Kind.OTHER) for n in names], dtype=np.int8)
    sizes = np.array([DEFAULT_SIZES.get(type_of[n], DEFAULT_SIZES["unknown"]) for n in names])
    shape = (n_steps, len(names))
    xy = np.full((*shape, 2), np.nan)
    heading = np.full(shape, np.nan)
    speed = np.full(shape, np.nan)
    valid = np.zeros(shape, dtype=bool)
    xy[step, agent] = df.select("position_x", "position_y").to_numpy()
    heading[step, agent] = df["heading"].to_numpy()
    speed[step, agent] = np.hypot(df["velocity_x"].to_numpy(), df["velocity_y"].to_numpy())
    valid[step, agent] = True
    table = TrackTable(
        ids=ids,
        kinds=kinds,
        t_s=np.arange(n_steps, dtype=np.float64),  # scaled by the period by the caller
        xy=xy,
        heading=heading,
        speed=speed,
        length=np.broadcast_to(sizes[:, 0], shape),
        width=np.broadcast_to(sizes[:, 1], shape),
        valid=valid,
    )
    return table, names, renamed


def frame_period_s(df: pl.DataFrame) -> float:
    """Time step from the scenario's start/end timestamps (ns), rounded to the millisecond;
    0.1 s (Argoverse 2's 10 Hz) when those columns are absent."""
    needed = ("start_timestamp", "end_timestamp", "num_timestamps")
    if not all(c in df.columns for c in needed):
        return 0.1
    row = df.select(needed).row(0)
    start, end, n = float(row[0]), float(row[1]), int(row[2])
    if n < 2 or not end > start:
        return 0.1
    return round((end - start) / 1e9 / (n - 1), 3)


def read_lane_map(path: pathlib.Path | None) -> LaneMap:
    """Lane segments of an Argoverse 2 map JSON (an empty map when ``path`` is None)."""
    if path is None:
        return LaneMap()
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        segments = data["lane_segments"]
        lanes = []
        for key, seg in segments.items():
            line = _centerline(seg)
            if len(line) < 2:
                continue
            lanes.append(
                Lane(
                    id=int(seg.get("id", key)),
                    centerline=line,
                    successors=tuple(int(s) for s in seg.get("successors") or ()),
                    kind=LANE_KINDS.get(str(seg.get("lane_type", "VEHICLE")).upper(), "vehicle"),
                )
            )
        lines = av2_lines(data)
    except RecursionError:  # (json and the walk below recurse once per level)
        raise ConversionError(
            f"{path}: not an Argoverse 2 map (nested deeper than Python can parse; a map"
            " nests a few levels)"
        ) from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ConversionError(
            f"{path}: not an Argoverse 2 map ({type(exc).__name__}: {exc})"
        ) from None
    return LaneMap(tuple(sorted(lanes, key=lambda lane: lane.id)), lines=lines)


def _centerline(seg: dict[str, Any]) -> np.ndarray:
    """A lane segment's ``centerline``; Argoverse 2 Sensor log maps may leave it out, then
    the mean of ``left_lane_boundary`` and ``right_lane_boundary`` (as av2-api does)."""
    if seg.get("centerline"):
        return np.array([(p["x"], p["y"]) for p in seg["centerline"]], dtype=np.float64)
    left, right = (
        np.array([(p["x"], p["y"]) for p in seg[k]], dtype=np.float64)
        for k in ("left_lane_boundary", "right_lane_boundary")
    )
    return lanelet_centerline(left, right)


def parquet_to_scene(
    parquet: str | os.PathLike,
    *,
    map_json: str | os.PathLike | None = None,
    paths: str = "map",
    settings: PathSettings | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
    skip_bad: bool = False,
    skipped: Skipped | None = None,
) -> Scene:
    """One scenario as a scene. The map is ``map_json`` or found beside the parquet
    (:func:`map_path_for`); without a map, ``--paths map`` gives straight paths."""
    parquet = pathlib.Path(parquet)
    settings = settings or PathSettings()
    df = read_table(parquet)
    scenario_id = str(df["scenario_id"][0])
    where = f"{parquet} (scenario {scenario_id})"
    table, names, renamed = scenario_tracks(df, where)
    if EGO_TRACK not in names:
        raise ConversionError(f"{where}: no ego track {EGO_TRACK!r}")
    period = frame_period_s(df)
    table = _scaled_times(table, period)
    map_file = (
        pathlib.Path(map_json) if map_json is not None else map_path_for(parquet, scenario_id)
    )
    categories = (
        df.group_by("track_id", maintain_order=True)
        .agg(pl.col("object_category").max())
        .to_dict(as_series=False)
    )
    id_of = dict(zip(names, table.ids.tolist(), strict=True))
    labels = {
        "focal": _with_category(categories, FOCAL_CATEGORY, id_of),
        "scored": _with_category(categories, SCORED_CATEGORY, id_of),
    }
    metadata = {
        "dataset": "argoverse2_motion_forecasting",
        "source_file": parquet.name,
        "map_file": map_file.name if map_file else "",
        "scenario_id": scenario_id,
        "converter": CONVERTER,
        "converter_version": CONVERTER_VERSION,
        "ego_track": EGO_TRACK,
        "ego_choice": "the autonomous vehicle (track AV)",
        "renamed_tracks": json.dumps(renamed, sort_keys=True),
    }
    if "city" in df.columns:
        metadata["city"] = str(df["city"][0])
    if "focal_track_id" in df.columns:
        metadata["focal_track_id"] = str(df["focal_track_id"][0])
    return build_scene(
        table,
        names.index(EGO_TRACK),
        read_lane_map(map_file),
        paths=paths,
        settings=settings,
        frame_period_s=period,
        metadata=metadata,
        labels=labels,
        source=where,
        progress=progress,
        time_step=time_step,
        skip_bad=skip_bad,
        skipped=skipped,
    )


def _scaled_times(table: TrackTable, period: float) -> TrackTable:
    return dataclasses.replace(table, t_s=table.t_s * period)


def _with_category(categories: dict[str, list[Any]], category: int, id_of: dict[str, int]):
    return tuple(
        id_of[str(t)]
        for t, c in zip(categories["track_id"], categories["object_category"], strict=True)
        if c == category
    )


def read_scenes(
    path: str | os.PathLike,
    *,
    paths: str = "map",
    settings: PathSettings | None = None,
    skip_bad: bool = False,
    skipped: Skipped | None = None,
    progress: bool = False,
) -> Iterator[Scene]:
    """Every scenario under ``path`` (:func:`find_scenarios`) as a scene."""
    for parquet in find_scenarios(path):
        try:
            yield parquet_to_scene(
                parquet, paths=paths, settings=settings, progress=progress,
                skip_bad=skip_bad, skipped=skipped,
            )  # fmt: skip
        except ConversionError as exc:
            if not skip_bad:
                raise
            if skipped is not None:
                skipped.add(str(exc))
