"""Round 4 of the reliability cases (issue 36): hostile pickles through the converter,
label columns that are not booleans, NaN and idle options, a scenario too long to convert,
and the smaller messages. :func:`round4_cases` is added to ``reliability_cases.cases()``;
``generated`` hostile pickles of the measured kinds join them (the census runs 300).
"""

from __future__ import annotations

import pathlib
import pickle

import numpy as np
import polars as pl
from hostile_pickles import generated, measured
from reliability_cases import Case, _run, scene, table
from test_convert_commonroad import scenario_xml
from test_convert_scenarionet import scenario


def _pickle_case(name: str, data: bytes) -> Case:
    def make(d: pathlib.Path, data: bytes = data):
        p = d / "bad.pkl"
        p.write_bytes(data)
        return _run(["convert", "scenarionet", p, "-o", d / "out.mcap", "--no-progress"], p)

    return Case(f"pickle-{name}", "pickle", make)


def _labelled(d: pathlib.Path, column: str, values: pl.Series, suffix: str = ".parquet"):
    """A real agents table with ``column`` replaced by ``values`` (cycled to its height)."""
    t = table(d, ".t.parquet")
    df = pl.read_parquet(t)
    t.unlink()
    reps = -(-df.height // len(values))
    df = df.with_columns(pl.concat([values] * reps)[: df.height].alias(column))
    path = d / f"tab{suffix}"
    if suffix == ".csv":
        df.write_csv(path)
    else:
        df.write_parquet(path)
    return path


def round4_cases(generated_count: int = 30) -> list[Case]:
    out: list[Case] = [_pickle_case(name, data) for name, data in measured()]
    structural = [(n, d) for n, d in generated(generated_count * 3 // 2) if "damaged" not in n]
    out += [_pickle_case(f"generated-{n}", d) for n, d in structural[:generated_count]]

    def add(name: str, kind: str, names_file: bool = True):
        def deco(make):
            out.append(Case(name, kind, make, names_file))
            return make

        return deco

    # label columns that are not booleans: one error naming the column
    for column, label, values in [
        ("planner_label", "words", pl.Series(["yes", "no"])),
        ("planner_label", "lists", pl.Series([[1], [0]])),
        ("planner_label", "two", pl.Series([2, 0])),
        ("planner_label", "nan", pl.Series([float("nan"), 1.0])),
        ("label_objects_of_interest", "words", pl.Series(["maybe", "true"])),
        ("label_objects_of_interest", "floats", pl.Series([0.5, 1.0])),
    ]:

        @add(f"label-{column}-{label}", "label")
        def _(d, column=column, values=values):
            t = _labelled(d, column, values)
            return _run(["evaluate", t, "-o", d / "ev", "--bootstrap", "0", "--no-plots",
                         "--no-progress"], t)  # fmt: skip

    @add("label-planner_label-words-csv", "label")
    def _(d):
        t = _labelled(d, "planner_label", pl.Series(["yes", "no"]), ".csv")
        return _run(["evaluate", t, "-o", d / "ev", "--bootstrap", "0", "--no-plots",
                     "--no-progress"], t)  # fmt: skip

    # NaN where a number is expected, options that do nothing here (usage errors)
    for cmd, option, value in [
        ("plan", "--horizon", "nan"), ("plan", "--tolerance", "nan"),
        ("plan", "--tolerance", "inf"), ("evaluate", "--truth-horizon", "nan"),
        ("evaluate", "--truth-gap", "-inf"), ("evaluate", "--truth-coverage", "nan"),
        ("calibrate", "--max-fn-rate", "nan"),
    ]:  # fmt: skip

        @add(f"option-{cmd}{option}-{value}", "option", names_file=False)
        def _(d, cmd=cmd, option=option, value=value):
            s = scene(d)
            return _run([cmd, s, "-o", d / "out", option, value, "--no-progress"], s)

    @add("option-convert-waymo-margin-nan", "option", names_file=False)
    def _(d):
        p = d / "w.tfrecord"
        p.write_bytes(b"")
        return _run(["convert", "waymo", p, "-o", d / "out", "--margin-m", "nan"], p)

    for cmd, option, value in [
        ("plan", "--closed-loop-sample", "3"), ("plan", "--closed-loop-egos", "2"),
        ("evaluate", "--sensitivity-scenes", "2"), ("evaluate", "--sensitivity-bootstrap", "5"),
        ("evaluate", "--report-note", "hello"),
    ]:  # fmt: skip

        @add(f"idle-{cmd}{option}", "option", names_file=False)
        def _(d, cmd=cmd, option=option, value=value):
            s = scene(d)
            return _run([cmd, s, "-o", d / "out", option, value, "--no-progress"], s)

    @add("same-path-evaluate-report-is-the-summary", "same-path")
    def _(d):
        s = scene(d)
        return _run(["evaluate", s, "-o", d / "ev", "--report", d / "ev" / "summary.json",
                     "--bootstrap", "0", "--no-progress"], s)  # fmt: skip

    # the smaller ones: messages that name what is wrong and what to do
    @add("same-path-run-o-and-table-one-file", "same-path")
    def _(d):
        s = scene(d)
        return _run(["run", s, "-o", d / "out", "--table", d / "out", "--no-progress"], s)

    for cmd in ("evaluate", "experiment", "plan", "convert-synthetic-situations"):

        @add(f"unwritable-{cmd}-output-under-a-file", "unwritable")
        def _(d, cmd=cmd):
            s = scene(d)
            (d / "afile").write_text("x")
            target = d / "afile" / "out"
            args = {
                "evaluate": ["evaluate", s, "-o", target, "--bootstrap", "0"],
                "experiment": ["experiment", "-o", target],
                "plan": ["plan", s, "-o", target],
                "convert-synthetic-situations": ["convert", "synthetic", "--situations", "2",
                                                 "-o", target],
            }[cmd]  # fmt: skip
            return _run([*args, "--no-progress"], s, d / "afile")

    @add("option-run-every-1e-9s", "option", names_file=False)
    def _(d):
        s = scene(d)
        return _run(["run", s, "--every", "1e-9s", "--no-rrd", "--table", d / "t.parquet",
                     "--no-progress"], s)  # fmt: skip

    @add("converter-commonroad-predecessor-ref-text", "converter")
    def _(d):
        x = d / "c.xml"
        x.write_text(scenario_xml().replace('<predecessor ref="1"/>', '<predecessor ref="one"/>'))
        return _run(["convert", "commonroad", x, "-o", d / "o.mcap"], x)

    @add("message-set-key-5000-characters", "option", names_file=False)
    def _(d):
        s = scene(d)
        return _run(["run", s, "--set", "survival." + "w" * 5000 + "=1", "--no-progress"], s)

    # a scenario whose step count passes the file-size check but not the memory one
    @add("steps-scenarionet-2e6", "memory")
    def _(d):
        sd = scenario()
        sd["metadata"]["ts"] = np.arange(2_000_000) * 0.1
        p = d / "long.pkl"
        p.write_bytes(pickle.dumps(sd))
        return _run(["convert", "scenarionet", p, "-o", d / "out.mcap", "--no-progress"], p)

    return out
