"""The one MCAP scene writer: a :class:`risk.Scene` into a self-describing ``.mcap`` file.

Layout (``docs/scene-format.md`` has the full specification):

- ``/map``: one :class:`~converters.scene.schema.Map` message (log time 0);
- ``/agents``: one ``Agents`` message per frame;
- ``/paths``: one ``Paths`` message per frame (every agent's forward path candidates);
- ``/labels``: one ``Labels`` message, only when the scene has labels;
- a metadata record named ``scene``: ``scene.metadata`` plus ``frame_period_s``,
  ``format_version``, ``converter``, ``converter_version`` and, when every frame has the
  same ego, ``ego_id``.

Paths go out with every frame rather than only when they change. A path starts at its
agent's current position, so it changes every frame; what repeats is the route's
vertices ahead, frame after frame, and zstd removes those repeats within a chunk.
Measured (``benchmarks/bench_scene_io.py --encodings``, synthetic intersection, 100
agents x 100 frames): ``/paths`` compresses to 36 kB of the 101 kB file, against 1.3 kB
for one frame's paths, so "only on change" could save at most a third of a small file,
while per-frame paths keep the reader stateless (any frame decodes from its own two
messages, which keeps seeking trivial).

Numbers are stored as integers in fixed units (mm, mm/s, micro-radians; see
:mod:`converters.scene.schema`), i.e. rounded to the nearest step. Integers keep the
same absolute resolution at any coordinate magnitude (float32 has a 6 cm step at 1000
km, which UTM-style map coordinates reach), and compress better than float32 (same
benchmark: 90 kB against 124 kB) because their low bits are not noise. Rounding is
idempotent: writing what was read back writes the same bytes.

Writing is atomic: the file is built under a temporary name in the target directory
and renamed over the target only when complete; any exception (including Ctrl-C)
removes the temporary file, so an interrupted conversion leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import math
import os
import pathlib
from collections.abc import Iterable, Mapping
from types import TracebackType

import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from tqdm import tqdm

from converters.errors import ConversionError
from converters.scene import foxglove as fg
from converters.scene import schema as sf
from outputs.atomic import commit, temp_path_beside
from risk.frame import Frame, LaneMap, Scene

CHUNK_SIZE_BYTES = 1024 * 1024
"""Uncompressed chunk size (mcap's default). Chunk size hardly changes the file: a
300-frame, 100-agent synthetic scene measured 266 761 bytes with 1 MiB chunks and
266 379 with 4 MiB (``benchmarks/bench_scene_io.py --duration 30 --arm-length 400
--chunk-mib 4``); smaller chunks let a streaming reader reach the first frame sooner."""

# Integers above 2**53 lose exactness on the way back to float64; no real coordinate
# comes near (2**53 mm is 9e9 km), so anything beyond is a converter bug.
_MAX_EXACT = float(2**53)

RESERVED_METADATA_KEYS = ("frame_period_s", "format_version", "ego_id")
"""Metadata keys the writer sets itself (a scene's own values for them are replaced)."""


def _version() -> str:
    try:
        return importlib.metadata.version("riskreplay")
    except importlib.metadata.PackageNotFoundError:  # a source tree without installation
        return "0.0.0+unknown"


# ---------------------------------------------------------------------- encoding
def quantise(values: np.ndarray, steps_per_unit: float, what: str) -> np.ndarray:
    """Round SI values to the format's integer steps, shape preserved, int64."""
    scaled = np.rint(np.asarray(values, dtype=np.float64) * steps_per_unit)
    if scaled.size and not np.abs(scaled).max() < _MAX_EXACT:
        raise ConversionError(f"{what}: value out of range for the scene format (|x| too large)")
    return scaled.astype(np.int64)


def encode_frame(
    frame: Frame, index: int, *, ego_id: int | None = None
) -> tuple[sf.Agents, sf.Paths]:
    """The ``/agents`` and ``/paths`` messages of one frame (vectorised over agents).

    ``ego_id`` overrides the ego recorded in the message (default ``frame.ego_id``); see
    :meth:`SceneWriter.add_frame`.
    """
    xy_mm = quantise(frame.xy, sf.MM_PER_M, "xy")
    agents = sf.Agents(
        frame_index=index,
        t_s=frame.t,
        ego_id=frame.ego_id if ego_id is None else int(ego_id),
        ids=frame.ids.tolist(),
        kinds=frame.kinds.tolist(),
        x_mm=xy_mm[:, 0].tolist(),
        y_mm=xy_mm[:, 1].tolist(),
        heading_urad=quantise(frame.heading, sf.URAD_PER_RAD, "heading").tolist(),
        speed_mmps=quantise(frame.speed, sf.MMPS_PER_MPS, "speed").tolist(),
        length_mm=quantise(frame.length, sf.MM_PER_M, "length").tolist(),
        width_mm=quantise(frame.width, sf.MM_PER_M, "width").tolist(),
        valid=frame.valid.tolist(),
    )
    # Real points only: padding is the reader's business (it re-pads to the longest).
    real = np.arange(frame.paths.shape[1])[None, :] < frame.path_points[:, None]
    points_mm = quantise(frame.paths[real], sf.MM_PER_M, "paths")
    paths = sf.Paths(
        frame_index=index,
        t_s=frame.t,
        candidates=np.bincount(frame.path_agent, minlength=frame.n_agents).tolist(),
        points=frame.path_points.tolist(),
        x_mm=points_mm[:, 0].tolist(),
        y_mm=points_mm[:, 1].tolist(),
    )
    return agents, paths


def encode_map(lane_map: LaneMap) -> sf.Map:
    """The ``/map`` message: every lane's centre line (mm) and successor ids, and the
    other map lines (lane boundaries, road edges, crosswalks; format version 2)."""
    message = sf.Map()
    for lane in lane_map.lanes:
        centre = np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2)
        if not np.isfinite(centre).all():
            raise ConversionError(f"lane {lane.id}: centre line has a non-finite point")
        mm = quantise(centre, sf.MM_PER_M, f"lane {lane.id}")
        message.lanes.add(
            id=int(lane.id),
            kind=str(lane.kind),
            x_mm=mm[:, 0].tolist(),
            y_mm=mm[:, 1].tolist(),
            successors=[int(s) for s in lane.successors],
        )
    for line in lane_map.lines:
        pts = np.asarray(line.points, dtype=np.float64).reshape(-1, 2)
        if not np.isfinite(pts).all():
            raise ConversionError(f"map line {line.id}: a non-finite point")
        if line.kind not in sf.MAP_LINE_KINDS:
            raise ConversionError(
                f"map line {line.id}: kind {line.kind!r} is not one of {', '.join(sf.MAP_LINE_KINDS)}"
            )
        mm = quantise(pts, sf.MM_PER_M, f"map line {line.id}")
        message.lines.add(
            id=int(line.id),
            kind=line.kind,
            style=str(line.style),
            x_mm=mm[:, 0].tolist(),
            y_mm=mm[:, 1].tolist(),
            closed=bool(line.closed),
        )
    return message


def encode_labels(labels: Mapping[str, Iterable[int]]) -> sf.Labels:
    """The ``/labels`` message: one named agent-id list per label."""
    message = sf.Labels()
    for name, ids in labels.items():
        message.labels.add(name=str(name), agent_ids=[int(i) for i in ids])
    return message


def time_ns(t_s: float) -> int:
    """MCAP log time of a frame: its time in integer nanoseconds, clamped at 0.

    MCAP times are unsigned; a source with negative frame times keeps its exact times in
    the messages (``t_s``). Messages with equal log times keep their file order, which is
    frame order, so readers still see the frames in time order.
    """
    return max(0, round(t_s * 1e9))


# ---------------------------------------------------------------------- writer
class SceneWriter:
    """Streams frames into a scene file; the target appears only on :meth:`close`.

    Use as a context manager (an exception inside the block discards the file)::

        with SceneWriter("scene.mcap", lane_map, frame_period_s=0.1, metadata=meta) as w:
            for frame in frames:
                w.add_frame(frame)
        # scene.mcap exists now

    Converters that hold a whole :class:`risk.Scene` call :func:`write_scene` instead.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        lane_map: LaneMap,
        *,
        frame_period_s: float,
        metadata: Mapping[str, str] | None = None,
        labels: Mapping[str, Iterable[int]] | None = None,
        foxglove: bool = False,
    ) -> None:
        if not (math.isfinite(frame_period_s) and frame_period_s > 0):
            raise ConversionError(
                f"frame period must be a positive number of seconds, got {frame_period_s}"
            )
        self.path = pathlib.Path(path)
        self._metadata = _check_metadata(metadata or {})
        self._frame_period_s = float(frame_period_s)
        self._n_frames = 0
        self._last_t: float | None = None
        self._ego_ids: set[int] = set()
        self._closed = False
        self._tmp = temp_path_beside(self.path)
        self._file = self._tmp.open("wb")
        try:
            self._writer = McapWriter(
                self._file, chunk_size=CHUNK_SIZE_BYTES, compression=CompressionType.ZSTD
            )
            self._writer.start(profile="", library=f"riskreplay {_version()}")
            schema_data = sf.file_descriptor_set()
            self._channels: dict[str, int] = {}
            for topic, schema_name in sf.TOPIC_SCHEMAS.items():
                if topic == sf.TOPIC_LABELS and not labels:
                    continue
                schema_id = self._writer.register_schema(
                    name=schema_name, encoding=SchemaEncoding.Protobuf, data=schema_data
                )
                self._channels[topic] = self._writer.register_channel(
                    topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=schema_id
                )
            if foxglove:
                fox_schema = self._writer.register_schema(
                    name=fg.SCHEMA_NAME, encoding=SchemaEncoding.Protobuf, data=fg.schema_data()
                )
                for topic in (fg.TOPIC_FOXGLOVE_MAP, fg.TOPIC_FOXGLOVE_SCENE):
                    self._channels[topic] = self._writer.register_channel(
                        topic=topic, message_encoding=MessageEncoding.Protobuf, schema_id=fox_schema
                    )
            self._foxglove = foxglove
            try:
                map_message = encode_map(lane_map)
            except ConversionError as exc:  # ("lane 0: ..." alone named no file, issue 36)
                raise ConversionError(f"{self.path}: the map: {exc}") from None
            self._write(sf.TOPIC_MAP, map_message, 0)
            if labels:
                self._write(sf.TOPIC_LABELS, encode_labels(labels), 0)
            if foxglove:
                self._write(fg.TOPIC_FOXGLOVE_MAP, fg.map_update(lane_map), 0)
        except BaseException:
            self.abort()
            raise

    def _write(self, topic: str, message: object, log_time: int) -> None:
        data = message.SerializeToString()  # type: ignore[attr-defined]
        self._writer.add_message(
            channel_id=self._channels[topic], log_time=log_time, data=data, publish_time=log_time
        )

    @property
    def n_frames(self) -> int:
        return self._n_frames

    def add_frame(self, frame: Frame, *, ego_id: int | None = None) -> None:
        """Append one frame; frame times must increase strictly.

        ``ego_id`` records a different ego than ``frame.ego_id``: for a converter that
        keeps a frame in which the scene's ego is not observed (``frame`` then needs some
        valid agent as its ego index; readers report such frames as ego-less).
        """
        if self._closed:
            raise ConversionError("the scene writer is already closed")
        if self._last_t is not None and not frame.t > self._last_t:
            raise ConversionError(
                f"frame {self._n_frames}: time {frame.t:g} s does not follow {self._last_t:g} s;"
                " frames must be in strictly increasing time order"
            )
        agents, paths = encode_frame(frame, self._n_frames, ego_id=ego_id)
        log_time = time_ns(frame.t)
        self._write(sf.TOPIC_AGENTS, agents, log_time)
        self._write(sf.TOPIC_PATHS, paths, log_time)
        if self._foxglove:
            self._write(fg.TOPIC_FOXGLOVE_SCENE, fg.frame_update(frame, log_time), log_time)
        self._ego_ids.add(int(agents.ego_id))
        self._last_t = frame.t
        self._n_frames += 1

    def close(self) -> pathlib.Path:
        """Finish the file (metadata, index, summary) and move it into place."""
        if self._closed:
            return self.path
        try:
            if self._n_frames == 0:
                raise ConversionError(f"{self.path}: a scene needs at least one frame; got none")
            self._writer.add_metadata(sf.METADATA_NAME, self._final_metadata())
            self._writer.finish()
            self._file.close()
            commit(self._tmp, self.path)
        except BaseException:
            self.abort()
            raise
        self._closed = True
        return self.path

    def abort(self) -> None:
        """Discard the partial file (idempotent)."""
        self._closed = True
        with contextlib.suppress(Exception):
            self._file.close()
        with contextlib.suppress(FileNotFoundError):
            self._tmp.unlink()

    def _final_metadata(self) -> dict[str, str]:
        meta = {k: v for k, v in self._metadata.items() if k not in RESERVED_METADATA_KEYS}
        meta.setdefault("converter", "unknown")
        meta.setdefault("converter_version", _version())
        meta["frame_period_s"] = repr(self._frame_period_s)
        meta["format_version"] = str(sf.FORMAT_VERSION)
        if len(self._ego_ids) == 1:
            meta["ego_id"] = str(next(iter(self._ego_ids)))
        return meta

    def __enter__(self) -> SceneWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _check_metadata(metadata: Mapping[str, str]) -> dict[str, str]:
    for key, value in metadata.items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise ConversionError(
                f"scene metadata must map strings to strings; got {key!r}: {value!r}"
                " (format numbers with str())"
            )
    return dict(metadata)


def write_scene(
    path: str | os.PathLike[str], scene: Scene, *, progress: bool = False, foxglove: bool = False
) -> pathlib.Path:
    """Write ``scene`` to ``path`` atomically; returns the path.

    ``foxglove``: also write the ``foxglove.SceneUpdate`` channels
    (:mod:`converters.scene.foxglove`) so that Foxglove draws the traffic.

    Raises :class:`~converters.errors.ConversionError` for a scene the format cannot hold
    (no frames, frames out of time order, non-string metadata) and ``OSError`` for file
    system trouble; either way no file (and no temporary file) is left behind.
    """
    if len(scene.frames) == 0:
        raise ConversionError(f"{path}: a scene needs at least one frame; got none")
    frames: Iterable[Frame] = scene.frames
    if progress:
        frames = tqdm(
            frames, total=len(scene.frames), desc="writing", unit="frame", leave=False,
            disable=None,  # (only on a terminal: bars in a pipe or log leave \r fragments)
        )  # fmt: skip
    with SceneWriter(
        path,
        scene.map,
        frame_period_s=scene.frame_period_s,
        metadata=scene.metadata,
        labels=scene.labels,
        foxglove=foxglove,
    ) as writer:
        for frame in frames:
            writer.add_frame(frame, ego_id=scene.ego_id)
    return writer.path
