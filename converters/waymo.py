"""Waymo Open Motion Dataset: ``Scenario`` records of a TFRecord file into scenes.

No TensorFlow and no Waymo package: :mod:`converters.tfrecord` reads the framing and
``waymo.proto`` (our own minimal definition, the fields below only) decodes each record;
its message classes are built at import time by :func:`converters.scene.schema.parse_proto`.

Mapping (docs/recorded-data.md has the full table):

- one scene per ``Scenario``; every track is an agent (id: Waymo's track id), valid where
  its state is ``valid``; time: ``timestamps_seconds``; frame period: their median step (to the ms);
- ego: the track ``sdc_track_index`` (the self-driving car);
- kinds: vehicle 1 -> vehicle, pedestrian 2 -> pedestrian, cyclist 3 -> cyclist,
  other 4 and unset 0 -> other;
- pose ``center_x``/``center_y`` (m), ``heading`` (rad), speed ``|(velocity_x, velocity_y)|``
  (m/s), ``length``/``width`` (m) per state;
- map: every ``lane`` map feature (centre line ``polyline``, successors ``exit_lanes``;
  kind ``bike`` for bike lanes, else ``vehicle``); road lines, edges, crosswalks and
  signals are not used;
- labels: ``objects_of_interest`` (track ids) and ``tracks_to_predict`` (their
  ``track_index`` turned into track ids).
"""

from __future__ import annotations

import os
import pathlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from google.protobuf import descriptor_pool, message_factory
from google.protobuf.message import DecodeError

from converters.clock import TimeStep
from converters.errors import ConversionError
from converters.lanegraph import PathSettings
from converters.map_lines import waymo_lines
from converters.scene.schema import parse_proto
from converters.tfrecord import Record, RecordError, read_records
from converters.tracks import Skipped, TrackTable, build_scene
from risk.frame import Kind, Lane, LaneMap, Scene

CONVERTER = "converters.waymo"
CONVERTER_VERSION = "1"
PROTO_PATH = pathlib.Path(__file__).with_name("waymo.proto")

OBJECT_KINDS: dict[int, Kind] = {
    0: Kind.OTHER,  # TYPE_UNSET
    1: Kind.VEHICLE,
    2: Kind.PEDESTRIAN,
    3: Kind.CYCLIST,
    4: Kind.OTHER,
}
BIKE_LANE_TYPE = 3


def _message_classes() -> dict[str, Any]:
    fdp = parse_proto(PROTO_PATH.read_text(encoding="utf-8"), filename="waymo.proto")
    pool = descriptor_pool.DescriptorPool()  # private: never clashes with other definitions
    pool.Add(fdp)
    return {
        m.name: message_factory.GetMessageClass(
            pool.FindMessageTypeByName(f"{fdp.package}.{m.name}")
        )
        for m in fdp.message_type
    }


_CLASSES = _message_classes()
Scenario = _CLASSES["Scenario"]
Track = _CLASSES["Track"]
ObjectState = _CLASSES["ObjectState"]
MapFeature = _CLASSES["MapFeature"]
LaneCenter = _CLASSES["LaneCenter"]
MapPoint = _CLASSES["MapPoint"]
RequiredPrediction = _CLASSES["RequiredPrediction"]


@dataclass
class ScenarioRecord:
    """One decoded record: the record's index in the file and the message."""

    index: int
    scenario: Any


def read_scenarios(
    path: str | os.PathLike, *, skip_bad: bool = False, skipped: Skipped | None = None
) -> Iterator[ScenarioRecord]:
    """Decode the ``Scenario`` records of a TFRecord file, in order.

    A corrupt record (CRC mismatch, truncation, undecodable payload) raises
    ConversionError naming the file and the record; with ``skip_bad`` it is recorded in
    ``skipped`` and reading goes on where the framing still allows.
    """
    for item in read_records(path):
        if isinstance(item, RecordError):
            if not skip_bad:
                raise item
            _note(skipped, str(item))
            continue
        try:
            yield ScenarioRecord(item.index, decode_scenario(item, path))
        except ConversionError as exc:
            if not skip_bad:
                raise
            _note(skipped, str(exc))


def _note(skipped: Skipped | None, message: str) -> None:
    if skipped is not None:
        skipped.add(message)


def decode_scenario(record: Record, path: str | os.PathLike = "input") -> Any:
    """Parse one record's payload as a ``Scenario``."""
    msg = Scenario()
    try:
        msg.ParseFromString(record.payload)
    except DecodeError as exc:
        raise ConversionError(
            f"{path}: record {record.index} (byte {record.offset}): not a Waymo Scenario ({exc})"
        ) from None
    return msg


def scenario_tracks(msg: Any, where: str) -> TrackTable:
    """The tracks of a ``Scenario`` as a :class:`TrackTable` (``where`` names it in errors)."""
    n_steps = len(msg.timestamps_seconds)
    if n_steps == 0 or len(msg.tracks) == 0:
        raise ConversionError(f"{where}: scenario has no timestamps or no tracks")
    fields = (
        "center_x", "center_y", "heading", "velocity_x", "velocity_y", "length", "width", "valid",
    )  # fmt: skip
    values = np.zeros((len(msg.tracks), n_steps, len(fields)))
    for i, track in enumerate(msg.tracks):
        if len(track.states) != n_steps:
            raise ConversionError(
                f"{where}: track {track.id} has {len(track.states)} states for {n_steps} timestamps"
            )
        values[i] = [
            (
                s.center_x,
                s.center_y,
                s.heading,
                s.velocity_x,
                s.velocity_y,
                s.length,
                s.width,
                s.valid,
            )
            for s in track.states
        ]
    v = values.transpose(1, 0, 2)  # (T, N, fields)
    kinds = np.array([OBJECT_KINDS.get(t.object_type, Kind.OTHER) for t in msg.tracks], np.int8)
    return TrackTable(
        ids=np.array([t.id for t in msg.tracks], dtype=np.int64),
        kinds=kinds,
        t_s=np.array(msg.timestamps_seconds, dtype=np.float64),
        xy=np.ascontiguousarray(v[:, :, 0:2]),
        heading=v[:, :, 2].copy(),
        speed=np.hypot(v[:, :, 3], v[:, :, 4]),
        length=v[:, :, 5].copy(),
        width=v[:, :, 6].copy(),
        valid=v[:, :, 7] > 0.5,
    )


def scenario_lane_map(msg: Any) -> LaneMap:
    """The lane centre lines of a ``Scenario`` (lanes without points are left out)."""
    lanes = []
    for feature in msg.map_features:
        if not feature.HasField("lane"):
            continue
        lane = feature.lane
        if len(lane.polyline) == 0:
            continue  # nothing to draw or match (a one-point lane is kept: the map is
            # the source's, and the lane graph ignores lanes without a direction)
        centerline = np.array([(p.x, p.y) for p in lane.polyline], dtype=np.float64)
        lanes.append(
            Lane(
                id=int(feature.id),
                centerline=centerline,
                successors=tuple(int(s) for s in lane.exit_lanes),
                kind="bike" if lane.type == BIKE_LANE_TYPE else "vehicle",
            )
        )
    return LaneMap(tuple(lanes), lines=waymo_lines(msg.map_features))


def scenario_labels(msg: Any, where: str) -> dict[str, tuple[int, ...]]:
    """``objects_of_interest`` and ``tracks_to_predict`` as track ids."""
    n = len(msg.tracks)
    bad = [r.track_index for r in msg.tracks_to_predict if not 0 <= r.track_index < n]
    if bad:
        raise ConversionError(
            f"{where}: tracks_to_predict index {bad[0]} is out of range ({n} tracks)"
        )
    return {
        "objects_of_interest": tuple(int(i) for i in msg.objects_of_interest),
        "tracks_to_predict": tuple(
            int(msg.tracks[r.track_index].id) for r in msg.tracks_to_predict
        ),
    }


def scenario_to_scene(
    msg: Any,
    *,
    source: str | os.PathLike,
    record: int = 0,
    paths: str = "map",
    settings: PathSettings | None = None,
    progress: bool = False,
    time_step: TimeStep = "auto",
    skip_bad: bool = False,
    skipped: Skipped | None = None,
) -> Scene:
    """One ``Scenario`` message as a scene (``source`` and ``record`` name it in errors)."""
    settings = settings or PathSettings()
    where = f"{source}: record {record} (scenario {msg.scenario_id or '?'})"
    table = scenario_tracks(msg, where)
    ego = int(msg.sdc_track_index)
    if not 0 <= ego < table.n_tracks:
        raise ConversionError(f"{where}: sdc_track_index {ego} is out of range")
    steps = np.diff(table.t_s)
    if steps.size and not (np.all(steps > 0) and np.isfinite(steps).all()):
        raise ConversionError(f"{where}: timestamps_seconds are not increasing")
    # Waymo's timestamps jitter around 10 Hz (0.09999, 0.10002 s): the nominal period is
    # their median rounded to the millisecond; frame times stay the recorded ones.
    period = (round(float(np.median(steps)), 3) or float(np.median(steps))) if steps.size else 0.1
    metadata = {
        "dataset": "waymo_open_motion",
        "source_file": os.path.basename(os.fspath(source)),
        "record": str(record),
        "scenario_id": str(msg.scenario_id),
        "converter": CONVERTER,
        "converter_version": CONVERTER_VERSION,
        "ego_track": str(int(table.ids[ego])),
        "ego_choice": "the self-driving car (sdc_track_index)",
        "current_time_index": str(int(msg.current_time_index)),
    }
    return build_scene(
        table,
        ego,
        scenario_lane_map(msg),
        paths=paths,
        settings=settings,
        frame_period_s=period,
        metadata=metadata,
        labels=scenario_labels(msg, where),
        source=where,
        progress=progress,
        time_step=time_step,
        skip_bad=skip_bad,
        skipped=skipped,
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
    """Every scenario of a Waymo TFRecord file as a scene, in file order."""
    for item in read_scenarios(path, skip_bad=skip_bad, skipped=skipped):
        try:
            yield scenario_to_scene(
                item.scenario,
                source=path,
                record=item.index,
                paths=paths,
                settings=settings,
                progress=progress,
                skip_bad=skip_bad,
                skipped=skipped,
            )
        except ConversionError as exc:
            if not skip_bad:
                raise
            _note(skipped, str(exc))
