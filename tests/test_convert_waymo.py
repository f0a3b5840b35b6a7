"""Waymo Open Motion: TFRecord framing, Scenario decoding (records hand-encoded on the
wire, so the field numbers are checked against the format, not against our own .proto),
the scene mapping, the CLI, and the real sample."""

from __future__ import annotations

import math
import pathlib
import shutil
import struct
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from converters.errors import ConversionError
from converters.scene.reader import read_scene
from converters.tfrecord import (
    Record,
    RecordError,
    encode_record,
    masked_crc32c,
    read_records,
    write_records,
)
from converters.waymo import read_scenes, scenario_to_scene
from replay.cli.app import main
from risk.frame import Kind


# ---------------------------------------------------------------------- wire encoding
def varint(n: int) -> bytes:
    n &= (1 << 64) - 1  # negative int32/int64: two's complement, 10 bytes
    out = bytearray()
    while True:
        low, n = n & 0x7F, n >> 7
        out.append(low | (0x80 if n else 0))
        if not n:
            return bytes(out)


def key(field: int, wire_type: int) -> bytes:
    return varint(field << 3 | wire_type)


def f_varint(field: int, n: int) -> bytes:
    return key(field, 0) + varint(n)


def f_double(field: int, x: float) -> bytes:
    return key(field, 1) + struct.pack("<d", x)


def f_float(field: int, x: float) -> bytes:
    return key(field, 5) + struct.pack("<f", x)


def f_bytes(field: int, data: bytes) -> bytes:
    return key(field, 2) + varint(len(data)) + data


def f_packed(field: int, values: list[int]) -> bytes:
    return f_bytes(field, b"".join(varint(v) for v in values))


def state(x, y, heading=0.0, vx=0.0, vy=0.0, length=4.5, width=2.0, valid=True) -> bytes:
    if not valid:  # what Waymo stores for a missing state
        return f_double(2, -1) + f_double(3, -1) + f_float(5, -1) + f_float(6, -1) + f_varint(11, 0)
    return (
        f_double(2, x) + f_double(3, y) + f_double(4, 0.5) + f_float(5, length) + f_float(6, width)
        + f_float(7, 1.5) + f_float(8, heading) + f_float(9, vx) + f_float(10, vy) + f_varint(11, 1)
    )  # fmt: skip


def track(track_id: int, object_type: int, states: list[bytes]) -> bytes:
    return (
        f_varint(1, track_id) + f_varint(2, object_type) + b"".join(f_bytes(3, s) for s in states)
    )


def lane_feature(feature_id, points, exits=(), entries=(), lane_type=2) -> bytes:
    pts = b"".join(
        f_bytes(8, f_double(1, x) + f_double(2, y) + f_double(3, 0.0)) for x, y in points
    )
    lane = f_double(1, 25.0) + f_varint(2, lane_type) + pts
    lane += f_packed(9, list(entries)) + f_packed(10, list(exits))
    return f_varint(1, feature_id) + f_bytes(3, lane)


def scenario(scenario_id="abc", sdc=1, steps=4) -> bytes:
    """3 tracks over ``steps`` steps: a pedestrian (valid at steps 0-1), the SDC vehicle
    driving east at 10 m/s along lane 11, a cyclist."""
    t = [0.1 * i for i in range(steps)]
    ped = track(
        101, 2, [state(5, 5, math.pi / 2, 0, 1.2, 0.5, 0.5, valid=i < 2) for i in range(steps)]
    )
    car = track(202, 1, [state(10 + i, 0.3, 0.0, 6.0, 8.0) for i in range(steps)])
    bike = track(303, 3, [state(50, -30 + i, math.pi / 2, 0, 4) for i in range(steps)])
    tracks = [ped, car, bike] if sdc == 1 else [car, ped, bike]
    msg = b"".join(f_double(1, x) for x in t)  # proto2 style: unpacked repeated double
    msg += b"".join(f_bytes(2, tr) for tr in tracks)
    msg += f_varint(4, 303)  # objects_of_interest
    msg += f_bytes(5, scenario_id.encode())
    msg += f_varint(6, sdc)
    msg += f_bytes(7, b"\x08\x01")  # dynamic_map_states: not declared, must be skipped
    msg += f_bytes(8, lane_feature(11, [(0, 0), (50, 0), (100, 0)], exits=[12]))
    msg += f_bytes(8, lane_feature(12, [(100, 0), (200, 0)], entries=[11]))
    msg += f_bytes(8, f_varint(1, 13) + f_bytes(4, f_varint(1, 2)))  # a road line: skipped
    msg += f_bytes(8, lane_feature(14, [(40, -40), (40, -39.9), (40, 60)], lane_type=3))
    msg += f_varint(10, 1)
    msg += f_bytes(11, f_varint(1, 2) + f_varint(2, 1)) + f_bytes(11, f_varint(1, 0))
    return msg


# ---------------------------------------------------------------------- framing
def test_masked_crc_of_known_values():
    # CRC-32C("") = 0, so the mask is just the delta; CRC-32C("123456789") = 0xE3069283,
    # rotated right by 15 bits = 0x2507C60D, plus 0xA282EAD8 (worked by hand).
    assert masked_crc32c(b"") == 0xA282EAD8
    assert masked_crc32c(b"123456789") == 0xC78AB0E5


def test_records_round_trip(tmp_path):
    path = write_records(tmp_path / "x.tfrecord", [b"one", b"", b"three" * 100])
    got = list(read_records(path))
    assert [r.payload for r in got] == [b"one", b"", b"three" * 100]
    assert [r.index for r in got] == [0, 1, 2]
    assert got[1].offset == 8 + 4 + 3 + 4


def _three_records(tmp_path):
    path = tmp_path / "x.tfrecord"
    path.write_bytes(b"".join(encode_record(p) for p in (b"aaaa", b"bbbb", b"cccc")))
    return path


def test_payload_crc_mismatch_is_reported_and_reading_resumes(tmp_path):
    path = _three_records(tmp_path)
    data = bytearray(path.read_bytes())
    data[12 + 4 + 4 + 12 + 1] ^= 0xFF  # second record's payload
    path.write_bytes(bytes(data))
    items = list(read_records(path))
    assert isinstance(items[0], Record) and isinstance(items[2], Record)
    err = items[1]
    assert isinstance(err, RecordError) and err.resumable and err.index == 1
    assert str(err) == f"{path}: record 1 (byte 20): payload CRC mismatch"


def test_length_crc_mismatch_and_truncation_stop_reading(tmp_path):
    path = _three_records(tmp_path)
    data = bytearray(path.read_bytes())
    data[20] ^= 0x01  # second record's length
    path.write_bytes(bytes(data))
    items = list(read_records(path))
    assert len(items) == 2 and "length CRC mismatch" in str(items[1])
    assert not items[1].resumable
    path.write_bytes(_three_records(tmp_path).read_bytes()[:-3])
    items = list(read_records(path))
    assert len(items) == 3 and "truncated" in str(items[2])


# ---------------------------------------------------------------------- scenario
def _scene(tmp_path, paths="map", payloads=None):
    path = write_records(tmp_path / "s.tfrecord", payloads or [scenario()])
    return list(read_scenes(path, paths=paths))


def test_scenario_maps_tracks_validity_kinds_and_labels(tmp_path):
    (scene,) = _scene(tmp_path)
    assert len(scene.frames) == 4
    f = scene.frames[2]
    assert f.t == pytest.approx(0.2)
    assert f.ids.tolist() == [101, 202, 303]
    assert f.kinds.tolist() == [Kind.PEDESTRIAN, Kind.VEHICLE, Kind.CYCLIST]
    assert f.valid.tolist() == [False, True, True]
    assert f.ego == 1 and f.ego_id == 202
    assert f.speed[1] == pytest.approx(10.0)  # |(6, 8)|
    np.testing.assert_allclose(f.xy[1], (12, 0.3))
    assert (f.length[1], f.width[1]) == pytest.approx((4.5, 2.0))
    assert scene.frame_period_s == pytest.approx(0.1)
    assert scene.labels == {"objects_of_interest": (303,), "tracks_to_predict": (303, 101)}
    assert scene.metadata["scenario_id"] == "abc"
    assert scene.metadata["dataset"] == "waymo_open_motion"
    lanes = scene.map.by_id()
    assert sorted(lanes) == [11, 12, 14]  # the road line is not a lane
    assert lanes[11].successors == (12,) and lanes[14].kind == "bike"
    # The SDC follows lane 11 into lane 12 to the map's end at x = 200 (the whole known
    # path: more than the 10 m/s * 12 s + 10 m it needs past its projection).
    (path,) = f.agent_paths(1)
    np.testing.assert_allclose(path[0], (12, 0.3))
    np.testing.assert_allclose(path[-1], (200, 0), atol=1e-9)
    assert np.all(path[1:, 1] == 0)
    # The cyclist rides the bike lane (x = 40) only if it is close: it is not (x = 50).
    (bike,) = f.agent_paths(2)
    assert len(bike) == 2 and bike[-1][0] == pytest.approx(50)


def test_hindsight_paths_follow_the_recorded_future(tmp_path):
    (scene,) = _scene(tmp_path, paths="hindsight")
    (path,) = scene.frames[0].agent_paths(1)
    np.testing.assert_allclose(path[0], (10, 0.3))
    np.testing.assert_allclose(path[1], (13, 0.3))  # last recorded state
    assert path[-1][0] == pytest.approx(10 + 130, abs=1e-6)  # extended straight east


def test_corrupt_payload_names_the_record(tmp_path):
    path = write_records(tmp_path / "s.tfrecord", [scenario(), b"\xff\xff\xff"])
    with pytest.raises(ConversionError, match=r"record 1 \(byte \d+\): not a Waymo Scenario"):
        list(read_scenes(path))


def test_sdc_index_out_of_range(tmp_path):
    path = write_records(tmp_path / "s.tfrecord", [scenario(sdc=7)])
    with pytest.raises(ConversionError, match="sdc_track_index 7 is out of range"):
        list(read_scenes(path))


def test_scenario_to_scene_works_on_decoded_messages(tmp_path):
    from converters.waymo import decode_scenario

    msg = decode_scenario(Record(0, 0, scenario("xyz", sdc=0)))
    scene = scenario_to_scene(msg, source="mem")
    assert scene.frames[0].ego_id == 202 and scene.metadata["scenario_id"] == "xyz"


# ---------------------------------------------------------------------- CLI
def _cli(*args):
    return CliRunner().invoke(main, ["convert", "waymo", *map(str, args)])


def test_cli_writes_one_mcap_per_scenario(tmp_path):
    src = write_records(tmp_path / "s.tfrecord", [scenario("a"), scenario("b/c")])
    result = _cli(src, "-o", tmp_path / "out")
    assert result.exit_code == 0, result.output
    written = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert written == ["a.mcap", "b_c.mcap"]
    assert str(tmp_path / "out" / "a.mcap") in result.stdout
    scene = read_scene(tmp_path / "out" / "b_c.mcap")
    assert len(scene.frames) == 4 and scene.labels["tracks_to_predict"] == (303, 101)
    result = _cli(src, "-o", tmp_path / "one.mcap")
    assert result.exit_code == 1 and "holds several scenarios" in result.output


def test_cli_single_scenario_to_a_file(tmp_path):
    src = write_records(tmp_path / "s.tfrecord", [scenario()])
    result = _cli(src, "-o", tmp_path / "x" / "one.mcap", "--paths", "hindsight")
    assert result.exit_code == 0, result.output
    assert read_scene(tmp_path / "x" / "one.mcap").metadata["paths"] == "hindsight"


def test_cli_crc_error_writes_nothing_and_skip_bad_converts_the_rest(tmp_path):
    src = write_records(tmp_path / "s.tfrecord", [scenario("a"), scenario("b"), scenario("c")])
    data = bytearray(src.read_bytes())
    second = len(encode_record(scenario("a")))
    data[second + 12 + 30] ^= 0xFF
    src.write_bytes(bytes(data))
    result = _cli(src, "-o", tmp_path / "out")
    assert result.exit_code == 1
    assert result.output.strip().splitlines()[-1] == (
        f"Error: {src}: record 1 (byte {second}): payload CRC mismatch"
    )
    assert "Traceback" not in result.output
    assert not (tmp_path / "out").exists()
    result = _cli(src, "-o", tmp_path / "out", "--skip-bad")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.mcap", "c.mcap"]
    assert "Skipped 1 bad record(s)" in result.stderr
    assert "record 1" in result.stderr


def test_cli_all_records_bad(tmp_path):
    src = tmp_path / "s.tfrecord"
    src.write_bytes(encode_record(b"\xff\xff")[:-1])
    result = _cli(src, "-o", tmp_path / "out", "--skip-bad")
    assert result.exit_code == 1 and "nothing converted" in result.output


# ---------------------------------------------------------------------- real sample
SAMPLE = (
    pathlib.Path(__file__).resolve().parents[2] / "shared/data/waymo/womd_637f20cafde22ff8.tfrecord"
)


@pytest.fixture(scope="module")
def sample_mcap(tmp_path_factory):
    """The sample converted once per module (skips like ``shared_data`` when absent)."""
    src = SAMPLE
    if not src.is_file():
        pytest.skip(f"real data sample not found at {src}")
    out = tmp_path_factory.mktemp("waymo") / "sample.mcap"
    result = _cli(src, "-o", out)
    assert result.exit_code == 0, result.output
    return out


@pytest.mark.realdata
def test_real_sample_converts_and_reads_back(shared_data, sample_mcap):
    scene = read_scene(sample_mcap)
    assert len(scene.frames) == 91
    f = scene.frames[10]
    assert f.n_agents == 83
    assert np.bincount(f.kinds, minlength=4).tolist() == [70, 10, 3, 0]
    assert f.ego_id == 2406  # the SDC (tracks[82])
    assert len(scene.map.lanes) == 199
    assert scene.labels["tracks_to_predict"] == (2320, 1676, 1675)
    assert scene.labels["objects_of_interest"] == ()
    # Every track valid in the record is valid in the frame (the first frame: 24 tracks
    # are valid over all 91 steps, so at least those).
    assert all(fr.valid.sum() >= 24 for fr in scene.frames)
    # Moving vehicles near the ego are on lanes: their paths have centre-line vertices.
    moving = f.valid & (f.kinds == Kind.VEHICLE) & (f.speed > 2)
    lane_paths = [max(len(p) for p in f.agent_paths(i)) > 2 for i in np.flatnonzero(moving)]
    assert np.mean(lane_paths) > 0.9


@pytest.mark.realdata
def test_real_sample_passes_rerun_mcap_check(shared_data, sample_mcap):
    import sys

    rerun = shutil.which("rerun") or str(pathlib.Path(sys.executable).with_name("rerun"))
    if not pathlib.Path(rerun).exists():
        pytest.skip("the rerun binary is not installed")
    out = subprocess.run([rerun, "mcap", "check", str(sample_mcap)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "/agents" in out.stdout and "/labels" in out.stdout


def assert_run_covers_every_valid_agent(scene_path: pathlib.Path, tmp_path: pathlib.Path) -> None:
    """``replay run`` on a converted scene: one finite risk per model for every valid
    non-ego agent of every frame (shared with the other converters' tests)."""
    import polars as pl

    table = tmp_path / "risks.parquet"
    result = CliRunner().invoke(
        main, ["run", str(scene_path), "--no-rrd", "--table", str(table), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(table)
    scene = read_scene(scene_path)
    expected = {
        (i, int(agent_id)) for i, f in enumerate(scene.frames) for agent_id in f.ids[f.others]
    }
    assert set(zip(rows["frame"].to_list(), rows["agent_id"].to_list(), strict=True)) == expected
    risks = [c for c in rows.columns if c.startswith("risk_")]
    assert len(risks) == 9
    assert rows.select(pl.all_horizontal([pl.col(c).is_finite() for c in risks])).to_series().all()


@pytest.mark.slow
@pytest.mark.realdata
def test_real_sample_replays_with_every_valid_agent_scored(shared_data, sample_mcap, tmp_path):
    assert_run_covers_every_valid_agent(sample_mcap, tmp_path)


@pytest.mark.parametrize("source", ["waymo", "av2", "commonroad", "interaction"])
def test_every_recorded_source_has_a_command_with_help(source):
    runner = CliRunner()
    listing = runner.invoke(main, ["convert", "--help"])
    assert listing.exit_code == 0 and source in listing.output
    result = runner.invoke(main, ["convert", source, "--help"])
    assert result.exit_code == 0
    for option in ("--output", "--paths [map|hindsight]", "--horizon-s", "--skip-bad"):
        assert option in result.output
