"""The map lines around the lanes (scene format version 2): boundaries, edges, crosswalks.

One function per source, each returning ``MapLine``s that the source's converter adds to
its :class:`risk.LaneMap` (``LaneMap(lanes, lines=...)``). They are context for a
reviewer (the recording draws them below the agents); no risk model reads them.

- Waymo: ``road_line`` (lane boundaries, with their paint type), ``road_edge`` (road
  boundaries and medians) and ``crosswalk`` polygons.
- Argoverse 2 (motion-forecasting map JSON): each lane segment's left and right lane
  boundary (its ``mark_type`` as the style; a boundary shared by two segments is drawn
  once), and ``pedestrian_crossings`` (two edges each, drawn as one closed polygon).
  Boundaries of segments without a neighbour on that side are road edges.
- CommonRoad: each lanelet's left and right bound (``lineMarking`` as the style; a
  shared bound drawn once); a bound with no adjacent lanelet on its side is a road edge;
  lanelets of type ``crosswalk`` become crosswalk polygons.
- Lanelet2 (INTERACTION): the ``sources`` converter can hand its way bounds to
  :func:`dedupe_lines` with ``kind`` ``lane_boundary`` / ``road_edge`` and the OSM
  ``subtype`` (``solid``, ``dashed``) as the style.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from risk.frame import MapLine

WAYMO_ROAD_LINE_STYLES = {
    1: "broken_white",
    2: "solid_white",
    3: "solid_double_white",
    4: "broken_yellow",
    5: "broken_double_yellow",
    6: "solid_yellow",
    7: "solid_double_yellow",
    8: "passing_double_yellow",
}
WAYMO_ROAD_EDGE_STYLES = {1: "boundary", 2: "median"}


def _key(points: np.ndarray) -> bytes:
    """A polyline's identity to the centimetre, the same in either direction."""
    cm = np.rint(np.asarray(points, dtype=np.float64).reshape(-1, 2) * 100.0).astype(np.int64)
    return min(cm.tobytes(), cm[::-1].tobytes())


def dedupe_lines(lines: Iterable[MapLine]) -> tuple[MapLine, ...]:
    """Drop lines with fewer than two points and repeats of the same polyline.

    Two lines are the same when their points agree to the centimetre, in either
    direction (two neighbouring lanes share a boundary, often reversed). The first
    occurrence wins; ids stay the source's.
    """
    seen: set[bytes] = set()
    kept = []
    for line in lines:
        pts = np.asarray(line.points, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 2 or not np.isfinite(pts).all():
            continue
        key = _key(pts)
        if key in seen:
            continue
        seen.add(key)
        kept.append(line)
    return tuple(kept)


def waymo_lines(features: Iterable[Any]) -> tuple[MapLine, ...]:
    """Road lines, road edges and crosswalks of a Waymo ``Scenario``'s ``map_features``."""
    lines = []
    for f in features:
        if f.HasField("road_line"):
            pts, kind = f.road_line.polyline, "lane_boundary"
            style = WAYMO_ROAD_LINE_STYLES.get(f.road_line.type, "unknown")
        elif f.HasField("road_edge"):
            pts, kind = f.road_edge.polyline, "road_edge"
            style = WAYMO_ROAD_EDGE_STYLES.get(f.road_edge.type, "unknown")
        elif f.HasField("crosswalk"):
            pts, kind, style = f.crosswalk.polygon, "crosswalk", ""
        else:
            continue
        xy = np.array([(p.x, p.y) for p in pts], dtype=np.float64).reshape(-1, 2)
        lines.append(MapLine(int(f.id), kind, xy, closed=kind == "crosswalk", style=style))
    return dedupe_lines(lines)


def _xy(points: Any) -> np.ndarray:
    return np.array([(p["x"], p["y"]) for p in points or ()], dtype=np.float64).reshape(-1, 2)


def av2_lines(data: Mapping[str, Any]) -> tuple[MapLine, ...]:
    """Lane boundaries and pedestrian crossings of an Argoverse 2 map JSON (parsed).

    Raises ``KeyError`` / ``TypeError`` / ``ValueError`` on a malformed map, like the
    converter's own lane reading (which reports them as one ``ConversionError``).
    """
    lines: list[MapLine] = []
    segments = data.get("lane_segments") or {}
    for key, seg in segments.items():
        sid = int(seg.get("id", key))
        for side, neighbour in (("left", "left_neighbor_id"), ("right", "right_neighbor_id")):
            bound = seg.get(f"{side}_lane_boundary")
            if not bound:
                continue
            kind = "lane_boundary" if seg.get(neighbour) is not None else "road_edge"
            style = str(seg.get(f"{side}_lane_mark_type", "")).lower()
            lines.append(MapLine(sid, kind, _xy(bound), style=style))
    for key, crossing in (data.get("pedestrian_crossings") or {}).items():
        e1, e2 = _xy(crossing["edge1"]), _xy(crossing["edge2"])
        polygon = np.concatenate([e1, e2[::-1]])
        lines.append(MapLine(int(crossing.get("id", key)), "crosswalk", polygon, closed=True))
    return dedupe_lines(lines)


def commonroad_lines(root: ET.Element) -> tuple[MapLine, ...]:
    """Lanelet bounds and crosswalk lanelets of a CommonRoad XML root element.

    Raises ``ValueError`` on a non-numeric id or coordinate.
    """
    lines: list[MapLine] = []
    for elem in root.findall("lanelet"):
        lid = int(elem.get("id", ""))
        bounds = {
            side: np.array(
                [
                    (float(p.findtext("x", "nan")), float(p.findtext("y", "nan")))
                    for p in elem.findall(f"{side}Bound/point")
                ],
                dtype=np.float64,
            ).reshape(-1, 2)
            for side in ("left", "right")
        }
        types = {(t.text or "").strip() for t in elem.findall("laneletType")}
        if "crosswalk" in types:
            polygon = np.concatenate([bounds["left"], bounds["right"][::-1]])
            lines.append(MapLine(lid, "crosswalk", polygon, closed=True))
            continue
        for side, adjacent in (("left", "adjacentLeft"), ("right", "adjacentRight")):
            kind = "lane_boundary" if elem.find(adjacent) is not None else "road_edge"
            style = (elem.findtext(f"{side}Bound/lineMarking") or "").strip()
            lines.append(MapLine(lid, kind, bounds[side], style=style))
    # A bound that two lanelets share lies between lanes, whatever the adjacency tags say
    # (recorded maps such as SinD's often leave them out).
    keys = [_key(ln.points) for ln in lines]
    shared = {k for k in keys if keys.count(k) > 1}
    lines = [
        dataclasses.replace(ln, kind="lane_boundary")
        if ln.kind == "road_edge" and k in shared
        else ln
        for ln, k in zip(lines, keys, strict=True)
    ]
    return dedupe_lines(lines)
