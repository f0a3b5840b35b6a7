"""Speed and size of the scene pipeline: generate, write and read back a synthetic scene.

The issue's reference case: 100 agents, 10 s at 10 Hz (100 frames). Each stage runs
``--repeat`` times (default 7) and the median is reported, since the machine is shared.
Goals (issue 3): read 100 frames into Frames in < 0.1 s, write in < 0.3 s, file < 1 MB.

    .venv/bin/python benchmarks/bench_scene_io.py [--agents 100] [--duration 10] [--repeat 7]
    .venv/bin/python benchmarks/bench_scene_io.py --encodings   # + the size trade-off table
    .venv/bin/python benchmarks/bench_scene_io.py --duration 30 --arm-length 400 --chunk-mib 4

``--encodings`` compresses the scene's per-frame ``/agents`` + ``/paths`` payloads (one
zstd level-3 stream, like one MCAP chunk) in alternative encodings: the numbers behind
the choices in docs/scene-format.md.
"""

from __future__ import annotations

import argparse
import pathlib
import re
import statistics
import tempfile
import time
from collections.abc import Callable

import numpy as np

from converters.intersection import IntersectionSettings
from converters.scene import schema as sf
from converters.scene import writer as mcap_io
from converters.scene.reader import open_scene, read_scene
from converters.scene.writer import encode_frame, write_scene
from converters.synthetic import SyntheticSettings, generate_scene, generate_situation


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, list[float], object]:
    """Median wall time in s, all times, and the last result."""
    times, result = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), times, result


def _variant_classes(float_fields: bool) -> tuple[type, type]:
    """Agents/Paths classes from scene.proto, optionally with float32 numeric fields."""
    from google.protobuf import descriptor_pool, message_factory

    text = sf.PROTO_PATH.read_text(encoding="utf-8").replace(sf.PACKAGE, "bench.variant")
    if float_fields:
        names = "x_mm|y_mm|heading_urad|speed_mmps|length_mm|width_mm"
        text = re.sub(rf"repeated sint64 ({names})", r"repeated float \1", text)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(sf.parse_proto(text))
    get = message_factory.GetMessageClass
    return (
        get(pool.FindMessageTypeByName("bench.variant.Agents")),
        get(pool.FindMessageTypeByName("bench.variant.Paths")),
    )


def encoding_sizes(frames: list) -> list[tuple[str, int]]:
    """Compressed bytes of all frames' /agents + /paths payloads per encoding."""
    import zstandard

    def zlen(chunks: list[bytes]) -> int:
        return len(zstandard.ZstdCompressor(level=3).compress(b"".join(chunks)))

    def encode(pos: float | None, heading: float, speed: float, delta: bool = False) -> int:
        agents_cls, paths_cls = _variant_classes(float_fields=pos is None)
        out = []
        for i, f in enumerate(frames):

            def q(v: np.ndarray, step: float | None) -> list:
                v = np.asarray(v, dtype=np.float64)
                return (
                    v.astype(np.float32).tolist()
                    if step is None
                    else np.rint(v * step).astype(np.int64).tolist()
                )

            real = np.arange(f.paths.shape[1])[None, :] < f.path_points[:, None]
            pts = np.array(q(f.paths[real], pos)).reshape(-1, 2)
            if delta:  # each point relative to the previous one of its candidate
                first = np.cumsum(f.path_points) - f.path_points
                d = np.diff(pts, axis=0, prepend=pts[:1] * 0)
                d[first] = pts[first]
                pts = d
            a = agents_cls(
                frame_index=i, t_s=f.t, ego_id=f.ego_id, ids=f.ids.tolist(),
                kinds=f.kinds.tolist(), x_mm=q(f.xy[:, 0], pos), y_mm=q(f.xy[:, 1], pos),
                heading_urad=q(f.heading, heading), speed_mmps=q(f.speed, speed),
                length_mm=q(f.length, pos), width_mm=q(f.width, pos), valid=f.valid.tolist(),
            )  # fmt: skip
            p = paths_cls(
                frame_index=i, t_s=f.t, candidates=np.bincount(f.path_agent).tolist(),
                points=f.path_points.tolist(), x_mm=pts[:, 0].tolist(), y_mm=pts[:, 1].tolist(),
            )  # fmt: skip
            out.append(a.SerializeToString() + p.SerializeToString())
        return zlen(out)

    ours = [
        b"".join(m.SerializeToString() for m in encode_frame(f, i)) for i, f in enumerate(frames)
    ]
    return [
        ("format as written (mm, mm/s, urad)", zlen(ours)),
        ("float32 positions, sizes, speeds, headings", encode(None, None, None)),
        ("integers: cm, cm/s, 100 urad", encode(100.0, 1e4, 100.0)),
        ("integers: 0.1 mm, 0.1 mm/s, 0.1 urad", encode(1e4, 1e7, 1e4)),
        ("mm, urad, with delta-coded path points", encode(1000.0, 1e6, 1000.0, delta=True)),
        (
            "/paths alone, as written",
            zlen([encode_frame(f, i)[1].SerializeToString() for i, f in enumerate(frames)]),
        ),
        (
            "/paths alone, first frame only",
            zlen([encode_frame(frames[0], 0)[1].SerializeToString()]),
        ),
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--arm-length", type=float, default=150.0, help="m (longer scenes need longer arms)"
    )
    parser.add_argument(
        "--chunk-mib", type=float, default=None, help="override the writer's chunk size"
    )
    parser.add_argument("--encodings", action="store_true", help="also the size trade-off table")
    args = parser.parse_args()

    if args.chunk_mib is not None:
        mcap_io.CHUNK_SIZE_BYTES = int(args.chunk_mib * 1024 * 1024)
    settings = SyntheticSettings(
        n_agents=args.agents,
        duration_s=args.duration,
        intersection=IntersectionSettings(arm_length_m=args.arm_length),
    )
    rows = []
    t_gen, all_gen, scene = timed(lambda: generate_scene(settings, args.seed), args.repeat)
    rows.append(("generate scene", t_gen, all_gen))
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "scene.mcap"
        t_write, all_write, _ = timed(lambda: write_scene(path, scene), args.repeat)
        rows.append(("write (write_scene)", t_write, all_write))

        def read_all() -> int:
            return sum(1 for _ in open_scene(path).frames())

        t_read, all_read, n_read = timed(read_all, args.repeat)
        rows.append(("read into Frames (open_scene + frames)", t_read, all_read))
        t_open, all_open, _ = timed(lambda: open_scene(path), args.repeat)
        rows.append(("  of which open (summary, map, metadata)", t_open, all_open))
        back = read_scene(path)
        size = path.stat().st_size
        reader = open_scene(path)
        channel_counts = {c.topic: c.message_count for c in reader.channels}
    t_sit, all_sit, _ = timed(lambda: generate_situation(settings, args.seed), args.repeat)
    rows.append(("generate one situation", t_sit, all_sit))

    frames = scene.frames  # type: ignore[attr-defined]
    valid = [int(f.valid.sum()) for f in frames]
    max_err = max(
        float(np.abs(a.xy - b.xy).max()) for a, b in zip(back.frames, frames, strict=True)
    )
    print(f"scene: {len(frames)} frames, {args.agents} agents ({min(valid)}-{max(valid)} valid),"
          f" seed {args.seed}; messages {channel_counts}")  # fmt: skip
    print(f"{'stage':42s} {'median':>9s}   all runs (s)")
    for name, median, times in rows:
        print(f"{name:42s} {median:8.4f}s   " + " ".join(f"{t:.4f}" for t in times))
    print(f"{'file size':42s} {size / 1e6:8.3f} MB  ({size} bytes)")
    print(f"frames read: {n_read}; max position rounding error {max_err * 1000:.3f} mm")
    if args.encodings:
        print("\nencoding (zstd level 3 over all frames)         compressed bytes")
        for name, n_bytes in encoding_sizes(list(frames)):
            print(f"  {name:46s} {n_bytes:>9d}")


if __name__ == "__main__":
    main()
