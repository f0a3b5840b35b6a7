"""A ``foxglove.SceneUpdate`` view of a scene, so that Foxglove shows the traffic.

MCAP's own viewer, Foxglove, draws messages of its well-known schemas in its 3D panel.
The scene channels (``/map``, ``/agents``, ``/paths``) carry riskreplay's own schemas,
which Foxglove lists field by field but cannot draw. The writer can add two channels
of ``foxglove.SceneUpdate`` messages (the ``foxglove-schemas-protobuf`` package's
classes; the schema is their ``FileDescriptorSet``):

- :data:`TOPIC_FOXGLOVE_MAP` (one message, log time 0): entity ``map``, one line strip per
  lane centre line and per map line (lane boundaries, road edges, closed crosswalks), in
  the recording's muted colours;
- :data:`TOPIC_FOXGLOVE_SCENE` (one message per frame, the frame's log time): entity
  ``agents``, one cube per valid agent (its length x width footprint, 1.5 m tall for
  vehicles, rotated by its heading), coloured by kind, the ego green. Each frame's
  message replaces the previous one.

Everything is in the scene's own metric frame, ``frame_id`` :data:`FRAME_ID`. riskreplay's
reader ignores these channels (other channels are allowed by the format).
"""

from __future__ import annotations

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor

from risk.frame import Frame, LaneMap

TOPIC_FOXGLOVE_MAP = "/foxglove/map"
TOPIC_FOXGLOVE_SCENE = "/foxglove/scene"
SCHEMA_NAME = "foxglove.SceneUpdate"
FRAME_ID = "map"

# RGBA in 0..1, as Foxglove's Color wants.
_LANE = (0.41, 0.41, 0.43, 1.0)
_LANE_OTHER = (0.27, 0.35, 0.43, 1.0)
_LINE_COLORS = {
    "lane_boundary": (0.30, 0.30, 0.33, 1.0),
    "road_edge": (0.47, 0.43, 0.35, 1.0),
    "crosswalk": (0.27, 0.37, 0.47, 1.0),
    "stop_line": (0.43, 0.27, 0.27, 1.0),
    "other": (0.24, 0.24, 0.24, 1.0),
}
_EGO = (0.16, 0.78, 0.35, 1.0)
# risk.Kind codes: vehicle, pedestrian, cyclist, other.
_KIND_COLORS = np.array(
    [(0.85, 0.85, 0.88, 0.9), (1.0, 0.6, 0.2, 0.9), (0.3, 0.7, 1.0, 0.9), (0.6, 0.6, 0.6, 0.9)]
)
_KIND_HEIGHTS = np.array([1.5, 1.8, 1.7, 1.0])  # m, only for the look of the cubes


def schema_data() -> bytes:
    """The serialised ``FileDescriptorSet`` of ``foxglove.SceneUpdate`` and its imports."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fds.file.add().ParseFromString(fd.serialized_pb)

    add(SceneUpdate.DESCRIPTOR.file)
    return fds.SerializeToString()


def _color(rgba) -> Color:
    r, g, b, a = (float(v) for v in rgba)
    return Color(r=r, g=g, b=b, a=a)


def _strip(points: np.ndarray, rgba, thickness_px: float) -> LinePrimitive:
    return LinePrimitive(
        type=LinePrimitive.LINE_STRIP,
        pose=Pose(orientation=Quaternion(w=1.0)),
        thickness=thickness_px,
        scale_invariant=True,
        points=[Point3(x=float(x), y=float(y)) for x, y in points],
        color=_color(rgba),
    )


def map_update(lane_map: LaneMap) -> SceneUpdate:
    """The map as one entity of line strips (lanes, then the other map lines)."""
    entity = SceneEntity(frame_id=FRAME_ID, id="map")
    for lane in lane_map.lanes:
        line = np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2)
        if len(line) >= 2:
            rgba = _LANE if lane.kind == "vehicle" else _LANE_OTHER
            entity.lines.append(_strip(line, rgba, 1.5))
    for ml in lane_map.lines:
        pts = np.asarray(ml.points, dtype=np.float64).reshape(-1, 2)
        if len(pts) >= 2:
            pts = np.vstack([pts, pts[:1]]) if ml.closed else pts
            entity.lines.append(_strip(pts, _LINE_COLORS.get(ml.kind, _LINE_COLORS["other"]), 1.0))
    return SceneUpdate(entities=[entity])


def frame_update(frame: Frame, t_ns: int) -> SceneUpdate:
    """One frame's agents as cubes (the ego green), in one entity that replaces the last."""
    valid = np.flatnonzero(frame.valid)
    kinds = np.clip(np.asarray(frame.kinds)[valid], 0, len(_KIND_COLORS) - 1)
    half = np.asarray(frame.heading)[valid] / 2.0
    height = _KIND_HEIGHTS[kinds]
    rgba = _KIND_COLORS[kinds].copy()
    rgba[valid == frame.ego] = _EGO
    xy = np.asarray(frame.xy)[valid]
    length = np.maximum(np.asarray(frame.length)[valid], 0.1)
    width = np.maximum(np.asarray(frame.width)[valid], 0.1)
    columns = zip(
        xy[:, 0].tolist(), xy[:, 1].tolist(), height.tolist(), np.sin(half).tolist(),
        np.cos(half).tolist(), length.tolist(), width.tolist(), rgba.tolist(), strict=True,
    )  # fmt: skip
    # Building protobuf messages needs one Python object per cube; the numbers are
    # prepared vectorised above.
    cubes = [
        CubePrimitive(
            pose=Pose(position=Vector3(x=x, y=y, z=h / 2.0), orientation=Quaternion(z=qz, w=qw)),
            size=Vector3(x=ln, y=wd, z=h),
            color=Color(r=c[0], g=c[1], b=c[2], a=c[3]),
        )
        for x, y, h, qz, qw, ln, wd, c in columns
    ]
    seconds, nanos = divmod(int(t_ns), 1_000_000_000)
    entity = SceneEntity(frame_id=FRAME_ID, id="agents", cubes=cubes)
    entity.timestamp.seconds, entity.timestamp.nanos = seconds, nanos
    return SceneUpdate(entities=[entity])
