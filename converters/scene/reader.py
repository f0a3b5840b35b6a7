"""The one scene reader: an MCAP scene file into :class:`risk.Frame` objects, lazily.

::

    from converters.scene.reader import open_scene, read_scene

    reader = open_scene("scene.mcap")      # checks the file, reads map, metadata, labels
    reader.map, reader.metadata, reader.labels, reader.frame_period_s, reader.n_frames
    for frame in reader.frames():          # decodes one frame at a time, in time order
        ...
    scene = read_scene("scene.mcap")       # everything at once, as a risk.Scene

Frames whose ego is missing. A frame's ``/agents`` message names the ego by id; the
scene's ego may be absent from a frame (a track that starts late or ends early) or
present but not valid. A :class:`risk.Frame` cannot exist without a valid ego, so:

- :meth:`SceneReader.entries` yields one :class:`FrameEntry` per stored frame, with
  ``frame=None`` for such frames (and their index, time and ego id), so that the replay
  engine can skip them with a warning and still count them;
- :meth:`SceneReader.frames` yields only frames; by default it raises
  :class:`~replay.errors.SceneFormatError` at a frame without its ego, and with
  ``skip_missing_ego=True`` it leaves such frames out (``entries`` says which).

Every problem with the file raises :class:`~replay.errors.SceneFormatError` with one line
saying what is wrong and what to do: not an MCAP file, a truncated file (with how many
frames are still intact), an MCAP file without the scene channels (naming the missing
ones), a scene without frames, or messages that disagree with the format.
"""

from __future__ import annotations

import errno
import math
import os
import pathlib
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Schema

from converters.scene import schema as sf
from converters.scene.errors import SceneFormatError
from outputs.atomic import target_kind
from outputs.memory import check_fits
from risk.errors import FrameError, RiskError
from risk.frame import MAX_CANDIDATES, Frame, Lane, LaneMap, MapLine, Scene
from risk.hindsight import Tracks, check_period, tracks_from_states

MCAP_MAGIC = b"\x89MCAP0\r\n"
_MAX_EXACT_MM = 2**53  # coordinates are exact integers of mm up to here

# What the mcap library raises on damaged input (it has no single base class for it).
_DAMAGE = (
    McapError, EOFError, struct.error, ValueError, IndexError, KeyError, OverflowError,
    zstandard.ZstdError,
)  # fmt: skip


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of the file, for ``replay inspect``."""

    topic: str
    schema_name: str
    message_encoding: str
    message_count: int


@dataclass(frozen=True, eq=False)
class FrameEntry:
    """One stored frame: ``frame`` is None when its ego is not a valid agent in it."""

    index: int  # position in the scene, 0-based
    t_s: float  # frame time, s
    ego_id: int  # the ego named by the /agents message
    n_agents: int  # agents stored in the frame (valid or not)
    frame: Frame | None


@dataclass(frozen=True)
class FrameStats:
    """Per-frame facts from the ``/agents`` channel alone (cheap: paths are not decoded).

    Every array has shape ``(F,)`` for ``F`` frames.
    """

    t_s: np.ndarray  # float64, s
    n_agents: np.ndarray  # int64, agents stored
    n_valid: np.ndarray  # int64, valid agents (ego included when present)
    ego_id: np.ndarray  # int64
    ego_present: np.ndarray  # bool, the ego is a valid agent of the frame


class SceneReader:
    """A scene file opened for reading; see the module docstring.

    Opening checks the file and reads its summary, map, metadata and labels; frames are
    decoded only while iterating (:meth:`frames`, :meth:`entries`), one at a time.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = pathlib.Path(path)
        kind = target_kind(self.path)
        if kind not in ("file", "missing"):  # (missing: open() says so)
            raise SceneFormatError(
                f"{self.path}: is {'a folder' if kind == 'folder' else 'a ' + kind}, not a"
                " scene file; give an .mcap file (a pipe would be read for ever)"
            )
        with open(self.path, "rb") as f:
            _check_magic(self.path, f)
            reader = SeekingReader(f, validate_crcs=True)
            summary = _summary_or_raise(self.path, f, reader)
            _check_section_crcs(self.path, f)
            self.library: str = _header_library(reader)
            self.channels: tuple[ChannelInfo, ...] = _channel_infos(summary)
            self._channel_ids = {c.topic: c.id for c in summary.channels.values()}
            _check_channels(self.path, summary)
            counts = (
                summary.statistics.channel_message_counts
                if summary.statistics
                else self._count_messages(reader)  # (Statistics are optional in MCAP)
            )
            if not summary.statistics:
                self.channels = _channel_infos(summary, counts)
            self.n_frames: int = int(counts.get(self._channel_ids[sf.TOPIC_AGENTS], 0))
            n_paths = int(counts.get(self._channel_ids[sf.TOPIC_PATHS], 0))
            if self.n_frames == 0:
                raise SceneFormatError(
                    f"{self.path}: the scene has no frames (channel /agents is empty);"
                    " convert the source again"
                )
            if n_paths != self.n_frames:
                raise SceneFormatError(
                    f"{self.path}: {self.n_frames} /agents messages but {n_paths} /paths"
                    " messages; every frame needs one of each (convert the source again)"
                )
            self.metadata: dict[str, str] = _read_metadata(self.path, reader)
            self.frame_period_s: float = _frame_period(self.path, self.metadata)
            self.map: LaneMap = self._read_map(reader)
            self.labels: dict[str, tuple[int, ...]] = self._read_labels(reader)
        #: Every frame's /agents columns (file order), kept by a complete entries() pass.
        self._agent_states: list[tuple[float, dict[str, np.ndarray]]] | None = None

    def _count_messages(self, reader: SeekingReader) -> dict[int, int]:
        """Messages per channel id, counted by reading them: for files without the
        optional Statistics record (other MCAP writers may leave it out)."""
        counts: dict[int, int] = {}
        try:
            for _, channel, _ in reader.iter_messages(log_time_order=False):
                counts[channel.id] = counts.get(channel.id, 0) + 1
        except _DAMAGE as exc:
            raise self._damaged(exc) from None
        return counts

    # ------------------------------------------------------------------ static parts
    def _single(self, reader: SeekingReader, topic: str) -> bytes | None:
        data = None
        try:
            for _, _, message in reader.iter_messages(topics=[topic]):
                if data is not None:
                    raise SceneFormatError(
                        f"{self.path}: channel {topic} must hold one message, it holds several"
                    )
                data = message.data
        except _DAMAGE as exc:
            raise self._damaged(exc) from None
        return data

    def _read_map(self, reader: SeekingReader) -> LaneMap:
        data = self._single(reader, sf.TOPIC_MAP)
        if data is None:
            raise SceneFormatError(f"{self.path}: channel /map has no message; convert again")
        message = self._parse(sf.Map, data, "/map")
        lanes = []
        for lane in message.lanes:
            if len(lane.x_mm) != len(lane.y_mm):
                raise SceneFormatError(
                    f"{self.path}: /map lane {lane.id}: x_mm and y_mm differ in length"
                )
            mm = np.column_stack(
                (np.array(lane.x_mm, dtype=np.int64), np.array(lane.y_mm, dtype=np.int64))
            )
            self._check_map_exact(f"lane {lane.id}", mm)
            line = mm / sf.MM_PER_M
            lanes.append(
                Lane(
                    id=int(lane.id),
                    centerline=line,
                    successors=tuple(int(s) for s in lane.successors),
                    kind=lane.kind,
                )
            )
        return LaneMap(lanes=tuple(lanes), lines=self._map_lines(message))

    def _map_lines(self, message: Any) -> tuple[MapLine, ...]:
        """``Map.lines`` (format version 2; a version 1 map has none)."""
        lines = []
        for line in message.lines:
            if len(line.x_mm) != len(line.y_mm):
                raise SceneFormatError(
                    f"{self.path}: /map line {line.id}: x_mm and y_mm differ in length"
                )
            points = np.column_stack(
                (np.array(line.x_mm, dtype=np.int64), np.array(line.y_mm, dtype=np.int64))
            )
            self._check_map_exact(f"line {line.id}", points)
            kind = line.kind if line.kind in sf.MAP_LINE_KINDS else "other"
            lines.append(
                MapLine(
                    id=int(line.id),
                    kind=kind,
                    points=points / sf.MM_PER_M,
                    closed=bool(line.closed),
                    style=line.style,
                )
            )
        return tuple(lines)

    def _read_labels(self, reader: SeekingReader) -> dict[str, tuple[int, ...]]:
        if sf.TOPIC_LABELS not in self._channel_ids:
            return {}
        data = self._single(reader, sf.TOPIC_LABELS)
        if data is None:
            return {}
        message = self._parse(sf.Labels, data, "/labels")
        return {label.name: tuple(int(i) for i in label.agent_ids) for label in message.labels}

    @property
    def ego_id(self) -> int | None:
        """The scene's ego id when every frame names the same one (else None)."""
        value = self.metadata.get("ego_id")
        return int(value) if value is not None and value.lstrip("-").isdigit() else None

    @property
    def duration_s(self) -> float:
        """Nominal duration: ``n_frames * frame_period_s``."""
        return self.n_frames * self.frame_period_s

    # ------------------------------------------------------------------ frames
    def _messages(self, topics: list[str]) -> Iterator[tuple[str, bytes]]:
        """(topic, payload) of the given channels, in log time order, one chunk at a time."""
        with open(self.path, "rb") as f:
            reader = SeekingReader(f, validate_crcs=True)
            try:
                for _, channel, message in reader.iter_messages(topics=topics):
                    yield channel.topic, message.data
            except _DAMAGE as exc:
                raise self._damaged(exc) from None

    def entries(self, *, any_ego: bool = False) -> Iterator[FrameEntry]:
        """Every stored frame in time order, ``frame=None`` where the ego is missing.

        With ``any_ego`` a frame whose recorded ego is missing is still decoded when any
        agent is valid, seen from the first valid agent (for replays that choose their own
        ego per frame, such as ``--ego all``); ``FrameEntry.ego_id`` stays the recorded one.
        """
        pending: dict[str, dict[int, Any]] = {sf.TOPIC_AGENTS: {}, sf.TOPIC_PATHS: {}}
        classes = {sf.TOPIC_AGENTS: sf.Agents, sf.TOPIC_PATHS: sf.Paths}
        # (place among the /agents messages, (t_s, the agents' columns)), for tracks()
        states: list[tuple[int, tuple[float, dict[str, np.ndarray]]]] = []
        order: dict[int, int] = {}  # frame index -> its place among the /agents messages
        previous: tuple[int, float] | None = None  # the last frame yielded: index, time
        for topic, data in self._messages([sf.TOPIC_AGENTS, sf.TOPIC_PATHS]):
            message = self._parse(classes[topic], data, topic)
            index = int(message.frame_index)
            if index in pending[topic]:
                raise SceneFormatError(f"{self.path}: frame {index} appears twice on {topic}")
            pending[topic][index] = message
            if topic == sf.TOPIC_AGENTS:
                order[index] = len(order)
            other = pending[sf.TOPIC_PATHS if topic == sf.TOPIC_AGENTS else sf.TOPIC_AGENTS]
            if index in other:
                agents = pending[sf.TOPIC_AGENTS].pop(index)
                paths = pending[sf.TOPIC_PATHS].pop(index)
                entry, columns = self._decode(agents, paths, any_ego=any_ego)
                t_s = float(agents.t_s)
                self._check_order(previous, index, t_s)
                previous = (index, t_s)
                states.append((order[index], (t_s, columns)))
                yield entry
        if len(states) > 1:  # (tracks are built after this pass: check before them)
            self._grid_index(np.array([t for _, (t, _) in states]), np.empty(0), 0.0)
        for topic, left in pending.items():
            if left:
                index = min(left)
                raise SceneFormatError(
                    f"{self.path}: frame {index} has a {topic} message but no matching"
                    f" {sf.TOPIC_PATHS if topic == sf.TOPIC_AGENTS else sf.TOPIC_AGENTS}"
                    " message (same frame_index); convert the source again"
                )
        if len(states) == self.n_frames:
            self._agent_states = [state for _, state in sorted(states, key=lambda s: s[0])]

    def frames(self, *, skip_missing_ego: bool = False) -> Iterator[Frame]:
        """Every frame in time order, decoded lazily.

        A frame whose ego is not a valid agent raises SceneFormatError, or is left out
        when ``skip_missing_ego`` is true (use :meth:`entries` to learn which).
        """
        for entry in self.entries():
            if entry.frame is not None:
                yield entry.frame
            elif not skip_missing_ego:
                raise SceneFormatError(
                    f"{self.path}: frame {entry.index} (t={entry.t_s:g} s): the ego (id"
                    f" {entry.ego_id}) is not a valid agent; skip such frames"
                    " (skip_missing_ego=True) or choose another ego"
                )

    def frame_stats(self) -> FrameStats:
        """Agent counts, times and ego presence of every frame, from ``/agents`` only."""
        rows = []
        previous: tuple[int, float] | None = None
        for _, data in self._messages([sf.TOPIC_AGENTS]):
            m = self._parse(sf.Agents, data, sf.TOPIC_AGENTS)
            self._check_order(previous, int(m.frame_index), float(m.t_s))
            previous = (int(m.frame_index), float(m.t_s))
            ids = np.array(m.ids, dtype=np.int64)
            valid = np.array(m.valid, dtype=bool)
            if valid.shape != ids.shape:
                raise self._bad_length(int(m.frame_index), "valid", valid.size, ids.size)
            ego_present = bool(valid[ids == m.ego_id].any())
            rows.append((m.t_s, ids.size, int(valid.sum()), m.ego_id, ego_present))
        t_s, n_agents, n_valid, ego_id, present = zip(*rows, strict=True)
        return FrameStats(
            t_s=np.array(t_s, dtype=np.float64),
            n_agents=np.array(n_agents, dtype=np.int64),
            n_valid=np.array(n_valid, dtype=np.int64),
            ego_id=np.array(ego_id, dtype=np.int64),
            ego_present=np.array(present, dtype=bool),
        )

    def tracks(self) -> Tracks:
        """Every recorded agent state of the scene as :class:`risk.hindsight.Tracks`
        (``/agents`` only: paths are not decoded). Frame ``k`` of the grid is the stored
        frame nearest ``t0 + k * frame_period_s``, ``t0`` the first frame's time.

        After a complete pass of :meth:`entries` the states it decoded are reused: reading
        the file again cost the demo's replay 34 ms of its 0.7 s."""
        states = self._agent_states
        if states is None:
            states = []
            for _, data in self._messages([sf.TOPIC_AGENTS]):
                m = self._parse(sf.Agents, data, sf.TOPIC_AGENTS)
                ids = np.array(m.ids, dtype=np.int64)
                columns = {"ids": ids, "valid": np.array(m.valid, dtype=bool)}
                for name in _TRACK_FIELDS[1:]:
                    values = np.array(getattr(m, name), dtype=np.int64)
                    if values.size != ids.size:
                        raise self._bad_length(
                            int(m.frame_index), f"/agents {name}", values.size, ids.size
                        )
                    columns[name] = values
                states.append((float(m.t_s), columns))
        cols: dict[str, list[np.ndarray]] = {k: [] for k in ("t", *_TRACK_FIELDS)}
        for t_s, columns in states:
            valid = columns["valid"]
            for name in _TRACK_FIELDS:
                cols[name].append(columns[name][valid])
            cols["t"].append(np.full(int(valid.sum()), t_s))
        flat = {k: np.concatenate(v) if v else np.empty(0) for k, v in cols.items()}
        t0 = float(min((c[0] for c in cols["t"] if c.size), default=0.0))
        grid = self._grid_index(np.array([t for t, _ in states]), flat["t"], t0)
        n_ids = np.unique(flat["ids"]).size
        check_fits(
            (int(grid.max(initial=-1)) + 1) * n_ids * _TRACK_BYTES,
            f"{self.path}: the hindsight grid ({int(grid.max(initial=-1)) + 1} frames of"
            f" {self.frame_period_s:g} s x {n_ids} agents)",
            "replay a shorter part of the scene, or convert it with fewer agents",
        )
        return tracks_from_states(
            grid,
            flat["ids"],
            flat["kinds"],
            np.column_stack((flat["x_mm"], flat["y_mm"])) / sf.MM_PER_M,
            flat["heading_urad"] / sf.URAD_PER_RAD,
            flat["length_mm"] / sf.MM_PER_M,
            flat["width_mm"] / sf.MM_PER_M,
            t0_s=t0,
            dt_s=self.frame_period_s,
        )

    def _grid_index(self, frame_t: np.ndarray, t: np.ndarray, t0: float) -> np.ndarray:
        """Grid frame of each time ``t``, after checking the metadata's frame period
        against the frames themselves: the grid is as long as the scene's time span
        over the period, so a period far below the frames' spacing (``1e-12``) would
        size it from one bad number (78 TiB), and is refused."""
        try:
            check_period(frame_t, self.frame_period_s)
        except RiskError as exc:
            raise SceneFormatError(f"{self.path}: metadata: {exc}") from None
        return np.rint((t - t0) / self.frame_period_s).astype(np.int64)

    def read(self, *, skip_missing_ego: bool = False) -> Scene:
        """The whole scene in memory.

        A scene file with one ego (``ego_id`` in its metadata) may hold frames where that
        ego is not observed (recorded scenes keep them, see ``converters.tracks``): they
        are kept, seen from their first valid agent, and the Scene's ``ego_id`` names the
        real ego, so the scene writes back unchanged. With ``skip_missing_ego`` they are
        left out. Without a scene ego, such a frame raises as in :meth:`frames`.
        """
        meta = {k: v for k, v in self.metadata.items() if k not in _STRUCTURAL_KEYS}
        ego_id = self.ego_id
        if ego_id is None or skip_missing_ego:
            frames = tuple(self.frames(skip_missing_ego=skip_missing_ego))
        else:
            frames = tuple(self._frames_any_ego())
        return Scene(
            map=self.map,
            frames=frames,
            frame_period_s=self.frame_period_s,
            metadata=meta,
            labels=dict(self.labels),
            ego_id=ego_id,
        )

    def _frames_any_ego(self) -> Iterator[Frame]:
        for entry in self.entries(any_ego=True):
            if entry.frame is None:
                raise SceneFormatError(
                    f"{self.path}: frame {entry.index} (t={entry.t_s:g} s) has no valid agent"
                )
            yield entry.frame

    # ------------------------------------------------------------------ decoding
    def _decode(
        self, agents: Any, paths: Any, *, any_ego: bool = False
    ) -> tuple[FrameEntry, dict[str, np.ndarray]]:
        """The frame entry, and the agents' columns as stored (for :meth:`tracks`)."""
        index = int(agents.frame_index)
        ids = np.array(agents.ids, dtype=np.int64)
        n = ids.size
        fields = {}
        for name in (
            "kinds",
            "x_mm",
            "y_mm",
            "heading_urad",
            "speed_mmps",
            "length_mm",
            "width_mm",
            "valid",
        ):
            values = np.array(getattr(agents, name), dtype=bool if name == "valid" else np.int64)
            if values.size != n:
                raise self._bad_length(index, f"/agents {name}", values.size, n)
            fields[name] = values
        for name in ("x_mm", "y_mm"):
            self._check_exact(index, f"/agents {name}", fields[name])
        valid = fields["valid"]
        ego_hits = np.flatnonzero((ids == agents.ego_id) & valid)
        if ego_hits.size == 0 and any_ego:
            ego_hits = np.flatnonzero(valid)
        stored = {"ids": ids, **fields}
        if ego_hits.size == 0:
            return FrameEntry(index, float(agents.t_s), int(agents.ego_id), n, frame=None), stored
        path_agent, path_points, padded = self._decode_paths(index, paths, n)
        try:
            frame = Frame.from_padded(
                ids=ids,
                kinds=fields["kinds"],
                xy=np.column_stack((fields["x_mm"], fields["y_mm"])) / sf.MM_PER_M,
                heading=fields["heading_urad"] / sf.URAD_PER_RAD,
                speed=fields["speed_mmps"] / sf.MMPS_PER_MPS,
                length=fields["length_mm"] / sf.MM_PER_M,
                width=fields["width_mm"] / sf.MM_PER_M,
                valid=valid,
                paths=padded,
                path_points=path_points,
                path_agent=path_agent,
                ego=int(ego_hits[0]),
                t=float(agents.t_s),
            )
        except FrameError as exc:
            raise SceneFormatError(
                f"{self.path}: frame {index} (t={agents.t_s:g} s): {exc}"
            ) from None
        return FrameEntry(index, float(agents.t_s), int(agents.ego_id), n, frame=frame), stored

    def _decode_paths(
        self, index: int, paths: Any, n: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(path_agent (M,), path_points (M,), padded paths (M, P, 2) in m)``."""
        candidates = np.array(paths.candidates, dtype=np.int64)
        if candidates.size != n:
            raise self._bad_length(index, "/paths candidates", candidates.size, n)
        if n and candidates.min() < 1:
            raise SceneFormatError(f"{self.path}: frame {index}: an agent has no path candidate")
        if n and candidates.max() > MAX_CANDIDATES:
            raise SceneFormatError(
                f"{self.path}: frame {index}: an agent has {int(candidates.max())} path"
                f" candidates, more than the {MAX_CANDIDATES} supported (every pair of"
                " candidates is compared); convert the source again with fewer"
                " (--max-candidates)"
            )
        points = np.array(paths.points, dtype=np.int64)
        if points.size != candidates.sum():
            raise self._bad_length(index, "/paths points", points.size, int(candidates.sum()))
        if points.size and points.min() < 1:
            raise SceneFormatError(f"{self.path}: frame {index}: a path candidate has no point")
        x = np.array(paths.x_mm, dtype=np.int64)
        y = np.array(paths.y_mm, dtype=np.int64)
        total = int(points.sum())
        self._check_exact(index, "/paths x_mm", x)
        self._check_exact(index, "/paths y_mm", y)
        if x.size != total or y.size != total:
            raise self._bad_length(index, "/paths x_mm/y_mm", min(x.size, y.size), total)
        # Gather every candidate into (M, P) slots; slots past a candidate's end repeat its
        # last point, which is the padding risk.Frame expects.
        width = int(points.max()) if points.size else 1
        check_fits(
            points.size * width * _PADDED_BYTES,
            f"{self.path}: frame {index}: {points.size} path candidates padded to the"
            f" longest ({width} points)",
            "the paths of one frame are padded to their longest; convert the source"
            " again with shorter paths (--horizon-s, --map-path-m)",
        )
        starts = np.cumsum(points) - points
        gather = starts[:, None] + np.minimum(np.arange(width)[None, :], points[:, None] - 1)
        padded = np.stack((x[gather], y[gather]), axis=-1) / sf.MM_PER_M
        return np.repeat(np.arange(n), candidates), points, padded

    # ------------------------------------------------------------------ errors
    def _parse(self, cls: Any, data: bytes, topic: str) -> Any:
        try:
            return cls.FromString(data)
        except Exception as exc:  # protobuf's DecodeError has no stable import path
            raise SceneFormatError(
                f"{self.path}: a {topic} message does not decode as {cls.DESCRIPTOR.full_name}"
                f" ({exc}); the file is damaged, convert the source again"
            ) from None

    def _check_exact(self, index: int, what: str, values: np.ndarray) -> None:
        """Coordinates beyond 2**53 mm cannot come from a converter (docs/scene-format.md)."""
        if values.size and np.abs(values).max() > _MAX_EXACT_MM:
            raise SceneFormatError(
                f"{self.path}: frame {index}: {what} holds a value beyond the format's"
                " 2**53 mm limit; the file is damaged, convert the source again"
            )

    def _check_order(self, previous: tuple[int, float] | None, index: int, t_s: float) -> None:
        """Frames must come in increasing index and time (both ``run`` and ``inspect``:
        times that ran backwards or repeated replayed with exit 0)."""
        if previous is None or not (math.isfinite(t_s) and math.isfinite(previous[1])):
            return  # (a time that is not finite is reported as such, by the frame's check)
        if index <= previous[0] or not t_s > previous[1]:
            raise SceneFormatError(
                f"{self.path}: frame {index} (t={t_s:g} s) follows frame {previous[0]}"
                f" (t={previous[1]:g} s); frame indices and times must increase through the"
                " file: convert the source again"
            )

    def _check_map_exact(self, what: str, values: np.ndarray) -> None:
        """A map point beyond 2**53 mm (2**62 mm converted and replayed without a word)."""
        if values.size and np.abs(values).max() > _MAX_EXACT_MM:
            raise SceneFormatError(
                f"{self.path}: /map {what} holds a point beyond the format's 2**53 mm limit;"
                " the file is damaged, convert the source again"
            )

    def _bad_length(self, index: int, what: str, got: int, expected: int) -> SceneFormatError:
        return SceneFormatError(
            f"{self.path}: frame {index}: {what} has {got} values, expected {expected};"
            " the writer broke the format (docs/scene-format.md)"
        )

    def _damaged(self, exc: BaseException) -> SceneFormatError:
        return SceneFormatError(
            f"{self.path}: damaged MCAP data ({type(exc).__name__}: {exc}); convert the source"
            " again"
        )


_TRACK_FIELDS = ("ids", "kinds", "x_mm", "y_mm", "heading_urad", "length_mm", "width_mm")
#: Bytes per (frame, agent) of :class:`risk.hindsight.Tracks` (xy, heading, length,
#: width float64, valid) and of the truth computed from it (about the same again).
_TRACK_BYTES = 2 * (8 * 5 + 1)
#: Bytes per padded path point while decoding (gather index, x and y, the float copy)
#: and in the models' working arrays (about the same again).
_PADDED_BYTES = 2 * (8 + 16 + 16)

_STRUCTURAL_KEYS = ("frame_period_s", "format_version", "ego_id")
"""Metadata keys that describe the file rather than the source (not in Scene.metadata)."""


def open_scene(path: str | os.PathLike[str]) -> SceneReader:
    """Open a scene file: checks it and reads everything but the frames."""
    return SceneReader(path)


def read_scene(path: str | os.PathLike[str], *, skip_missing_ego: bool = False) -> Scene:
    """Read a whole scene file into a :class:`risk.Scene` (all frames in memory)."""
    return SceneReader(path).read(skip_missing_ego=skip_missing_ego)


# ---------------------------------------------------------------------- file checks
def _check_magic(path: pathlib.Path, f: IO[bytes]) -> None:
    head = f.read(len(MCAP_MAGIC))
    f.seek(0)
    if head != MCAP_MAGIC:
        what = "it is empty" if not head else f"it starts with {head[:8]!r}"
        raise SceneFormatError(
            f"{path}: not an MCAP file ({what}); scene files come from `replay convert`"
        )


def _summary_or_raise(path: pathlib.Path, f: IO[bytes], reader: SeekingReader) -> Any:
    try:
        summary = reader.get_summary()
    except _DAMAGE:
        raise SceneFormatError(_truncated_message(path, f)) from None
    except OSError as exc:
        # A file shorter than the MCAP footer makes the reader seek before its start.
        if exc.errno != errno.EINVAL:
            raise
        raise SceneFormatError(_truncated_message(path, f)) from None
    if summary is None:
        raise SceneFormatError(
            f"{path}: the MCAP file has no summary section (channels, statistics, index);"
            " scene files need one: convert the source again"
        )
    return summary


def _truncated_message(path: pathlib.Path, f: IO[bytes]) -> str:
    """Say the file is cut short and, best effort, how many complete frames it holds."""
    size = f.seek(0, os.SEEK_END)
    f.seek(0)
    frames = 0
    try:
        topics: dict[str, int] = {}
        for _, channel, _ in NonSeekingReader(f).iter_messages(log_time_order=False):
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
            frames = min(topics.get(sf.TOPIC_AGENTS, 0), topics.get(sf.TOPIC_PATHS, 0))
    except (*_DAMAGE, OSError):
        pass  # the cut: everything before it has been counted
    return (
        f"{path}: truncated MCAP file ({size} bytes, no footer at the end);"
        f" {frames} complete frame(s) precede the cut. The copy or conversion was"
        " interrupted: copy or convert it again"
    )


_FOOTER = struct.Struct("<BQQQI")  # opcode, record length, summary start, offset start, crc
_DATA_END = struct.Struct("<BQI")  # opcode, record length, data section crc


def _check_section_crcs(path: pathlib.Path, f: IO[bytes]) -> None:
    """Check the CRCs of the data and summary sections (MCAP's DataEnd and Footer
    records), so that damage the reader would not notice (message indexes, statistics)
    is reported too. A CRC of 0 means "not computed" and is not checked."""
    size = f.seek(0, os.SEEK_END)
    footer_at = size - len(MCAP_MAGIC) - _FOOTER.size
    f.seek(footer_at)
    _, _, summary_start, _, summary_crc = _FOOTER.unpack(f.read(_FOOTER.size))
    damaged = SceneFormatError(
        f"{path}: damaged MCAP file (a section checksum does not match); copy or convert it again"
    )
    if summary_start and summary_crc:
        f.seek(summary_start)
        data = f.read(footer_at + _FOOTER.size - 4 - summary_start)
        if zlib.crc32(data) != summary_crc:
            raise damaged
    data_end_at = summary_start - _DATA_END.size if summary_start else 0
    if data_end_at > len(MCAP_MAGIC):
        f.seek(data_end_at)
        opcode, _, data_crc = _DATA_END.unpack(f.read(_DATA_END.size))
        if opcode == 0x0F and data_crc:
            f.seek(0)
            crc = 0
            remaining = data_end_at
            while remaining:
                block = f.read(min(remaining, 1 << 22))
                if not block:
                    break
                crc = zlib.crc32(block, crc)
                remaining -= len(block)
            if crc != data_crc:
                raise damaged
    f.seek(0)


def _header_library(reader: SeekingReader) -> str:
    try:
        return reader.get_header().library
    except _DAMAGE:
        return ""


def _channel_infos(summary: Any, counts: dict[int, int] | None = None) -> tuple[ChannelInfo, ...]:
    if counts is None:
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
    infos = []
    for channel in sorted(summary.channels.values(), key=lambda c: c.id):
        schema: Schema | None = summary.schemas.get(channel.schema_id)
        infos.append(
            ChannelInfo(
                topic=channel.topic,
                schema_name=schema.name if schema else "",
                message_encoding=channel.message_encoding,
                message_count=int(counts.get(channel.id, 0)),
            )
        )
    return tuple(infos)


def _check_channels(path: pathlib.Path, summary: Any) -> None:
    by_topic: dict[str, Channel] = {c.topic: c for c in summary.channels.values()}
    missing = [t for t in sf.REQUIRED_TOPICS if t not in by_topic]
    if missing:
        found = ", ".join(sorted(by_topic)) or "none"
        raise SceneFormatError(
            f"{path}: an MCAP file but not a riskreplay scene: channel(s) {', '.join(missing)}"
            f" missing (found: {found}); convert the source with `replay convert`"
        )
    for topic, expected in sf.TOPIC_SCHEMAS.items():
        channel = by_topic.get(topic)
        if channel is None:
            continue
        schema = summary.schemas.get(channel.schema_id)
        name = schema.name if schema else "no schema"
        if channel.message_encoding != "protobuf" or name != expected:
            raise SceneFormatError(
                f"{path}: channel {topic} carries {channel.message_encoding or 'unknown'}"
                f" messages of {name!r}, expected protobuf {expected!r}; not a riskreplay scene"
                " (or written by an incompatible version)"
            )


def _read_metadata(path: pathlib.Path, reader: SeekingReader) -> dict[str, str]:
    try:
        records = [m for m in reader.iter_metadata() if m.name == sf.METADATA_NAME]
    except _DAMAGE as exc:
        raise SceneFormatError(f"{path}: damaged metadata record ({exc}); convert again") from None
    if not records:
        raise SceneFormatError(
            f"{path}: no '{sf.METADATA_NAME}' metadata record (frame period, converter);"
            " convert the source again"
        )
    metadata = dict(records[0].metadata)
    version = metadata.get("format_version", "")
    if not version.isdigit():
        raise SceneFormatError(f"{path}: metadata has no valid format_version ({version!r})")
    if len(version) > 9 or int(version) > sf.FORMAT_VERSION:  # (int() refuses 4,300+ digits)
        raise SceneFormatError(
            f"{path}: written in scene format version {version[:12]}"
            f"{'...' if len(version) > 12 else ''}, this riskreplay reads up to"
            f" version {sf.FORMAT_VERSION}; upgrade riskreplay"
        )
    return metadata


def _frame_period(path: pathlib.Path, metadata: dict[str, str]) -> float:
    text = metadata.get("frame_period_s", "")
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise SceneFormatError(
            f"{path}: metadata frame_period_s must be a positive number of seconds, got {text!r}"
        )
    return value
