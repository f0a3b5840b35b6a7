"""CommonRoad XML scenarios (2018b and 2020a) into scenes, with the standard library.

``commonroad-io`` is not used: its current release pins protobuf 3.20 (we run protobuf
>= 4.25) and brings scipy, shapely, networkx, rtree and lxml; the part of the format we
need reads in a page of ``xml.etree.ElementTree``.

Mapping (docs/recorded-data.md has the tables):

- every ``dynamicObstacle`` is an agent (id: its ``id``); its ``initialState`` and
  ``trajectory`` states give its pose at their ``time`` steps, and it is invalid at every
  other step; frame period: the root's ``timeStepSize`` (s), unless the clock check of
  :mod:`converters.clock` corrects it (SinD and highD files label 0.5 s and 0.2 s as 0.1 s);
- pose ``position/point`` (m), ``orientation`` (rad), speed ``|(velocity, velocityY)|``
  (m/s; a state without ``velocity`` gets the finite-difference speed of its track, one
  without ``orientation`` the direction of motion); size from the ``shape``
  (rectangle length x width; circle: its diameter both ways; polygon: its extents);
  values given as intervals take the interval's midpoint;
- kinds: car, truck, bus, taxi, priorityVehicle, parkedVehicle, motorcycle -> vehicle;
  bicycle -> cyclist; pedestrian -> pedestrian; anything else -> other;
- static obstacles (``staticObstacle``, e.g. a parked vehicle): an agent with speed 0 at
  its ``initialState`` pose, valid at every step of the scene;
- traffic lights are counted (metadata ``traffic_lights``) but their states are not used:
  the risk models have no notion of signals;
- ego: ``--ego ID``, default the moving-ego rule of :func:`converters.tracks.moving_ego`
  (the vehicle that travels farthest); ``planningProblem`` is ignored (it holds the
  planned vehicle's start only, no motion);
- map: each ``lanelet`` is a lane whose centre line is the mean of its left and right
  bounds (resampled to a common count when they differ), with its ``successor`` links;
  kind from ``laneletType`` (bicycleLane -> bike, busLane/busStop -> bus, crosswalk,
  sidewalk -> walkway, else vehicle).
"""

from __future__ import annotations

import math
import os
import pathlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.input_checks import MAX_STEPS, check_grid, check_points, integer_id
from converters.lanegraph import PathSettings, dedupe, lanelet_centerline
from converters.map_lines import commonroad_lines
from converters.tracks import Skipped, TrackTable, build_scene, moving_ego
from risk.frame import Kind, Lane, LaneMap, Scene

CONVERTER = "converters.commonroad"
CONVERTER_VERSION = "2"
#: The longest time step accepted (an hour; 1e300 overflowed the time grid).
MAX_TIME_STEP_S = 3600.0

OBSTACLE_KINDS: dict[str, Kind] = {
    "car": Kind.VEHICLE,
    "truck": Kind.VEHICLE,
    "bus": Kind.VEHICLE,
    "taxi": Kind.VEHICLE,
    "priorityVehicle": Kind.VEHICLE,
    "parkedVehicle": Kind.VEHICLE,
    "motorcycle": Kind.VEHICLE,  # moves and uses lanes like a vehicle
    "bicycle": Kind.CYCLIST,
    "pedestrian": Kind.PEDESTRIAN,
}
"""CommonRoad obstacle ``type`` -> kind; any other type (train, constructionZone,
roadBoundary, building, pillar, median_strip, unknown) is ``other``."""

LANELET_KINDS: tuple[tuple[str, str], ...] = (
    ("sidewalk", "walkway"),
    ("crosswalk", "crosswalk"),
    ("bicycleLane", "bike"),
    ("busLane", "bus"),
    ("busStop", "bus"),
)
"""First ``laneletType`` match wins; a lanelet with none of these is a vehicle lane."""


@dataclass(frozen=True)
class Obstacle:
    """One dynamic obstacle's states, sorted by time step."""

    id: int
    kind: Kind
    length: float
    width: float
    steps: np.ndarray  # (K,) int64
    xy: np.ndarray  # (K, 2) m
    heading: np.ndarray  # (K,) rad
    speed: np.ndarray  # (K,) m/s
    speed_measured: np.ndarray | None = None  # (K,) bool: <velocity> given (else derived)


def parse(path: str | os.PathLike) -> ET.Element:
    """The root element; ConversionError when the file is not CommonRoad XML."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise ConversionError(f"{path}: not well-formed XML ({exc})") from None
    if root.tag != "commonRoad":
        raise ConversionError(
            f"{path}: not a CommonRoad scenario (root element <{root.tag}>, expected <commonRoad>)"
        )
    return root


def _value(elem: ET.Element | None, what: str) -> float:
    """A CommonRoad value: ``<exact>``, an interval's midpoint, or a bare number."""
    if elem is None:
        raise ValueError(f"missing <{what}>")
    if len(elem) and elem[0].tag == "exact":  # the common case, without a search
        return float(elem[0].text or "")
    exact = elem.find("exact")
    if exact is not None:
        return float(exact.text or "")
    lo, hi = elem.find("intervalStart"), elem.find("intervalEnd")
    if lo is not None and hi is not None:
        return 0.5 * (float(lo.text or "") + float(hi.text or ""))
    return float((elem.text or "").strip())


def _optional(elem: ET.Element | None, what: str) -> float:
    """NaN when the element is absent (filled in later); an explicit NaN in the file is a
    bad value, not a missing one, so it becomes inf for converters.input_checks's rule."""
    if elem is None:
        return np.nan
    value = _value(elem, what)
    return np.inf if np.isnan(value) else value


def _point(elem: ET.Element) -> tuple[float, float]:
    return float(elem.findtext("x", "")), float(elem.findtext("y", ""))


def _shape_size(shape: ET.Element | None) -> tuple[float, float]:
    if shape is None:
        raise ValueError("missing <shape>")
    rect = shape.find("rectangle")
    if rect is not None:
        return float(rect.findtext("length", "")), float(rect.findtext("width", ""))
    circle = shape.find("circle")
    if circle is not None:
        d = 2.0 * float(circle.findtext("radius", ""))
        return d, d
    polygon = shape.find("polygon")
    if polygon is not None:
        pts = np.array([_point(p) for p in polygon.findall("point")])
        if len(pts):
            extent = pts.max(axis=0) - pts.min(axis=0)
            return float(extent[0]), float(extent[1])
    raise ValueError("unsupported <shape> (expected rectangle, circle or polygon)")


def parse_obstacle(elem: ET.Element, dt_s: float) -> Obstacle:
    """One ``dynamicObstacle`` or ``staticObstacle`` (its one ``initialState``; the
    caller spreads it over the scene); raises ValueError naming what is wrong."""
    try:
        oid = int(elem.get("id", "").strip())
    except ValueError:
        raise ValueError(f"the id must be an integer, got {elem.get('id')!r}") from None
    kind = OBSTACLE_KINDS.get((elem.findtext("type") or "").strip(), Kind.OTHER)
    length, width = _shape_size(elem.find("shape"))
    states = [s for s in [elem.find("initialState")] if s is not None]
    states += elem.findall("trajectory/state")
    if not states:
        raise ValueError("no states")
    table = np.array([_state_row(state) for state in states], dtype=np.float64)
    table = table[np.argsort(table[:, 0], kind="stable")]
    steps = table[:, 0].astype(np.int64)
    if np.any(np.diff(steps) == 0):
        raise ValueError("two states at the same time step")
    xy = table[:, 1:3]
    measured = ~np.isnan(table[:, 4])
    heading, speed = _fill_motion(steps, xy, table[:, 3], table[:, 4], dt_s)
    return Obstacle(oid, kind, length, width, steps, xy, heading, speed, measured)


def _state_row(state: ET.Element) -> tuple[float, float, float, float, float]:
    """``(time step, x, y, orientation, speed)`` of one state (NaN: not given). One pass
    over the state's children: a path ``find`` per value costs ten times more on files of
    tens of thousands of states."""
    found: dict[str, ET.Element] = {}
    for child in state:
        found[child.tag] = child
    position = found.get("position")
    point = None if position is None else position.find("point")
    if point is None:
        raise ValueError("a state has no <position><point>")
    vx = _optional(found.get("velocity"), "velocity")
    vy = _optional(found.get("velocityY"), "velocityY")
    time_step = _value(found.get("time"), "time")
    if not (math.isfinite(time_step) and 0 <= time_step <= MAX_STEPS):
        raise ValueError(f"<time> must be a time step in 0..{MAX_STEPS}, got {time_step:g}")
    return (
        round(time_step),
        *_point(point),
        _optional(found.get("orientation"), "orientation"),
        math.hypot(vx, 0.0 if math.isnan(vy) else vy),
    )


def _fill_motion(
    steps: np.ndarray, xy: np.ndarray, heading: np.ndarray, speed: np.ndarray, dt_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Missing speeds from finite differences of the positions, missing headings from
    the direction of motion (0 for a lone state)."""
    if len(steps) > 1 and (np.isnan(heading).any() or np.isnan(speed).any()):
        t = steps * dt_s
        vel = np.stack([np.gradient(xy[:, 0], t), np.gradient(xy[:, 1], t)], axis=1)
        speed = np.where(np.isnan(speed), np.hypot(*vel.T), speed)
        heading = np.where(np.isnan(heading), np.arctan2(vel[:, 1], vel[:, 0]), heading)
    # Missing values (NaN) of a lone state become 0; infinities stay, for converters.input_checks.
    return np.where(np.isnan(heading), 0.0, heading), np.where(np.isnan(speed), 0.0, speed)


def read_lane_map(root: ET.Element, where: str) -> LaneMap:
    lanes = []
    for elem in root.findall("lanelet"):
        lid = integer_id(elem.get("id"), f"{where}: lanelet {elem.get('id')!r}")
        try:
            left = np.array([_point(p) for p in elem.findall("leftBound/point")])
            right = np.array([_point(p) for p in elem.findall("rightBound/point")])
        except ValueError as exc:
            raise ConversionError(f"{where}: lanelet {elem.get('id')!r}: {exc}") from None
        for bound, pts in (("leftBound", left), ("rightBound", right)):
            check_points(pts, f"{where}: lanelet {lid} {bound}")
        if len(left) < 2 or len(right) < 2:
            continue
        line = dedupe(lanelet_centerline(dedupe(left), dedupe(right)))
        if len(line) < 2:
            continue
        types = {(t.text or "").strip() for t in elem.findall("laneletType")}
        kind = next((k for name, k in LANELET_KINDS if name in types), "vehicle")
        for ref in elem.iter():  # every reference checked, used or not (issue 36: a
            if "ref" in ref.attrib and ref is not elem:  # text one was silently ignored)
                integer_id(ref.get("ref"), f"{where}: lanelet {lid}: {ref.tag}", "ref")
        successors = tuple(
            integer_id(s.get("ref"), f"{where}: lanelet {lid}: successor", "ref")
            for s in elem.findall("successor")
        )
        lanes.append(Lane(id=lid, centerline=line, successors=successors, kind=kind))
    try:
        lines = commonroad_lines(root)
    except ValueError as exc:
        raise ConversionError(f"{where}: lanelet bounds: {exc}") from None
    return LaneMap(tuple(lanes), lines=lines)


def read_obstacles(
    root: ET.Element,
    dt_s: float,
    where: str,
    *,
    skip_bad: bool,
    skipped: Skipped | None,
    tag: str = "dynamicObstacle",
) -> list[Obstacle]:
    """The obstacles of element ``tag`` (``dynamicObstacle`` or ``staticObstacle``)."""
    obstacles = []
    for elem in root.findall(tag):
        try:
            obstacles.append(parse_obstacle(elem, dt_s))
        except (ValueError, TypeError) as exc:
            message = f"{where}: {tag} {elem.get('id')!r}: {exc}"
            if not skip_bad:
                raise ConversionError(message) from None
            if skipped is not None:
                skipped.add(message)
    return obstacles


def obstacles_table(
    obstacles: list[Obstacle],
    dt_s: float,
    static: list[Obstacle] | None = None,
    where: str = "input",
) -> TrackTable:
    """The obstacles on a common grid of time steps (from the earliest state's step of a
    dynamic obstacle); each ``static`` obstacle stands at its pose, speed 0, at every
    step. A grid too large for this machine's memory is refused before it is allocated."""
    static = static or []
    first = min(int(o.steps[0]) for o in obstacles)
    n_steps = max(int(o.steps[-1]) for o in obstacles) - first + 1
    check_grid(n_steps, len(obstacles) + len(static), source=where)
    grid = np.arange(n_steps)
    static = [
        Obstacle(
            o.id, o.kind, o.length, o.width, grid + first,
            np.repeat(o.xy[:1], n_steps, axis=0), np.repeat(o.heading[:1], n_steps),
            np.zeros(n_steps),
        )
        for o in static
    ]  # fmt: skip
    obstacles = [*obstacles, *static]
    shape = (n_steps, len(obstacles))
    xy = np.zeros((*shape, 2))
    heading = np.zeros(shape)
    speed = np.zeros(shape)
    valid = np.zeros(shape, dtype=bool)
    measured = np.ones(shape, dtype=bool)  # a static obstacle's speed 0 is exact
    for i, o in enumerate(obstacles):  # once per obstacle: scatter its states
        rows = o.steps - first
        xy[rows, i] = o.xy
        heading[rows, i] = o.heading
        speed[rows, i] = o.speed
        valid[rows, i] = True
        if o.speed_measured is not None:
            measured[rows, i] = o.speed_measured
    sizes = np.array([(o.length, o.width) for o in obstacles])
    return TrackTable(
        ids=np.array([o.id for o in obstacles], dtype=np.int64),
        kinds=np.array([o.kind for o in obstacles], dtype=np.int8),
        t_s=(first + np.arange(n_steps)) * dt_s,
        xy=xy,
        heading=heading,
        speed=speed,
        length=np.broadcast_to(sizes[:, 0], shape),
        width=np.broadcast_to(sizes[:, 1], shape),
        valid=valid,
        speed_measured=measured,
    )


def read_scene(
    path: str | os.PathLike,
    *,
    ego: int | None = None,
    paths: str = "map",
    settings: PathSettings | None = None,
    skip_bad: bool = False,
    skipped: Skipped | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
) -> Scene:
    """A CommonRoad XML file as a scene; ``ego`` is a dynamic obstacle id (default: the
    moving-ego rule, :func:`converters.tracks.moving_ego`)."""
    path = pathlib.Path(path)
    settings = settings or PathSettings()
    root = parse(path)
    where = str(path)
    try:
        dt_s = float(root.get("timeStepSize", ""))
    except ValueError:
        raise ConversionError(f"{path}: <commonRoad> has no numeric timeStepSize") from None
    if not (np.isfinite(dt_s) and 0 < dt_s <= MAX_TIME_STEP_S):
        raise ConversionError(
            f"{path}: timeStepSize must be > 0 and at most {MAX_TIME_STEP_S:g} s, got {dt_s:g}"
        )
    obstacles = read_obstacles(root, dt_s, where, skip_bad=skip_bad, skipped=skipped)
    if not obstacles:
        raise ConversionError(f"{path}: no dynamic obstacle to replay")
    static = read_obstacles(
        root, dt_s, where, skip_bad=skip_bad, skipped=skipped, tag="staticObstacle"
    )
    table = obstacles_table(obstacles, dt_s, static, where)
    ids = [o.id for o in obstacles]
    if ego is None:
        ego_index, choice = moving_ego(table)
    elif ego in ids:
        ego_index, choice = ids.index(ego), "--ego"
    else:
        listed = ", ".join(str(i) for i in sorted(ids)[:10])
        more = " ..." if len(ids) > 10 else ""
        raise ConversionError(f"{path}: no dynamic obstacle with id {ego} (ids: {listed}{more})")
    metadata = {
        "dataset": "commonroad",
        "source_file": path.name,
        "scenario_id": root.get("benchmarkID", path.stem),
        "commonroad_version": root.get("commonRoadVersion", ""),
        "source": root.get("source", ""),
        "converter": CONVERTER,
        "converter_version": CONVERTER_VERSION,
        "ego_track": str(ids[ego_index]),
        "ego_choice": choice,
        "static_obstacles": str(len(static)),
        "traffic_lights": str(len(root.findall("trafficLight"))),
    }
    return build_scene(
        table,
        ego_index,
        read_lane_map(root, where),
        paths=paths,
        settings=settings,
        frame_period_s=dt_s,
        metadata=metadata,
        source=where,
        progress=progress,
        time_step=time_step,
        skip_bad=skip_bad,
        skipped=skipped,
    )
