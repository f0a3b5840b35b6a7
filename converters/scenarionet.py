"""ScenarioNet scenarios (nuScenes, nuPlan, Lyft, Waymo, Argoverse 2 in one format) into scenes.

A ScenarioNet scenario is a pickle of nested dicts of numpy arrays (docs/recorded-data.md
has the table). It is loaded with :mod:`converters.safe_pickle`, which runs nothing from
the file, then checked field by field before anything is built from it.

Inputs: one scenario ``.pkl``, or a ScenarioNet **database folder**: the files that its
``dataset_mapping.pkl`` names (value ``""``: this folder, else the sub-folder given), or
else those of its ``dataset_summary.pkl``, or else every ``*.pkl`` in it. Every named file
must exist before anything is converted.

Mapping (one scene per scenario):

- time: ``metadata.ts``; frame period: the median step, to the ms;
- ego: ``metadata.sdc_id``, the vehicle that recorded the data;
- agents: every track; id: the track key when it is an integer (Waymo), else a number
  after the largest such key in sorted key order (nuScenes tokens, ``ego``; the
  renaming is the metadata ``renamed_tracks``); valid where ``state.valid``;
  position ``state.position[:, :2]``, heading, speed ``|state.velocity|``, length and width
  (``(T,)`` or ``(T, 1)``);
- kinds: :data:`TRACK_KINDS`, except nuScenes motorcycles (ScenarioNet's ``CYCLIST``
  with category ``vehicle.motorcycle``), which are vehicles. ``TRAFFIC_CONE`` and ``TRAFFIC_BARRIER`` are **kept** as
  standing agents of kind ``other``: unlike the bollards and signs that the Argoverse 2
  Sensor converter leaves out, they are temporary (road works), no map holds them, and
  a planner learns of them only from these tracks;
- map: lanes (``LANE_*``: centre line ``polyline``, successors ``exit_lanes``; a map whose
  lanes have no ``exit_lanes`` at all, nuScenes, is chained geometrically by
  :mod:`converters.lane_chain`), road lines (``ROAD_LINE_*`` -> ``lane_boundary``, the
  rest of the type as style), road edges (``ROAD_EDGE_*`` -> ``road_edge``), crosswalks,
  and speed bumps and driveways as closed ``other`` polygons; stop signs (points) and
  unknown types are counted in ``map_features_left_out``;
- paths (``--paths map``): vehicles and cyclists follow the lane graph; one that matches
  no lane follows its **recorded future** (nuScenes maps cover only part of the roads);
  pedestrians and ``other`` go straight; the labels ``paths_lane_graph``,
  ``paths_recorded_future`` and ``paths_straight`` say which agents got which;
- labels: Waymo's ``objects_of_interest`` and ``tracks_to_predict`` (track keys);
- traffic lights (``dynamic_map_states``): the metadata ``traffic_lights`` (JSON: per
  light its lane id, stop point and state changes); no model reads them.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import pathlib
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from converters import safe_pickle
from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.input_checks import check_grid
from converters.lane_chain import MAX_GAP_M, MAX_HEADING_RAD, chain_successors
from converters.lanegraph import PathSettings
from converters.map_lines import dedupe_lines
from converters.tracks import Skipped, TrackTable, build_scene, integer_ids
from risk.frame import Kind, Lane, LaneMap, MapLine, Scene

CONVERTER = "converters.scenarionet"
CONVERTER_VERSION = "1"
SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"
INDEX_FILES = (SUMMARY_FILE, MAPPING_FILE)

TRACK_KINDS: dict[str, Kind] = {
    "VEHICLE": Kind.VEHICLE,
    "PEDESTRIAN": Kind.PEDESTRIAN,
    "CYCLIST": Kind.CYCLIST,
    "TRAFFIC_CONE": Kind.OTHER,
    "TRAFFIC_BARRIER": Kind.OTHER,
}
"""ScenarioNet track ``type`` -> kind; any other type is ``other``."""

MOTORCYCLE_CATEGORY = "vehicle.motorcycle"
"""nuScenes category (the track's ``metadata.type``) that ScenarioNet types ``CYCLIST`` but
that is a vehicle here, as in every converter (motorcycles use lanes and move like cars)."""

POLYGON_TYPES = {"CROSSWALK": "crosswalk", "SPEED_BUMP": "other", "DRIVEWAY": "other"}
"""Map feature types kept as closed polygons, and their line kind."""

LABEL_KEYS = ("objects_of_interest", "tracks_to_predict")
MAX_POINTS = 1_000_000  # points of one map polyline given as a list


# ---------------------------------------------------------------------- inputs
def is_scenario_file(path: pathlib.Path) -> bool:
    """Cheap check: a pickle (any protocol, 0-5) whose first 4 KiB name the top-level keys of a
    ScenarioNet scenario (``version``, ``length``, ``metadata`` or ``tracks``), or one of
    the database's index files."""
    if path.name in INDEX_FILES:
        return True
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    protocol_2_to_5 = len(head) > 2 and head[0] == 0x80 and 2 <= head[1] <= 5
    protocol_0_or_1 = head[:1] in (b"(", b"}")  # a dict: MARK ... DICT, or EMPTY_DICT
    return (
        (protocol_2_to_5 or protocol_0_or_1)
        and b"version" in head
        and b"length" in head
        and (b"metadata" in head or b"tracks" in head)
    )


def is_database(folder: pathlib.Path) -> bool:
    return any((folder / name).is_file() for name in INDEX_FILES)


def _index(folder: pathlib.Path, name: str) -> dict[str, Any]:
    data = safe_pickle.load(folder / name, what=f"ScenarioNet {name}")
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise ConversionError(f"{folder / name}: not a ScenarioNet index (a dict of file names)")
    return data


def scenario_files(path: str | os.PathLike) -> list[pathlib.Path]:
    """The scenario files of an input: the file itself, or those of a database folder
    (mapping, else summary, else every ``*.pkl`` but the index files), in sorted order;
    a folder with none of these: those of its sub-folders that have them. Raises
    ConversionError when a named file is missing or no scenario is found."""
    path = pathlib.Path(path)
    if path.is_file():
        return [path]
    if not path.is_dir():
        raise ConversionError(f"{path}: no such file or folder")
    if (path / MAPPING_FILE).is_file():
        mapping = _index(path, MAPPING_FILE)
        bad = [k for k, v in mapping.items() if not isinstance(v, str)]
        if bad:
            raise ConversionError(f"{path / MAPPING_FILE}: {bad[0]!r} maps to no folder name")
        files = [path / sub / name for name, sub in mapping.items()]
        index = MAPPING_FILE
    elif (path / SUMMARY_FILE).is_file():
        files = [path / name for name in _index(path, SUMMARY_FILE)]
        index = SUMMARY_FILE
    else:
        files = [p for p in path.glob("*.pkl") if p.name not in INDEX_FILES and p.is_file()]
        index = ""
        if not files:  # a folder of databases (one level down), as the test data comes
            subs = sorted(d for d in path.iterdir() if d.is_dir() and _holds_scenarios(d))
            if not subs:
                raise ConversionError(
                    f"{path}: no ScenarioNet scenario (*.pkl) in this folder or its sub-folders"
                )
            return [f for d in subs for f in scenario_files(d)]
    missing = [f for f in files if not f.is_file()]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise ConversionError(
            f"{path / index}: names {os.path.relpath(missing[0], path)}, which does not exist"
            f"{more}; copy the whole database or rebuild its index"
        )
    return _distinct(files)


def _distinct(files: list[pathlib.Path]) -> list[pathlib.Path]:
    """Sorted, each file once: an index naming one file twice (through ``..`` or a link)
    converts it once (the first path in sorted order is kept)."""
    seen: set[tuple[int, int]] = set()
    out = []
    for f in sorted(set(files)):
        st = f.stat()
        if (st.st_dev, st.st_ino) not in seen:
            seen.add((st.st_dev, st.st_ino))
            out.append(f)
    return out


def _holds_scenarios(folder: pathlib.Path) -> bool:
    return is_database(folder) or any(
        p.name not in INDEX_FILES for p in folder.glob("*.pkl") if p.is_file()
    )


def companions(path: pathlib.Path) -> list[pathlib.Path]:
    """Every file a conversion of ``path`` reads besides it (a folder: its index files and
    scenarios); what cannot be listed yet is left to the conversion to report."""
    if not path.is_dir():
        return []
    found = [path / n for n in INDEX_FILES if (path / n).is_file()]
    with contextlib.suppress(ConversionError):  # the conversion reports it
        found += scenario_files(path)
    return found


# ---------------------------------------------------------------------- checking
def _get(d: Mapping[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    if key not in d:
        raise ConversionError(f"{where}: no {key!r}; not a ScenarioNet scenario")
    value = d[key]
    if not isinstance(value, kind):
        raise ConversionError(
            f"{where}: {key!r} is a {type(value).__name__}, not the expected type"
        )
    return value


def _array(
    state: Mapping[str, Any], key: str, n_steps: int, cols: tuple[int, ...], where: str
) -> np.ndarray:
    """``state[key]`` as float64 ``(T,)`` (cols ``()``), ``(T, 1)`` flattened, or
    ``(T, k)`` with k in ``cols``."""
    a = _get(state, key, np.ndarray, where)
    if a.dtype.kind not in "biuf":
        raise ConversionError(f"{where}: {key!r} holds {a.dtype} values, not numbers")
    if cols:
        ok = a.ndim == 2 and a.shape[1] in cols
    else:
        ok = a.ndim == 1 or (a.ndim == 2 and a.shape[1] == 1)
    if not ok or a.shape[0] != n_steps:
        want = f"(T, {' or '.join(map(str, cols))})" if cols else "(T,) or (T, 1)"
        raise ConversionError(
            f"{where}: {key!r} has shape {a.shape}, expected {want} with T = {n_steps} steps"
        )
    return a.astype(np.float64, copy=False) if cols else a.reshape(n_steps).astype(np.float64)


def _points(value: Any, where: str) -> np.ndarray:
    """A polyline or polygon as ``(K, 2)`` float64: an array ``(K, 2|3)`` or a list of
    2- or 3-number sequences (read element by element: a list cannot expand into more
    numbers than it holds)."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf" or value.ndim != 2 or value.shape[1] not in (2, 3):
            raise ConversionError(f"{where}: points of shape {value.shape}, expected (K, 2 or 3)")
        return value[:, :2].astype(np.float64)
    if not isinstance(value, (list, tuple)) or len(value) > MAX_POINTS:
        raise ConversionError(f"{where}: points are a {type(value).__name__}, not a list of points")
    widths = {len(p) if isinstance(p, (list, tuple, np.ndarray)) else -1 for p in value}
    if not value:
        return np.zeros((0, 2))
    if len(widths) != 1 or next(iter(widths)) not in (2, 3):
        raise ConversionError(f"{where}: points are not all (x, y) or (x, y, z)")
    width = next(iter(widths))
    try:
        flat = np.fromiter(
            itertools.chain.from_iterable(value), dtype=np.float64, count=len(value) * width
        )
    except (TypeError, ValueError):
        raise ConversionError(f"{where}: a point holds something other than numbers") from None
    return flat.reshape(-1, width)[:, :2].copy()


# ---------------------------------------------------------------------- reading
def read_scenario(path: str | os.PathLike) -> dict[str, Any]:
    """Load a scenario file safely and check its top level (:func:`check_scenario`)."""
    if pathlib.Path(path).name in INDEX_FILES:
        raise ConversionError(
            f"{path}: the index of a ScenarioNet database, not a scenario; give its folder"
        )
    sd = safe_pickle.load_isolated(path)  # (a crash would end a child, not this process)
    check_scenario(sd, str(path))
    return sd


def check_scenario(sd: Any, where: str) -> None:
    """Raise ConversionError unless ``sd`` is a dict with the dicts ``tracks``,
    ``metadata`` (holding ``sdc_id``) and ``map_features``."""
    if not isinstance(sd, dict):
        raise ConversionError(
            f"{where}: holds a {type(sd).__name__}, not a ScenarioNet scenario (a dict)"
        )
    for key, kind in (("tracks", dict), ("metadata", dict), ("map_features", dict)):
        _get(sd, key, kind, where)
    if "sdc_id" not in sd["metadata"]:
        raise ConversionError(
            f"{where}: metadata has no 'sdc_id' (the ego's track); not a ScenarioNet scenario"
        )


def _text(value: Any) -> str:
    """A metadata value as text when it is a string or an integer, else ''."""
    return str(value) if isinstance(value, (str, int, np.integer)) else ""


def scenario_tracks(
    sd: Mapping[str, Any], where: str
) -> tuple[TrackTable, list[str], dict[str, int]]:
    """The tracks as a TrackTable, their keys (in table order) and the renamed ids."""
    md = sd["metadata"]
    ts = md.get("ts")
    if not isinstance(ts, np.ndarray) or ts.ndim != 1 or ts.dtype.kind not in "biuf":
        raise ConversionError(f"{where}: metadata 'ts' is not a 1-D array of step times")
    t_s = ts.astype(np.float64)
    steps = np.diff(t_s)
    if t_s.size == 0 or not np.isfinite(t_s).all() or (steps <= 0).any():
        raise ConversionError(f"{where}: metadata 'ts' is empty or not increasing")
    names = [str(k) for k in sd["tracks"]]
    if not names:
        raise ConversionError(f"{where}: the scenario has no tracks")
    n_steps, n = t_s.size, len(names)
    check_grid(n_steps, n, source=where)
    xy = np.empty((n_steps, n, 2))
    heading = np.empty((n_steps, n))
    speed = np.empty((n_steps, n))
    length = np.empty((n_steps, n))
    width = np.empty((n_steps, n))
    valid = np.empty((n_steps, n), dtype=bool)
    kinds = np.empty(n, dtype=np.int8)
    for i, (key, track) in enumerate(sd["tracks"].items()):  # once per track: gather arrays
        w = f"{where}: track {key}"
        if not isinstance(track, dict):
            raise ConversionError(f"{w}: a {type(track).__name__}, not a dict")
        kind = _get(track, "type", str, w)
        state = _get(track, "state", dict, w)
        kinds[i] = TRACK_KINDS.get(kind, Kind.OTHER)
        meta = track.get("metadata")
        category = meta.get("type") if isinstance(meta, dict) else None
        if isinstance(category, str) and category.startswith(MOTORCYCLE_CATEGORY):
            kinds[i] = Kind.VEHICLE  # ScenarioNet makes them cyclists; we count them as vehicles
        xy[:, i] = _array(state, "position", n_steps, (2, 3), w)[:, :2]
        heading[:, i] = _array(state, "heading", n_steps, (), w)
        velocity = _array(state, "velocity", n_steps, (2,), w)
        speed[:, i] = np.hypot(velocity[:, 0], velocity[:, 1])
        length[:, i] = _array(state, "length", n_steps, (), w)
        width[:, i] = _array(state, "width", n_steps, (), w)
        valid[:, i] = _array(state, "valid", n_steps, (), w) > 0.5
    ids, renamed = integer_ids(names)
    table = TrackTable(ids, kinds, t_s, xy, heading, speed, length, width, valid)
    return table, names, renamed


def scenario_lane_map(sd: Mapping[str, Any], where: str) -> tuple[LaneMap, dict[str, str]]:
    """Lanes and map lines; also facts for the metadata (how lanes were linked, what was
    left out)."""
    features = sd["map_features"]
    id_of = _feature_ids(sd, where)
    keys = list(id_of)
    lanes: list[tuple[int, np.ndarray, str, Any]] = []  # id, centre line, kind, exit_lanes
    lines: list[MapLine] = []
    left_out: dict[str, int] = {}
    for key, f in zip(keys, features.values(), strict=True):
        w = f"{where}: map feature {key}"
        if not isinstance(f, dict):
            raise ConversionError(f"{w}: a {type(f).__name__}, not a dict")
        kind = _get(f, "type", str, w)
        fid = id_of[key]
        if kind.startswith("LANE_"):
            exits = f.get("exit_lanes")
            if exits is not None and not isinstance(exits, (list, tuple, np.ndarray)):
                raise ConversionError(f"{w}: 'exit_lanes' is not a list")
            lane_kind = "bike" if kind == "LANE_BIKE_LANE" else "vehicle"
            lanes.append((fid, _points(f.get("polyline"), w), lane_kind, exits))
        elif kind.startswith(("ROAD_LINE_", "ROAD_EDGE_")):
            line_kind = "lane_boundary" if kind.startswith("ROAD_LINE_") else "road_edge"
            style = kind.split("_", 2)[2].lower()  # ROAD_LINE_BROKEN_SINGLE_WHITE -> broken_...
            lines.append(MapLine(fid, line_kind, _points(f.get("polyline"), w), style=style))
        elif kind in POLYGON_TYPES:
            pts = _points(f["polygon"] if "polygon" in f else f.get("polyline"), w)
            style = "" if kind == "CROSSWALK" else kind.lower()
            lines.append(MapLine(fid, POLYGON_TYPES[kind], pts, closed=True, style=style))
        else:
            left_out[kind] = left_out.get(kind, 0) + 1
    linked = any(exits is not None for *_, exits in lanes)
    if linked:
        successors = [
            tuple(
                id_of[k]
                for k in map(_feature_key, exits if exits is not None else ())
                if k in id_of
            )
            for *_, exits in lanes
        ]
        how = "exit_lanes"
    else:
        chained = chain_successors([pts for _, pts, _, _ in lanes])
        successors = [tuple(lanes[j][0] for j in succ) for succ in chained]
        how = (
            f"chained: a lane starting within {MAX_GAP_M:g} m of another's end, heading "
            f"within {np.degrees(MAX_HEADING_RAD):g} deg"
        )
    lane_objs = tuple(
        Lane(id=fid, centerline=pts, successors=succ, kind=lane_kind)
        for (fid, pts, lane_kind, _), succ in zip(lanes, successors, strict=True)
        if len(pts)
    )
    facts = {
        "lane_links": how,
        "map_features_left_out": json.dumps(left_out, sort_keys=True),
    }
    return LaneMap(lane_objs, lines=dedupe_lines(lines)), facts


def scenario_labels(
    md: Mapping[str, Any], id_of: Mapping[str, int], where: str
) -> dict[str, tuple[int, ...]]:
    """Waymo's ``objects_of_interest`` and ``tracks_to_predict`` (keys of tracks) as ids."""
    labels: dict[str, tuple[int, ...]] = {}
    for name in LABEL_KEYS:
        if name not in md or md[name] is None:
            continue
        value = md[name]
        if not isinstance(value, (list, tuple, dict, set, np.ndarray)):
            raise ConversionError(f"{where}: metadata {name!r} is not a list of track ids")
        keys = [str(k) for k in value]
        unknown = [k for k in keys if k not in id_of]
        if unknown:
            raise ConversionError(
                f"{where}: metadata {name!r} names track {unknown[0]}, not in tracks"
            )
        labels[name] = tuple(id_of[k] for k in keys)
    return labels


def traffic_lights(
    sd: Mapping[str, Any], t_s: np.ndarray, lane_id: Mapping[str, int], where: str
) -> list[dict[str, Any]]:
    """``dynamic_map_states`` as JSON-able lights: lane id, stop point (m) and the state
    changes ``[t_s, state]`` (``LANE_STATE_`` dropped; ``null`` where unknown)."""
    states = sd.get("dynamic_map_states")
    if states is None:
        return []
    if not isinstance(states, dict):
        raise ConversionError(f"{where}: 'dynamic_map_states' is not a dict")
    out = []
    for key, light in states.items():
        w = f"{where}: dynamic map state {key}"
        if not isinstance(light, dict):
            raise ConversionError(f"{w}: a {type(light).__name__}, not a dict")
        state = light.get("state")
        seq = state.get("object_state") if isinstance(state, dict) else None
        if not isinstance(seq, (list, tuple)) or len(seq) != t_s.size:
            raise ConversionError(f"{w}: 'state.object_state' is not one state per step")
        changes: list[list[Any]] = []
        for k, s in enumerate(seq):
            name = s.removeprefix("LANE_STATE_") if isinstance(s, str) else None
            if not changes or changes[-1][1] != name:
                changes.append([round(float(t_s[k]), 3), name])
        stop = light.get("stop_point")
        stop_xy = (
            [round(float(v), 3) for v in stop[:2]]
            if isinstance(stop, np.ndarray) and stop.dtype.kind in "biuf" and stop.ndim == 1
            and stop.size >= 2
            else None
        )  # fmt: skip
        out.append(
            {
                "lane": lane_id.get(_feature_key(light.get("lane"))),
                "stop_point_m": stop_xy,
                "states": changes,
            }
        )
    return out


# ---------------------------------------------------------------------- conversion
def scenario_to_scene(
    sd: Mapping[str, Any],
    *,
    source: str | os.PathLike,
    paths: str = "map",
    settings: PathSettings | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
    skip_bad: bool = False,
    skipped: Skipped | None = None,
) -> Scene:
    """One checked scenario dict (:func:`read_scenario`) as a scene."""
    settings = settings or PathSettings()
    check_scenario(sd, str(source))
    md = sd["metadata"]
    scenario_id = _text(md.get("scenario_id")) or _text(md.get("id")) or _text(sd.get("id"))
    where = f"{source} (scenario {scenario_id or '?'})"
    table, names, renamed = scenario_tracks(sd, where)
    sdc = _text(md["sdc_id"])
    if sdc not in names:
        raise ConversionError(f"{where}: metadata sdc_id {sdc!r} is not one of the tracks")
    ego = names.index(sdc)
    lane_map, map_facts = scenario_lane_map(sd, where)
    id_of = dict(zip(names, table.ids.tolist(), strict=True))
    steps = np.diff(table.t_s)
    period = (round(float(np.median(steps)), 3) or float(np.median(steps))) if steps.size else 0.1
    lights = traffic_lights(sd, table.t_s, _feature_ids(sd, where), where)
    dataset = _text(md.get("dataset")) or "unknown"
    metadata = {
        "dataset": dataset,
        "source_format": f"scenarionet {_text(sd.get('version'))}".strip(),
        "source_file": os.path.basename(os.fspath(source)),
        "scenario_id": scenario_id,
        "converter": CONVERTER,
        "converter_version": CONVERTER_VERSION,
        "ego_track": sdc,
        "ego_choice": "the self-driving car (metadata.sdc_id)",
        "renamed_tracks": json.dumps(renamed, sort_keys=True),
        "static_obstacles": str(
            sum(
                str(t.get("type")) in ("TRAFFIC_CONE", "TRAFFIC_BARRIER")
                for t in sd["tracks"].values()
            )
        ),
        **map_facts,
    }
    for key in ("map", "current_time_index"):
        if _text(md.get(key)):
            metadata[key] = _text(md[key])
    if lights:
        metadata["traffic_lights"] = json.dumps(lights, separators=(",", ":"))
    return build_scene(
        table,
        ego,
        lane_map,
        paths=paths,
        settings=settings,
        frame_period_s=period,
        metadata=metadata,
        labels=scenario_labels(md, id_of, where),
        source=where,
        progress=progress,
        time_step=time_step,
        skip_bad=skip_bad,
        skipped=skipped,
        off_lane="hindsight",
        path_source_labels=True,
    )


def _feature_key(ref: Any) -> str:
    """A reference to a map feature (Waymo: an int; else the key itself) as its key."""
    if isinstance(ref, (bool, np.bool_)):
        return ""
    if isinstance(ref, (int, np.integer)):
        return str(int(ref))
    return ref if isinstance(ref, str) else ""


def _feature_ids(sd: Mapping[str, Any], where: str) -> dict[str, int]:
    """Map feature key -> integer id (integer keys keep their value, as for tracks)."""
    keys = [str(k) for k in sd["map_features"]]
    if len(set(keys)) != len(keys):
        raise ConversionError(f"{where}: two map features have the same key (as text)")
    ids, _ = integer_ids(keys)
    return dict(zip(keys, ids.tolist(), strict=True))


def read_scene(
    path: str | os.PathLike,
    *,
    paths: str = "map",
    settings: PathSettings | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
    skip_bad: bool = False,
    skipped: Skipped | None = None,
) -> Scene:
    """One scenario file as a scene."""
    return scenario_to_scene(
        read_scenario(path),
        source=path,
        paths=paths,
        settings=settings,
        progress=progress,
        time_step=time_step,
        skip_bad=skip_bad,
        skipped=skipped,
    )


def read_scenes(path: str | os.PathLike, **options: Any) -> Iterator[Scene]:
    """Every scenario of a file or database folder as a scene, in file order."""
    for f in scenario_files(path):
        yield read_scene(f, **options)
