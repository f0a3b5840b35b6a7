"""Generated bad inputs for every command, and a runner that judges the outcome.

Used by ``tests/test_reliability.py`` (one test per case) and by
``benchmarks/reliability_census.py`` (counts over all cases). Each :class:`Case` is a
``replay`` command line on a bad input; :func:`run_case` runs it in a subprocess (in its
own session, with a time limit) and returns an :class:`Outcome`: exit status, whether a
traceback was printed, whether it hung, the ``Error:`` lines, whether the inputs changed
(SHA-256) and which files were left behind in the case's folder.

Kinds: corrupted, truncated, foreign, non-finite, out-of-range, same-path, unwritable;
and from issue 31 (:func:`round3_cases`): device (outputs that are named pipes), hang
(named pipes as inputs, path candidates beyond the cap), memory (a metadata period that
would size a 78 TiB grid), exit-0 (bad values that used to convert or replay), recursion
(deep TOML and JSON) and converter (values that raised tracebacks); and from issue 36
(``reliability_round4.py``): pickle (hostile pickles, measured and generated), label
(label columns that are not booleans), option (NaN, options that do nothing) and memory
(a scenario too long to convert). Full-disk,
killed-mid-write, device-node and signal cases need a tmpfs, ``mknod`` or signals; they
live in ``test_reliability.py`` and ``test_reliability_edges.py``.
"""

from __future__ import annotations

import hashlib
import math
import os
import pathlib
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import polars as pl

from converters.tfrecord import write_records

TESTS = pathlib.Path(__file__).resolve().parent
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

from test_convert_av2 import _rows as av2_rows  # noqa: E402
from test_convert_av2 import write_scenario as av2_write_scenario  # noqa: E402
from test_convert_commonroad import RECT, _obstacle, scenario_xml  # noqa: E402
from test_convert_interaction import HEADER, osm_text, vehicle_csv  # noqa: E402
from test_convert_waymo import scenario as waymo_scenario  # noqa: E402

REPLAY = [sys.executable, "-m", "replay"]
TIME_LIMIT_S = 120.0


@dataclass(frozen=True)
class Case:
    """One bad invocation: ``make(folder)`` writes the inputs and returns the arguments
    (after ``replay``) and the input files whose bytes must not change."""

    name: str
    kind: str
    make: Callable[[pathlib.Path], tuple[list[str], list[pathlib.Path]]]
    names_file: bool = True  # the Error: line must name one of the inputs or outputs


@dataclass
class Outcome:
    case: str
    kind: str
    returncode: int | None
    stderr: str
    seconds: float
    hung: bool
    traceback: bool
    error_lines: list[str]
    inputs_changed: list[str]
    leftovers: list[str]
    survivors: list[int] = field(default_factory=list)

    @property
    def clean_error(self) -> bool:
        return (
            not self.hung
            and self.returncode not in (0, None)
            and not self.traceback
            and len(self.error_lines) == 1
            and not self.inputs_changed
            and not self.leftovers
            and not self.survivors
        )


# ---------------------------------------------------------------------- inputs
def sha256(path: pathlib.Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


_SCENE_CACHE: dict[str, bytes] = {}
_SCENE_LOCK = threading.Lock()


def scene_bytes() -> bytes:
    """A small valid scene (synthetic, 12 agents, 1 s), made once per process."""
    with _SCENE_LOCK:
        if "scene" not in _SCENE_CACHE:
            from converters.scene.writer import write_scene
            from converters.synthetic import SyntheticSettings, generate_scene

            settings = SyntheticSettings(n_agents=12, duration_s=1.0)
            with tempfile.TemporaryDirectory() as tmp:
                path = pathlib.Path(tmp, "scene.mcap")
                write_scene(path, generate_scene(settings, seed=3))
                _SCENE_CACHE["scene"] = path.read_bytes()
        return _SCENE_CACHE["scene"]


def scene(folder: pathlib.Path, name: str = "s.mcap") -> pathlib.Path:
    path = folder / name
    path.write_bytes(scene_bytes())
    return path


def flipped(folder: pathlib.Path, seed: int, name: str = "c.mcap") -> pathlib.Path:
    """The scene with 64 bytes inverted at a random place past the header."""
    data = bytearray(scene_bytes())
    at = random.Random(seed).randrange(64, len(data) - 128)
    for i in range(64):
        data[at + i] ^= 0xFF
    path = folder / name
    path.write_bytes(bytes(data))
    return path


def truncated(folder: pathlib.Path, fraction: float) -> pathlib.Path:
    data = scene_bytes()
    path = folder / "t.mcap"
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def table(folder: pathlib.Path, name: str = "tab.parquet") -> pathlib.Path:
    """A real agents table, from replaying the small scene (in-process)."""
    from replay.core.engine import run_scene
    from replay.core.tables import TableSink

    src = scene(folder, ".src.mcap")
    path = folder / name
    run_scene(src, sinks=[TableSink(path)], progress=False)
    src.unlink()
    return path


# ---------------------------------------------------------------------- cases
def _run(args: list[str], *inputs: pathlib.Path):
    return [str(a) for a in args], list(inputs)


def cases(generated: int = 30) -> list[Case]:
    """Every case; ``generated``: how many generated hostile pickles join round 4."""
    out: list[Case] = []

    def add(name: str, kind: str, names_file: bool = True):
        def deco(make):
            out.append(Case(name, kind, make, names_file))
            return make

        return deco

    # corrupted scenes, in every command that reads one
    for seed in range(4):
        for cmd in ("run", "inspect", "calibrate"):

            def make(d, seed=seed, cmd=cmd):
                c = flipped(d, seed)
                extra = {"run": ["--no-progress"], "inspect": [], "calibrate": []}[cmd]
                if cmd == "calibrate":
                    extra = ["-o", d / "cal.toml", "--no-progress"]
                return _run([cmd, c, *extra], c)

            out.append(Case(f"corrupted-{cmd}-{seed}", "corrupted", make))

    for frac in (0.5, 0.97):

        @add(f"truncated-run-{frac}", "truncated")
        def _(d, frac=frac):
            t = truncated(d, frac)
            return _run(["run", t, "--no-progress"], t)

        @add(f"truncated-inspect-{frac}", "truncated")
        def _(d, frac=frac):
            t = truncated(d, frac)
            return _run(["inspect", t], t)

    @add("foreign-png-run", "foreign")
    def _(d):
        p = d / "img.mcap"
        p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
        return _run(["run", p, "--no-progress"], p)

    @add("foreign-empty-inspect", "foreign")
    def _(d):
        p = d / "empty.mcap"
        p.write_bytes(b"")
        return _run(["inspect", p], p)

    @add("foreign-text-stats", "foreign")
    def _(d):
        p = d / "notes.csv"
        p.write_text("hello\nworld\n")
        return _run(["stats", p, "-o", d / "st", "--no-plots", "--no-progress"], p)

    @add("header-only-csv-stats", "foreign")
    def _(d):
        t = table(d)
        csv = d / "h.csv"
        csv.write_text(",".join(pl.read_parquet(t).columns) + "\n")
        t.unlink()
        return _run(["stats", csv, "-o", d / "st", "--no-plots", "--no-progress"], csv)

    @add("corrupted-parquet-stats", "corrupted")
    def _(d):
        t = table(d)
        data = bytearray(t.read_bytes())
        for i in range(len(data) // 2, len(data) // 2 + 64):
            data[i] ^= 0xFF
        t.write_bytes(bytes(data))
        return _run(["stats", t, "-o", d / "st", "--no-plots", "--no-progress"], t)

    @add("risk-out-of-range-stats", "out-of-range")
    def _(d):
        t = table(d)
        df = pl.read_parquet(t)
        col = next(c for c in df.columns if c.startswith("risk_"))
        df = df.with_columns(pl.lit(-757.0).alias(col))
        df.write_parquet(t)
        return _run(["stats", t, "-o", d / "st", "--no-plots", "--no-progress"], t)

    # same path: an output that is an input, or two outputs that are one file
    @add("same-path-run-output-is-scene", "same-path")
    def _(d):
        s = scene(d)
        return _run(["run", s, "-o", s, "--no-progress"], s)

    @add("same-path-run-symlink", "same-path")
    def _(d):
        s = scene(d)
        (d / "link.rrd").symlink_to(s)
        return _run(["run", s, "-o", d / "link.rrd", "--no-progress"], s)

    @add("same-path-run-hardlink-table", "same-path")
    def _(d):
        s = scene(d)
        os.link(s, d / "hard.parquet")
        return _run(["run", s, "--no-rrd", "--table", d / "hard.parquet", "--no-progress"], s)

    @add("same-path-run-table-is-output", "same-path")
    def _(d):
        s = scene(d)
        return _run(["run", s, "-o", d / "o.rrd", "--table", d / "o.rrd", "--no-progress"], s)

    @add("same-path-calibrate", "same-path")
    def _(d):
        s = scene(d)
        return _run(["calibrate", s, "-o", s, "--no-progress"], s)

    @add("same-path-waymo", "same-path")
    def _(d):
        w = write_records(d / "w.mcap", [waymo_scenario()])
        return _run(["convert", "waymo", w, "-o", w], w)

    @add("same-path-interaction-map", "same-path")
    def _(d):
        csv, osm = d / "t.csv", d / "m.mcap"
        csv.write_text(vehicle_csv())
        osm.write_text(osm_text())
        return _run(["convert", "interaction", csv, "--map", osm, "-o", osm], csv, osm)

    @add("same-path-commonroad", "same-path")
    def _(d):
        x = d / "c.mcap"
        x.write_text(scenario_xml())
        return _run(["convert", "commonroad", x, "-o", x], x)

    @add("same-path-av2", "same-path")
    def _(d):
        p = av2_write_scenario(d / "sc")
        target = d / "sc" / "x.mcap"
        os.symlink(p, target)
        return _run(["convert", "av2", d / "sc", "-o", target], p)

    @add("same-path-stats-table-in-out-dir", "same-path")
    def _(d):
        out = d / "st"
        out.mkdir()
        t = table(out, "roc.parquet")
        return _run(["stats", t, "-o", out, "--no-plots", "--no-progress"], t)

    # unwritable / impossible outputs, found before the replay
    @add("unwritable-run-output-under-a-file", "unwritable")
    def _(d):
        s = scene(d)
        return _run(["run", s, "-o", d / "s.mcap" / "x.rrd", "--no-progress"], s)

    @add("unwritable-run-table-is-folder", "unwritable")
    def _(d):
        s = scene(d)
        (d / "tab.parquet").mkdir()
        return _run(["run", s, "--table", d / "tab.parquet", "--no-rrd", "--no-progress"], s)

    @add("unwritable-run-table-missing-folder", "unwritable")
    def _(d):
        s = scene(d)
        return _run(["run", s, "--table", d / "no" / "t.parquet", "--no-progress"], s)

    @add("unwritable-demo-output-is-file", "unwritable")
    def _(d):
        f = d / "f"
        f.write_text("x")
        return _run(["demo", "-o", f, "--no-progress"], f)

    # non-finite values in every converter
    for field_, value in (("x", "inf"), ("x", "nan"), ("vx", "inf"), ("psi_rad", "-inf")):

        @add(f"nonfinite-interaction-{field_}-{value}", "non-finite")
        def _(d, field_=field_, value=value):
            csv, osm = d / "t.csv", d / "m.osm"
            lines = vehicle_csv().splitlines()
            cols = HEADER.split(",")
            row = lines[2].split(",")
            row[cols.index(field_)] = value
            lines[2] = ",".join(row)
            csv.write_text("\n".join(lines) + "\n")
            osm.write_text(osm_text())
            return _run(["convert", "interaction", csv, "--map", osm, "-o", d / "o.mcap"], csv)

    for what, state in (
        ("velocity-inf", (5, 15, 0, 0.0, "inf")),
        ("orientation-nan", (5, 15, 0, "nan", 10.0)),
        ("x-inf", (5, "inf", 0, 0.0, 10.0)),
    ):

        @add(f"nonfinite-commonroad-{what}", "non-finite")
        def _(d, state=state):
            x = d / "c.xml"
            extra = _obstacle(
                40, "car", RECT, [(t, 10 + t, 8, 0.0, 10.0) for t in range(5)] + [state]
            )
            x.write_text(scenario_xml(extra))
            return _run(["convert", "commonroad", x, "-o", d / "o.mcap"], x)

    for column, value in (("position_x", math.inf), ("heading", math.nan)):

        @add(f"nonfinite-av2-{column}", "non-finite")
        def _(d, column=column, value=value):
            p = av2_write_scenario(d / "sc")
            df = av2_rows().with_columns(pl.lit("tiny-0001").alias("scenario_id"))
            df = df.with_columns(
                pl.when(pl.col("timestep") == 3).then(value).otherwise(pl.col(column)).alias(column)
            )
            df.write_parquet(p)
            return _run(["convert", "av2", d / "sc", "-o", d / "o.mcap"], p)

    # out-of-range requests and values
    for args in (
        ["demo", "--seed", "-1"],
        ["demo", "--agents", "1000000000"],
        ["convert", "synthetic", "--agents", "1000000000"],
        ["convert", "synthetic", "--arm-length", "1e300"],
        ["convert", "synthetic", "--period", "1e-9"],
        ["convert", "synthetic", "--duration", "1e12"],
        ["experiment", "--workers", "99999999999999999999", "--situations", "2"],
        ["batch", "x", "--workers", "99999999999999999999"],
        ["stats", "x", "--workers", "10000000"],
    ):

        @add("out-of-range-" + "-".join(a.lstrip("-") for a in args), "out-of-range", False)
        def _(d, args=args):
            a = [x if x != "x" else str(d / "missing") for x in args]
            return _run([*a, "-o", d / "out"])

    @add("out-of-range-av2-timestep-1e12", "out-of-range")
    def _(d):
        p = av2_write_scenario(d / "sc")
        df = av2_rows().with_columns(pl.lit("tiny-0001").alias("scenario_id"))
        df = df.with_columns(
            pl.when(pl.col("timestep") == 4).then(10**12).otherwise(pl.col("timestep"))
            .alias("timestep"), pl.lit(5).alias("num_timestamps"),
        )  # fmt: skip
        df.write_parquet(p)
        return _run(["convert", "av2", d / "sc", "-o", d / "o.mcap"], p)

    @add("out-of-range-commonroad-time-2e9", "out-of-range")
    def _(d):
        x = d / "c.xml"
        extra = _obstacle(40, "car", RECT, [(0, 1, 8, 0.0, 1.0), (2_000_000_000, 2, 8, 0.0, 1.0)])
        x.write_text(scenario_xml(extra))
        return _run(["convert", "commonroad", x, "-o", d / "o.mcap"], x)

    @add("out-of-range-commonroad-negative-time", "out-of-range")
    def _(d):
        x = d / "c.xml"
        extra = _obstacle(40, "car", RECT, [(-3, 1, 8, 0.0, 1.0), (0, 2, 8, 0.0, 1.0)])
        x.write_text(scenario_xml(extra))
        return _run(["convert", "commonroad", x, "-o", d / "o.mcap"], x)

    @add("out-of-range-interaction-frame-inf", "out-of-range")
    def _(d):
        csv, osm = d / "t.csv", d / "m.osm"
        lines = vehicle_csv().splitlines()
        row = lines[3].split(",")
        row[1] = "inf"
        lines[3] = ",".join(row)
        csv.write_text("\n".join(lines) + "\n")
        osm.write_text(osm_text())
        return _run(["convert", "interaction", csv, "--map", osm, "-o", d / "o.mcap"], csv)

    @add("out-of-range-interaction-frame-1e15", "out-of-range")
    def _(d):
        csv, osm = d / "t.csv", d / "m.osm"
        lines = vehicle_csv().splitlines()
        row = lines[3].split(",")
        row[1] = "1000000000000000"
        lines[3] = ",".join(row)
        csv.write_text("\n".join(lines) + "\n")
        osm.write_text(osm_text())
        return _run(["convert", "interaction", csv, "--map", osm, "-o", d / "o.mcap"], csv)

    out += round3_cases()
    from reliability_round4 import round4_cases  # (it builds on this module's helpers)

    out += round4_cases(generated)
    return out


# ---------------------------------------------------------------------- round 3 (issue 31)
def tampered(folder: pathlib.Path, name: str, *, period: float | None = None,
             tamper: Callable | None = None) -> pathlib.Path:  # fmt: skip
    """The small scene rewritten frame by frame: another metadata period, or
    ``tamper(agents, paths, k)`` applied to each frame's messages."""
    from converters.scene import schema as sf
    from converters.scene.reader import read_scene
    from converters.scene.writer import SceneWriter, encode_frame

    src = scene(folder, ".good.mcap")
    good = read_scene(src)
    src.unlink()
    path = folder / name
    w = SceneWriter(path, good.map, frame_period_s=period or good.frame_period_s,
                    metadata={"converter": "test"})  # fmt: skip
    for k, frame in enumerate(good.frames):
        agents, paths = encode_frame(frame, k)
        if tamper is not None:
            tamper(agents, paths, k)
        t = int(1e9 * frame.t)
        w._write(sf.TOPIC_AGENTS, agents, t)
        w._write(sf.TOPIC_PATHS, paths, t)
        w._n_frames += 1
    w.close()
    return path


def many_candidates(agents, paths, k, count: int = 100) -> None:
    """Every agent's first path candidate repeated ``count`` times."""
    cands, pts = list(paths.candidates), list(paths.points)
    xs, ys = list(paths.x_mm), list(paths.y_mm)
    new_c, new_p, new_x, new_y = [], [], [], []
    pi = xi = 0
    for c in cands:
        n = pts[pi]
        new_c.append(count)
        new_p += [n] * count
        new_x += xs[xi : xi + n] * count
        new_y += ys[xi : xi + n] * count
        xi += sum(pts[pi : pi + c])
        pi += c
    for field_, values in (("candidates", new_c), ("points", new_p), ("x_mm", new_x),
                           ("y_mm", new_y)):  # fmt: skip
        del getattr(paths, field_)[:]
        getattr(paths, field_).extend(values)


def _stats(table_path: pathlib.Path, d: pathlib.Path, *extra: str):
    return _run(["stats", table_path, "-o", d / "st", "--no-plots", "--no-progress", *extra],
                table_path)  # fmt: skip


def _retyped(d: pathlib.Path, column: str, value: object, suffix: str = ".parquet"):
    t = table(d, ".t.parquet")
    df = pl.read_parquet(t).with_columns(pl.lit(value).alias(column))
    t.unlink()
    path = d / f"tab{suffix}"
    if suffix == ".csv":
        df.select(pl.all().cast(pl.String)).write_csv(path)
    else:
        df.write_parquet(path)
    return path


def without_statistics(
    src: pathlib.Path, path: pathlib.Path, *, statistics: bool = False, edit_map=None
) -> pathlib.Path:
    """A copy of the scene ``src`` written without MCAP's optional Statistics record
    (``statistics=True``: with it), its ``/map`` message passed through ``edit_map``."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f_in, open(path, "wb") as f_out:
        reader = make_reader(f_in)
        summary = reader.get_summary()
        w = Writer(f_out, use_statistics=statistics)
        w.start(profile="", library="test")
        schema_ids = {
            sid: w.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()
        }
        channel_ids = {
            cid: w.register_channel(c.topic, c.message_encoding, schema_ids[c.schema_id])
            for cid, c in summary.channels.items()
        }
        for _, channel, message in reader.iter_messages(log_time_order=False):
            data = message.data
            if channel.topic == "/map" and edit_map is not None:
                from converters.scene import schema as sf

                m = sf.Map()
                m.ParseFromString(data)
                edit_map(m)
                data = m.SerializeToString()
            w.add_message(channel_ids[channel.id], message.log_time, data,
                          message.publish_time)  # fmt: skip
        for record in reader.iter_metadata():
            w.add_metadata(record.name, record.metadata)
        w.finish()
    return path


def round3_cases() -> list[Case]:
    out: list[Case] = []

    def add(name: str, kind: str, names_file: bool = True):
        def deco(make):
            out.append(Case(name, kind, make, names_file))
            return make

        return deco

    # data destroyed: outputs that are pipes, reports that are inputs or outputs
    @add("device-run-output-is-a-fifo", "device")
    def _(d):
        s = scene(d)
        os.mkfifo(d / "pipe.rrd")
        return _run(["run", s, "-o", d / "pipe.rrd", "--no-progress"], s)

    @add("device-table-is-a-fifo", "device")
    def _(d):
        s = scene(d)
        os.mkfifo(d / "pipe.parquet")
        return _run(["run", s, "--no-rrd", "--table", d / "pipe.parquet", "--no-progress"], s)

    @add("same-path-evaluate-report-is-an-input-in-a-folder", "same-path")
    def _(d):
        (d / "in").mkdir()
        s = scene(d / "in")
        return _run(["evaluate", d / "in", "-o", d / "ev", "--report", s, "--no-progress",
                     "--bootstrap", "0"], s)  # fmt: skip

    # hangs: a named pipe with no writer as an input
    for cmd in ("run", "inspect", "stats", "evaluate"):

        @add(f"hang-fifo-scene-{cmd}", "hang")
        def _(d, cmd=cmd):
            os.mkfifo(d / "p.mcap")
            extra = {"run": ["--no-progress"], "inspect": [],
                     "stats": ["-o", d / "st", "--no-progress"],
                     "evaluate": ["-o", d / "ev", "--no-progress"]}[cmd]  # fmt: skip
            return _run([cmd, d / "p.mcap", *extra])

    @add("hang-fifo-batch-input", "hang")
    def _(d):
        os.mkfifo(d / "p.mcap")
        return _run(["batch", d / "p.mcap", "-o", d / "out", "--no-progress"])

    @add("hang-many-path-candidates", "hang")
    def _(d):
        s = tampered(d, "c.mcap", tamper=many_candidates)
        return _run(["run", s, "--no-rrd", "--table", d / "t.parquet", "--no-progress"], s)

    # memory from one number
    for args in (["run", "--no-rrd", "--table", "t.parquet"], ["run", "--ego", "all",
                 "--table", "t.parquet"], ["evaluate", "-o", "ev", "--bootstrap", "0"]):  # fmt: skip

        @add(f"memory-period-1e-12-{'-'.join(a.lstrip('-') for a in args[1:3])}", "memory")
        def _(d, args=args):
            s = tampered(d, "p.mcap", period=1e-12)
            return _run([args[0], s, *args[1:], "--no-progress"], s)

    # bad frame order
    def backwards(agents, paths, k):
        if k == 5:
            agents.t_s = 0.05

    def repeated(agents, paths, k):
        if k == 5:
            agents.t_s -= 0.1

    for name, tamper in (("backwards", backwards), ("repeated", repeated)):

        @add(f"exit0-frame-times-{name}", "exit-0")
        def _(d, tamper=tamper):
            s = tampered(d, "b.mcap", tamper=tamper)
            return _run(["run", s, "--no-rrd", "--table", d / "t.parquet", "--no-progress"], s)

        @add(f"exit0-frame-times-{name}-inspect", "exit-0")
        def _(d, tamper=tamper):
            s = tampered(d, "b.mcap", tamper=tamper)
            return _run(["inspect", s], s)

    # recursion
    @add("recursion-cascade-toml", "recursion")
    def _(d):
        s = scene(d)
        toml = d / "deep.toml"
        toml.write_text("a = " + "[" * 50_000 + "]" * 50_000 + "\n")
        return _run(["run", s, "--cascade", toml, "--no-rrd", "--table", d / "t.parquet",
                     "--no-progress"], s, toml)  # fmt: skip

    @add("recursion-av2-map-json", "recursion")
    def _(d):
        p = av2_write_scenario(d / "sc")
        m = next((d / "sc").glob("*.json"))
        m.write_text('{"lane_segments": ' + "[" * 200_000 + "]" * 200_000 + "}")
        return _run(["convert", "av2", d / "sc", "-o", d / "o.mcap"], p, m)

    # stats on tables of the wrong types
    for column, value, suffix in (
        ("frame", "x", ".parquet"), ("ego_id", "x", ".parquet"), ("agent_id", "x", ".parquet"),
        ("t_s", "x", ".parquet"), ("baseline", "maybe", ".csv"),
    ):  # fmt: skip

        @add(f"exit0-stats-{column}-{value}{suffix.replace('.', '-')}", "exit-0")
        def _(d, column=column, value=value, suffix=suffix):
            return _stats(_retyped(d, column, value, suffix), d)

    @add("exit0-stats-models-empty", "exit-0", False)
    def _(d):
        return _stats(table(d), d, "--models", "")

    for value in ("nan", "-1"):

        @add(f"exit0-evaluate-baseline-threshold-{value}", "exit-0", False)
        def _(d, value=value):
            s = scene(d)
            return _run(["evaluate", s, "-o", d / "ev", "--baseline-threshold", value,
                         "--no-progress", "--bootstrap", "0"], s)  # fmt: skip

    # converters: tracebacks and exit 0 on bad values
    def commonroad(d, xml: str):
        x = d / "c.xml"
        x.write_text(xml)
        return _run(["convert", "commonroad", x, "-o", d / "o.mcap"], x)

    for name, old, new in (
        ("commonroad-lanelet-point-inf", "<x>50</x><y>2</y>", "<x>inf</x><y>2</y>"),
        ("commonroad-lanelet-point-nan", "<x>50</x><y>2</y>", "<x>nan</x><y>2</y>"),
        ("commonroad-successor-abc", '<successor ref="2"/>', '<successor ref="abc"/>'),
        ("commonroad-time-step-1e300", 'timeStepSize="0.1"', 'timeStepSize="1e300"'),
        ("commonroad-obstacle-id-abc", '<dynamicObstacle id="7">', '<dynamicObstacle id="x7">'),
        ("commonroad-lane-point-2^62", "<x>150</x><y>2</y>", f"<x>{2**62}</x><y>2</y>"),
    ):  # fmt: skip

        @add(f"converter-{name}", "converter")
        def _(d, old=old, new=new):
            xml = scenario_xml()
            assert old in xml, old
            return commonroad(d, xml.replace(old, new, 1))

    def av2(d, change):
        p = av2_write_scenario(d / "sc")
        df = change(av2_rows().with_columns(pl.lit("tiny-0001").alias("scenario_id")))
        df.write_parquet(p)
        return _run(["convert", "av2", d / "sc", "-o", d / "o.mcap"], p)

    for name, change in (
        ("position-abc", lambda df: df.with_columns(
            pl.col("position_x").cast(pl.String).set(0, "abc") if False else
            pl.when(pl.col("timestep") == 3).then(pl.lit("abc"))
            .otherwise(pl.col("position_x").cast(pl.String)).alias("position_x"))),
        ("track-id-null", lambda df: df.with_columns(pl.lit(None, pl.String).alias("track_id"))),
        ("start-timestamp-text", lambda df: df.with_columns(pl.lit("soon").alias("start_timestamp"))),
        ("timestep-strings", lambda df: df.with_columns(pl.col("timestep").cast(pl.String))),
    ):  # fmt: skip

        @add(f"converter-av2-{name}", "converter")
        def _(d, change=change):
            return av2(d, change)

    def interaction(d, edit_csv=None, edit_osm=None):
        csv, osm = d / "t.csv", d / "m.osm"
        text = vehicle_csv()
        csv.write_text(edit_csv(text) if edit_csv else text)
        o = osm_text()
        osm.write_text(edit_osm(o) if edit_osm else o)
        return _run(["convert", "interaction", csv, "--map", osm, "-o", d / "o.mcap"], csv, osm)

    def frame_id(value: str, ms: str, line: int = 3):
        """Car 1's row on ``line`` moved to frame ``value`` at ``ms`` (consistent)."""

        def edit(text):
            lines = text.splitlines()
            cells = lines[line].split(",")
            cells[1], cells[2] = value, ms
            lines[line] = ",".join(cells)
            return "\n".join(lines) + "\n"

        return edit

    def lat(value):
        def edit(text):
            import re

            return re.sub(r'lat="[^"]*"', f'lat="{value}"', text, count=1)

        return edit

    def quoted_newline(text):
        lines = text.splitlines()
        cells = lines[3].split(",")
        cells[3] = '"ca\nr"'
        lines[3] = ",".join(cells)
        return "\n".join(lines) + "\n"

    for name, kwargs in (
        ("frame-id-fractional", {"edit_csv": frame_id("2.5", "250")}),
        ("frame-id-9e6", {"edit_csv": frame_id("9000000", "900000000", line=5)}),
        ("quoted-newline", {"edit_csv": quoted_newline}),
        ("osm-lat-north", {"edit_osm": lat("north")}),
        ("osm-lat-1e300", {"edit_osm": lat("1e300")}),
    ):  # fmt: skip

        @add(f"converter-interaction-{name}", "converter")
        def _(d, kwargs=kwargs):
            return interaction(d, **kwargs)

    @add("converter-inspect-format-version-5000-digits", "converter")
    def _(d):
        from converters.scene.reader import read_scene
        from converters.scene.writer import SceneWriter

        s = scene(d)
        meta = {"converter": "test"}
        good = read_scene(s)
        w = SceneWriter(d / "v.mcap", good.map, frame_period_s=good.frame_period_s,
                        metadata=meta)  # fmt: skip
        for f in good.frames:
            w.add_frame(f)
        w._final_metadata = lambda: {  # type: ignore[method-assign]
            "format_version": "9" * 5000, "frame_period_s": str(good.frame_period_s),
            "converter": "test",
        }  # fmt: skip
        w.close()
        s.unlink()
        return _run(["inspect", d / "v.mcap"], d / "v.mcap")

    @add("exit0-scene-lane-point-2^62-mm", "exit-0")
    def _(d):
        def far(m):
            m.lanes[0].x_mm[0] = 2**62

        s = without_statistics(scene(d, ".ok.mcap"), d / "far.mcap", statistics=True,
                               edit_map=far)  # fmt: skip
        (d / ".ok.mcap").unlink()
        return _run(["run", s, "--no-rrd", "--table", d / "t.parquet", "--no-progress"], s)

    @add("message-cut-parquet", "foreign")
    def _(d):
        t = table(d)
        t.write_bytes(t.read_bytes()[: t.stat().st_size // 2])
        return _stats(t, d)

    return out


# ---------------------------------------------------------------------- running
def _snapshot(folder: pathlib.Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def session_members(sid: int) -> list[int]:
    """Processes of session ``sid`` still alive (zombies excluded)."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        state, session = fields[0], int(fields[3])
        if session == sid and state != "Z":
            found.append(int(entry))
    return found


def run_cli(
    args: list[str], cwd: pathlib.Path, time_limit_s: float = TIME_LIMIT_S
) -> tuple[int | None, str, str, float, list[int]]:
    """Run ``replay ARGS`` in a new session; ``(returncode or None if killed for the time
    limit, stdout, stderr, seconds, survivors of its session)``."""
    env = {**os.environ, "COLUMNS": "200"}
    start = time.monotonic()
    proc = subprocess.Popen(
        [*REPLAY, *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, start_new_session=True, env=env,
    )  # fmt: skip
    try:
        out, err = proc.communicate(timeout=time_limit_s)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        code = None
    seconds = time.monotonic() - start
    deadline = time.monotonic() + 3.0
    survivors = session_members(proc.pid)
    while survivors and time.monotonic() < deadline:
        time.sleep(0.1)
        survivors = session_members(proc.pid)
    for pid in survivors:  # never leave them running, but report them
        os.kill(pid, signal.SIGKILL)
    return code, out, err, seconds, survivors


def run_case(case: Case, folder: pathlib.Path, time_limit_s: float = TIME_LIMIT_S) -> Outcome:
    folder.mkdir(parents=True, exist_ok=True)
    args, inputs = case.make(folder)
    sums = {p: sha256(p) for p in inputs}
    before = _snapshot(folder)
    code, _out, err, seconds, survivors = run_cli(args, folder, time_limit_s)
    errors = [line for line in err.splitlines() if line.startswith("Error:")]
    changed = [str(p) for p, s in sums.items() if not p.exists() or sha256(p) != s]
    leftovers = sorted(_snapshot(folder) - before)
    return Outcome(
        case=case.name, kind=case.kind, returncode=code, stderr=err, seconds=seconds,
        hung=code is None, traceback="Traceback (most recent call last)" in err,
        error_lines=errors, inputs_changed=changed, leftovers=leftovers, survivors=survivors,
    )  # fmt: skip


def run_case_in_process(case: Case, folder: pathlib.Path) -> Outcome:
    """:func:`run_case` through click's ``CliRunner`` in this process (no interpreter start:
    fast). An exception other than ``SystemExit`` counts as a traceback; hangs and
    surviving processes are not observable here (the subprocess runner sees them)."""
    from click.testing import CliRunner

    from replay.cli.app import main

    folder.mkdir(parents=True, exist_ok=True)
    args, inputs = case.make(folder)
    sums = {p: sha256(p) for p in inputs}
    before = _snapshot(folder)
    cwd = os.getcwd()
    start = time.monotonic()
    try:
        os.chdir(folder)
        result = CliRunner().invoke(main, args)
    finally:
        os.chdir(cwd)
    err = result.stderr if result.stderr_bytes is not None else result.output
    crashed = result.exception is not None and not isinstance(result.exception, SystemExit)
    return Outcome(
        case=case.name, kind=case.kind, returncode=result.exit_code, stderr=err,
        seconds=time.monotonic() - start, hung=False, traceback=crashed,
        error_lines=[line for line in err.splitlines() if line.startswith("Error:")],
        inputs_changed=[str(p) for p, s in sums.items() if not p.exists() or sha256(p) != s],
        leftovers=sorted(_snapshot(folder) - before),
    )  # fmt: skip
