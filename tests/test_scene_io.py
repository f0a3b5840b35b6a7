"""The MCAP scene format: round trip, quantisation, self-description, bad input, atomicity."""

from __future__ import annotations

import pathlib
import shutil
import subprocess

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_protobuf.decoder import DecoderFactory

from converters.errors import ConversionError
from converters.scene import schema as sf
from converters.scene import writer as mcap_io
from converters.scene.errors import SceneFormatError
from converters.scene.reader import open_scene, read_scene
from converters.scene.writer import SceneWriter, write_scene
from risk import Frame, Kind, Lane, LaneMap, Scene

# ---------------------------------------------------------------------- fixtures


def q(values, step=1000.0):
    """The format's rounding, written independently of the writer."""
    return np.round(np.asarray(values, dtype=np.float64) * step) / step


def small_map() -> LaneMap:
    return LaneMap(
        (
            Lane(7, np.array([[0.0, 0.0], [50.0, 0.0004]]), (8, 9)),
            Lane(8, np.array([[50.0, 0.0], [100.0, 0.0], [120.0, 3.25]]), ()),
            Lane(9, np.array([[50.0, 0.0], [60.0, -10.0]]), (), kind="bike"),
        )
    )


def frame_a() -> Frame:
    """Three agents, one with two candidates, one invalid; ego is the second agent."""
    return Frame.from_arrays(
        xy=np.array([[1.0004, 2.0], [10.0, -3.1234567], [0.0, 0.0]]),
        heading=np.array([0.1, -3.0000004, 0.0]),
        speed=np.array([5.0, 12.3456, 0.0]),
        length=np.array([4.5, 4.8, 0.0]),
        width=np.array([1.8, 2.0, 0.0]),
        paths=[
            np.array([[1.0004, 2.0], [30.0, 2.0]]),
            [
                np.array([[10.0, -3.1234567], [40.0, -3.0], [60.0, 5.0]]),
                np.array([[10.0, -3.1234567], [10.0, 30.0]]),
            ],
            np.array([[0.0, 0.0]]),
        ],
        ego=1,
        ids=[101, 5, 77],
        kinds=["vehicle", "cyclist", "pedestrian"],
        valid=[True, True, False],
        t=0.0,
    )


def frame_b() -> Frame:
    """A later frame: agent 101 left, agent 300 appeared (the agent set changes)."""
    return Frame.from_arrays(
        xy=np.array([[11.0, -3.0], [-20.0, 4.0]]),
        heading=np.array([0.2, np.pi]),
        speed=np.array([12.0, 3.0]),
        length=np.array([4.8, 0.6]),
        width=np.array([2.0, 0.6]),
        paths=[np.array([[11.0, -3.0], [40.0, -3.0]]), np.array([[-20.0, 4.0], [-25.0, 4.0]])],
        ego=0,
        ids=[5, 300],
        kinds=["cyclist", "pedestrian"],
        t=0.1,
    )


def small_scene() -> Scene:
    return Scene(
        map=small_map(),
        frames=(frame_a(), frame_b()),
        frame_period_s=0.1,
        metadata={"dataset": "unit-test", "scenario_id": "abc", "converter": "tests"},
        labels={"tracks_to_predict": (5, 300), "objects_of_interest": ()},
    )


def assert_frame_quantised(got: Frame, want: Frame) -> None:
    """``got`` equals ``want`` after the format's documented rounding, exactly."""
    np.testing.assert_array_equal(got.ids, want.ids)
    np.testing.assert_array_equal(got.kinds, want.kinds)
    np.testing.assert_array_equal(got.valid, want.valid)
    np.testing.assert_array_equal(got.xy, q(want.xy))
    np.testing.assert_array_equal(got.heading, q(want.heading, 1e6))
    np.testing.assert_array_equal(got.speed, q(want.speed))
    np.testing.assert_array_equal(got.length, q(want.length))
    np.testing.assert_array_equal(got.width, q(want.width))
    np.testing.assert_array_equal(got.path_agent, want.path_agent)
    np.testing.assert_array_equal(got.path_points, want.path_points)
    # Padding is not stored: the reader pads to the longest candidate of the frame.
    assert got.paths.shape[1] == want.path_points.max()
    np.testing.assert_array_equal(got.paths, q(want.paths[:, : got.paths.shape[1]]))
    assert got.ego == want.ego
    assert got.t == want.t


# ---------------------------------------------------------------------- round trip


def test_round_trip_equals_quantised_input(tmp_path):
    scene = small_scene()
    path = write_scene(tmp_path / "s.mcap", scene)
    assert path == tmp_path / "s.mcap"
    back = read_scene(path)
    assert len(back.frames) == 2
    for got, want in zip(back.frames, scene.frames, strict=True):
        assert_frame_quantised(got, want)
    assert back.frames[0].n_agents == 3 and back.frames[1].n_agents == 2
    assert list(back.frames[0].path_agent) == [0, 1, 1, 2]
    assert back.frame_period_s == 0.1
    assert back.labels == {"tracks_to_predict": (5, 300), "objects_of_interest": ()}
    assert back.metadata["dataset"] == "unit-test"
    assert back.metadata["converter"] == "tests"
    assert "converter_version" in back.metadata
    assert "frame_period_s" not in back.metadata  # structural keys stay in the file
    lanes = back.map.by_id()
    assert sorted(lanes) == [7, 8, 9]
    assert lanes[7].successors == (8, 9)
    assert lanes[9].kind == "bike"
    np.testing.assert_array_equal(lanes[7].centerline, [[0.0, 0.0], [50.0, 0.0]])
    np.testing.assert_array_equal(lanes[8].centerline, small_map().lanes[1].centerline)


def test_write_read_write_is_a_byte_identical_fixed_point(tmp_path):
    first = write_scene(tmp_path / "a.mcap", small_scene())
    second = write_scene(tmp_path / "b.mcap", read_scene(first))
    assert first.read_bytes() == second.read_bytes()


def test_negative_frame_times_keep_their_order(tmp_path):
    frames = [Frame(**{**frame_b()._fields(), "t": t}) for t in (-0.3, -0.2, -0.1, 0.0, 0.1)]
    back = read_scene(write_scene(tmp_path / "n.mcap", Scene(small_map(), frames, 0.1)))
    assert [f.t for f in back.frames] == [-0.3, -0.2, -0.1, 0.0, 0.1]


def test_reader_metadata_channels_and_counts(tmp_path):
    path = write_scene(tmp_path / "s.mcap", small_scene())
    reader = open_scene(path)
    assert reader.n_frames == 2
    assert reader.frame_period_s == 0.1
    assert reader.metadata["format_version"] == str(sf.FORMAT_VERSION)
    assert reader.metadata["frame_period_s"] == "0.1"
    assert reader.ego_id == 5
    topics = {c.topic: c for c in reader.channels}
    assert set(topics) == {"/map", "/agents", "/paths", "/labels"}
    assert topics["/agents"].message_count == 2
    assert topics["/agents"].schema_name == "riskreplay.scene.v1.Agents"
    assert topics["/map"].message_encoding == "protobuf"
    stats = reader.frame_stats()
    assert list(stats.n_agents) == [3, 2]
    assert list(stats.n_valid) == [2, 2]
    assert list(stats.ego_present) == [True, True]
    np.testing.assert_array_equal(stats.t_s, [0.0, 0.1])


def test_no_labels_channel_when_scene_has_none(tmp_path):
    scene = small_scene()
    bare = Scene(scene.map, scene.frames, 0.1)
    reader = open_scene(write_scene(tmp_path / "s.mcap", bare))
    assert "/labels" not in {c.topic for c in reader.channels}
    assert reader.labels == {}
    assert reader.metadata["converter"] == "unknown"


def test_frames_are_lazy_and_restartable(tmp_path):
    reader = open_scene(write_scene(tmp_path / "s.mcap", small_scene()))
    it = reader.frames()
    first = next(it)
    assert first.t == 0.0 and first.ego_id == 5
    assert [f.t for f in reader.frames()] == [0.0, 0.1]  # a second pass starts over


def test_messages_decode_without_our_code(tmp_path):
    """Self-describing: a generic protobuf decoder reads the embedded schema."""
    path = write_scene(tmp_path / "s.mcap", small_scene())
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = {}
        for _, channel, _, msg in reader.iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(msg)
        summary = reader.get_summary()
    assert summary is not None and len(summary.chunk_indexes) >= 1
    assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
    agents = decoded["/agents"][0]
    assert type(agents) is not sf.Agents  # built from the file's schema, not ours
    assert list(agents.ids) == [101, 5, 77]
    assert list(agents.x_mm) == [1000, 10000, 0]
    assert list(agents.y_mm) == [2000, -3123, 0]
    assert list(agents.speed_mmps) == [5000, 12346, 0]
    assert agents.ego_id == 5
    paths = decoded["/paths"][0]
    assert list(paths.candidates) == [1, 2, 1]
    assert list(paths.points) == [2, 3, 2, 1]
    assert decoded["/map"][0].lanes[0].successors == [8, 9]


def test_kinds_survive(tmp_path):
    back = read_scene(write_scene(tmp_path / "s.mcap", small_scene()))
    assert [Kind(k) for k in back.frames[0].kinds] == [Kind.VEHICLE, Kind.CYCLIST, Kind.PEDESTRIAN]


@pytest.mark.skipif(
    shutil.which("rerun") is None
    and not (pathlib.Path(__file__).parents[1] / ".venv/bin/rerun").exists(),
    reason="rerun CLI not installed",
)
def test_rerun_mcap_check_passes(tmp_path):
    path = write_scene(tmp_path / "s.mcap", small_scene())
    exe = shutil.which("rerun") or str(pathlib.Path(__file__).parents[1] / ".venv/bin/rerun")
    done = subprocess.run(
        [exe, "mcap", "check", str(path)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_synthetic_scene_round_trip_and_size(tmp_path):
    """The issue's reference scene: 100 agents, 10 s at 10 Hz, some leaving on the way."""
    from converters.synthetic import SyntheticSettings, generate_scene

    scene = generate_scene(SyntheticSettings(n_agents=100), 4)
    path = write_scene(tmp_path / "syn.mcap", scene)
    assert path.stat().st_size < 1_000_000
    back = read_scene(path)
    assert len(back.frames) == len(scene.frames) == 100
    assert not back.frames[-1].valid.all()  # agents that left stay, invalid
    for got, want in zip(back.frames, scene.frames, strict=True):
        assert_frame_quantised(got, want)
    assert len(back.map.lanes) == len(scene.map.lanes)
    for a, b in zip(back.map.lanes, scene.map.lanes, strict=True):
        np.testing.assert_array_equal(a.centerline, q(b.centerline))
        assert a.successors == b.successors


# ---------------------------------------------------------------------- property test

coord = st.floats(-5e4, 5e4, allow_nan=False, allow_infinity=False)


@st.composite
def random_frames(draw):
    n = draw(st.integers(1, 6))
    xy = np.array(draw(st.lists(st.tuples(coord, coord), min_size=n, max_size=n)))
    paths = []
    for i in range(n):
        k = draw(st.integers(1, 3))
        cands = []
        for _ in range(k):
            p = draw(st.integers(1, 5))
            pts = np.array(draw(st.lists(st.tuples(coord, coord), min_size=p, max_size=p)))
            pts[0] = xy[i]
            cands.append(pts)
        paths.append(cands)
    nonneg = st.floats(0, 50, allow_nan=False)
    valid = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    ego = draw(st.integers(0, n - 1))
    valid[ego] = True
    return Frame.from_arrays(
        xy=xy,
        heading=np.array(draw(st.lists(st.floats(-10, 10), min_size=n, max_size=n))),
        speed=np.array(draw(st.lists(nonneg, min_size=n, max_size=n))),
        length=np.array(draw(st.lists(nonneg, min_size=n, max_size=n))),
        width=np.array(draw(st.lists(nonneg, min_size=n, max_size=n))),
        paths=paths,
        ego=ego,
        ids=draw(st.lists(st.integers(-(2**40), 2**40), min_size=n, max_size=n, unique=True)),
        kinds=draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)),
        valid=valid,
        t=draw(st.floats(-100, 100)),
    )


@settings(
    max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(frame=random_frames())
def test_any_frame_round_trips_to_its_rounding(tmp_path, frame):
    scene = Scene(LaneMap(), (frame,), 0.05)
    first = write_scene(tmp_path / "p.mcap", scene)
    (got,) = read_scene(first).frames
    assert_frame_quantised(got, frame)
    # Rounding error is at most half a step.
    assert np.abs(got.xy - frame.xy).max() <= 0.0005 + 1e-9
    again = write_scene(tmp_path / "p2.mcap", read_scene(first))
    assert again.read_bytes() == first.read_bytes()


# ---------------------------------------------------------------------- missing ego


def test_frame_without_its_ego_is_reported_not_dropped(tmp_path):
    path = tmp_path / "s.mcap"
    with SceneWriter(path, small_map(), frame_period_s=0.1) as w:
        w.add_frame(frame_a())  # ego id 5
        w.add_frame(frame_b(), ego_id=101)  # 101 is not in frame b
        w.add_frame(Frame(**{**frame_b()._fields(), "t": 0.2}), ego_id=5)
    reader = open_scene(path)
    assert reader.ego_id is None  # frames name different egos
    entries = list(reader.entries())
    assert [e.frame is None for e in entries] == [False, True, False]
    assert entries[1].ego_id == 101 and entries[1].t_s == 0.1 and entries[1].n_agents == 2
    assert [f.t for f in reader.frames(skip_missing_ego=True)] == [0.0, 0.2]
    with pytest.raises(SceneFormatError, match=r"frame 1 \(t=0.1 s\): the ego \(id 101\)"):
        list(reader.frames())
    assert list(reader.frame_stats().ego_present) == [True, False, True]


def test_invalid_ego_counts_as_missing(tmp_path):
    path = tmp_path / "s.mcap"
    with SceneWriter(path, small_map(), frame_period_s=0.1) as w:
        w.add_frame(frame_a(), ego_id=77)  # present but invalid
    (entry,) = open_scene(path).entries()
    assert entry.frame is None


# ---------------------------------------------------------------------- bad input


def test_not_an_mcap_file(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_text("hello, I am a CSV\n1,2,3\n")
    with pytest.raises(SceneFormatError, match="not an MCAP file"):
        open_scene(path)
    path.write_bytes(b"")
    with pytest.raises(SceneFormatError, match=r"not an MCAP file \(it is empty"):
        open_scene(path)


def test_truncated_file_says_so_and_counts_intact_frames(tmp_path):
    frames = [Frame(**{**frame_b()._fields(), "t": 0.1 * k}) for k in range(40)]
    scene = Scene(small_map(), frames, 0.1)
    full = write_scene(tmp_path / "full.mcap", scene).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[: len(full) // 2])
    with pytest.raises(SceneFormatError, match="truncated") as info:
        open_scene(cut)
    assert "\n" not in str(info.value)
    assert "complete frame(s) precede the cut" in str(info.value)


@pytest.mark.parametrize("keep", [8, 10, 20])
def test_file_shorter_than_the_footer_is_reported_as_truncated(tmp_path, keep):
    """Magic bytes, then almost nothing: the reader must not leak a raw OSError."""
    frames = [Frame(**{**frame_b()._fields(), "t": 0.1 * k}) for k in range(3)]
    full = write_scene(tmp_path / "full.mcap", Scene(small_map(), frames, 0.1)).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[:keep])
    with pytest.raises(SceneFormatError, match="truncated"):
        open_scene(cut)


def test_truncated_file_frame_count_is_exact_without_chunking(tmp_path):
    """The recovery hint counts whole frames; shown on an unchunked file cut mid-way."""
    path = tmp_path / "u.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f, use_chunking=False)
        w.start()
        schema = w.register_schema(
            sf.TOPIC_SCHEMAS["/agents"], "protobuf", sf.file_descriptor_set()
        )
        ids = {t: w.register_channel(t, "protobuf", schema) for t in ("/agents", "/paths")}
        for k in range(10):
            agents, paths = mcap_io.encode_frame(frame_b(), k)
            w.add_message(ids["/agents"], k, agents.SerializeToString(), k)
            w.add_message(ids["/paths"], k, paths.SerializeToString(), k)
        f.flush()
        cut_at = f.tell()  # right after frame 9: all ten complete
        w.finish()
    data = path.read_bytes()
    path.write_bytes(data[: cut_at + 5])
    with pytest.raises(SceneFormatError, match="10 complete frame"):
        open_scene(path)


def write_foreign_mcap(path: pathlib.Path, topics: list[str]) -> None:
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        schema = w.register_schema("foo.Bar", "jsonschema", b"{}")
        for t in topics:
            cid = w.register_channel(t, "json", schema)
            w.add_message(cid, 0, b"{}", 0)
        w.finish()


def test_mcap_without_scene_channels_names_the_missing(tmp_path):
    path = tmp_path / "other.mcap"
    write_foreign_mcap(path, ["/camera", "/agents"])
    with pytest.raises(SceneFormatError, match=r"channel\(s\) /map, /paths missing") as info:
        open_scene(path)
    assert "found: /agents, /camera" in str(info.value)


def test_channel_with_a_foreign_schema_is_refused(tmp_path):
    path = tmp_path / "other.mcap"
    write_foreign_mcap(path, ["/map", "/agents", "/paths"])
    with pytest.raises(SceneFormatError, match=r"expected protobuf .riskreplay\.scene\.v1\.Map."):
        open_scene(path)


def test_scene_without_frames(tmp_path):
    path = tmp_path / "empty.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        fds = sf.file_descriptor_set()
        for topic in sf.REQUIRED_TOPICS:
            sid = w.register_schema(sf.TOPIC_SCHEMAS[topic], "protobuf", fds)
            cid = w.register_channel(topic, "protobuf", sid)
            if topic == "/map":
                w.add_message(cid, 0, mcap_io.encode_map(small_map()).SerializeToString(), 0)
        w.add_metadata("scene", {"frame_period_s": "0.1", "format_version": "1"})
        w.finish()
    with pytest.raises(SceneFormatError, match="the scene has no frames"):
        open_scene(path)


def test_writer_refuses_an_empty_scene_and_leaves_nothing(tmp_path):
    with pytest.raises(ConversionError, match="at least one frame"):
        write_scene(tmp_path / "e.mcap", Scene(small_map(), (), 0.1))
    with (
        pytest.raises(ConversionError, match="at least one frame"),
        SceneWriter(tmp_path / "e.mcap", small_map(), frame_period_s=0.1),
    ):
        pass
    assert list(tmp_path.iterdir()) == []


def test_newer_format_version_is_refused(tmp_path):
    path = write_scene(tmp_path / "s.mcap", small_scene())
    with open(path, "rb") as f:
        data = f.read()
    # Same length replacement of the metadata value keeps every offset valid.
    marker = b"format_version\x01\x00\x00\x00" + str(sf.FORMAT_VERSION).encode()
    assert data.count(marker) == 1
    path.write_bytes(data.replace(marker, marker[:-1] + b"9"))
    with pytest.raises(SceneFormatError, match=r"format version 9.*upgrade riskreplay"):
        open_scene(path)


@pytest.mark.parametrize(
    ("scene_kwargs", "match"),
    [
        ({"frame_period_s": 0.0}, "frame period must be a positive"),
        ({"metadata": {"seed": 3}}, "strings to strings"),
        ({"frames": (frame_b(), frame_a())}, "strictly increasing time order"),
    ],
)
def test_writer_rejects_bad_scenes_without_leftovers(tmp_path, scene_kwargs, match):
    base = small_scene()
    scene = Scene(
        map=base.map,
        frames=scene_kwargs.get("frames", base.frames),
        frame_period_s=scene_kwargs.get("frame_period_s", 0.1),
        metadata=scene_kwargs.get("metadata", {}),
    )
    with pytest.raises(ConversionError, match=match):
        write_scene(tmp_path / "bad.mcap", scene)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------- atomic writing


@pytest.mark.parametrize("exc_type", [RuntimeError, KeyboardInterrupt])
def test_interrupted_write_leaves_no_file(tmp_path, monkeypatch, exc_type):
    frames = [Frame(**{**frame_b()._fields(), "t": 0.1 * k}) for k in range(20)]
    real = mcap_io.encode_frame
    calls = {"n": 0}

    def failing(frame, index, **kw):
        calls["n"] += 1
        if calls["n"] == 10:
            raise exc_type("interrupted")
        return real(frame, index, **kw)

    monkeypatch.setattr(mcap_io, "encode_frame", failing)
    with pytest.raises(exc_type):
        write_scene(tmp_path / "s.mcap", Scene(small_map(), frames, 0.1))
    assert calls["n"] == 10
    assert list(tmp_path.iterdir()) == []


def test_interrupted_rewrite_keeps_the_old_file(tmp_path, monkeypatch):
    path = write_scene(tmp_path / "s.mcap", small_scene())
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(mcap_io, "encode_frame", boom)
    with pytest.raises(RuntimeError):
        write_scene(path, small_scene())
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.mcap"]


def test_missing_directory_is_an_os_error(tmp_path):
    with pytest.raises(OSError):
        write_scene(tmp_path / "nope" / "s.mcap", small_scene())


# ---------------------------------------------------------------------- .proto parser


def test_parsed_schema_has_the_documented_fields():
    fields = {f.name: f for f in sf.Agents.DESCRIPTOR.fields}
    assert fields["ids"].number == 4
    assert fields["x_mm"].type == fields["x_mm"].TYPE_SINT64
    assert fields["kinds"].enum_type.values_by_name["CYCLIST"].number == Kind.CYCLIST
    assert sf.Map.DESCRIPTOR.fields_by_name["lanes"].message_type is sf.Lane.DESCRIPTOR
    # proto3 packs repeated scalars: 3 agents x 1 byte + tag + length.
    assert len(sf.Agents(valid=[True, False, True]).SerializeToString()) == 5


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ('syntax = "proto3"; message A { message B { int32 x = 1; } }', "unsupported"),
        ('syntax = "proto3"; message A { oneof o { int32 x = 1; } }', "unsupported"),
        ('syntax = "proto3"; message A { map<string, int32> m = 1; }', "unsupported"),
        ('syntax = "proto3"; message A { Unknown u = 1; }', "unknown type 'Unknown'"),
        ('syntax = "proto2"; message A { int32 x = 1; }', ":1: unsupported"),
        ('syntax = "proto3";\n\nimport "x.proto";', ":3: unsupported statement"),
    ],
)
def test_proto_parser_rejects_what_it_does_not_support(text, match):
    with pytest.raises(sf.ProtoSyntaxError, match=match):
        sf.parse_proto(text)


def test_parser_matches_protoc():
    """The import-time parser gives exactly protoc's descriptor of scene.proto.

    The fixture came from ``python -m grpc_tools.protoc -Iconverters
    --descriptor_set_out=tests/fixtures/scene_proto_protoc.pb converters/scene/scene.proto``
    (grpcio-tools 1.85.1); regenerate it after changing scene.proto.
    """
    from google.protobuf import descriptor_pb2

    fixture = pathlib.Path(__file__).parent / "fixtures" / "scene_proto_protoc.pb"
    (reference,) = descriptor_pb2.FileDescriptorSet.FromString(fixture.read_bytes()).file
    assert reference == sf.FILE_DESCRIPTOR
