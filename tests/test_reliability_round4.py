"""Reliability round 4 (issue 36), the cases that are not one bad command line: the
Python API's checks, the option audit over every command, filters given with a matched
cut, valid label columns still read, and the AOT build key.

The command-line cases (hostile pickles, label columns, NaN and idle options, a scenario
too long) are in ``reliability_round4.py`` and run with the others in
``test_reliability.py``; the loader's own bounds in ``test_reliability_pickles.py``.
"""

from __future__ import annotations

import json

import click
import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from reliability_cases import scene, table

import risk
from replay.cli.app import main
from replay.cli.limits import FiniteRange
from risk.errors import FrameError, RiskError

# ---------------------------------------------------------------------- the Python API
TWO = dict(
    xy=np.array([[0.0, 0.0], [10.0, 0.0]]), heading=[0.0, 0.0], speed=[1.0, 1.0],
    length=[4.0, 4.0], width=[2.0, 2.0],
    paths=[np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([[10.0, 0.0], [11.0, 0.0]])], ego=0,
)  # fmt: skip


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        ({"valid": ["yes", "no"]}, "valid", "expected booleans, got text"),
        ({"valid": [2, 1]}, "valid", "expected booleans"),
        ({"ids": [1.5, 2]}, "ids", "expected integers, got fractions"),
        ({"ids": [2**64, 1]}, "ids", "integers beyond 64 bits"),
        ({"ids": [2**63, 1]}, "ids", "outside the int64 range"),
        ({"ego": True}, "ego", "an agent index"),
        ({"ego": 1.0}, "ego", "an agent index"),
        ({"t": "noon"}, "t", "a number of seconds"),
        ({"speed": ["a", "b"]}, "speed", "expected numbers, got text"),
        ({"xy": [["a", "b"], ["c", "d"]]}, "xy", "expected numbers, got text"),
        ({"heading": [0.0, None]}, "heading", "Python objects"),
        ({"kinds": [99, 0]}, "kinds", "unknown kind code"),
        ({"kinds": ["car", "vehicle"]}, "kinds", "unknown kind 'car'"),
        ({"paths": [np.zeros((10**6, 2)), [np.zeros((2, 2))] * 30]}, "paths", "resample"),
    ],
)
def test_the_api_refuses_what_it_used_to_coerce_naming_the_field(change, field, words):
    with pytest.raises(FrameError) as err:
        risk.Frame.from_arrays(**{**TWO, **change})
    assert err.value.field == field and words in str(err.value), str(err.value)
    assert isinstance(err.value, RiskError) and "\n" not in str(err.value)


def test_the_api_still_takes_plain_equivalents():
    """Integral floats as ids, 0/1 as flags, numpy integers as the ego: unchanged."""
    frame = risk.Frame.from_arrays(
        **{**TWO, "ego": np.int64(0)}, ids=[7.0, 9.0], valid=[1, 1], t=np.float32(0.5)
    )
    assert frame.ids.tolist() == [7, 9] and frame.valid.all()


# ---------------------------------------------------------------------- options
def _commands(group: click.Group, ctx: click.Context, path=()):
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, ctx, (*path, name))
        elif cmd is not None:
            yield (*path, name), cmd


def test_every_number_option_refuses_nan_and_infinity():
    """The audit: no float option of any command is a plain click float (it lets NaN in)."""
    ctx = click.Context(main)
    plain = [
        f"{' '.join(path)} {p.opts[0]}"
        for path, cmd in _commands(main, ctx)
        for p in cmd.params
        if isinstance(p.type, click.types.FloatParamType) and not isinstance(p.type, FiniteRange)
    ]
    assert plain == []
    with pytest.raises(click.BadParameter):
        FiniteRange(min=0.0).convert("nan", None, None)


def test_nearest_match_beside_the_same_explicit_cut_is_accepted(tmp_path):
    """``--filter nearest:match --filter nearest:1`` was refused as "given twice" (the
    early check filled match with 1); a matched cut equal to a given one is that filter."""
    s = scene(tmp_path)
    out = tmp_path / "out"
    result = CliRunner().invoke(main, [
        "plan", str(s), "-o", str(out), "--filter", "nearest:match", "--filter", "nearest:1",
        "--no-plots", "--no-progress", "--workers", "1",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    filters = json.loads((out / "summary.json").read_text())["planners"]["idm"]["filters"]
    assert "nearest:1" in filters


# ---------------------------------------------------------------------- label columns
def test_label_columns_of_words_nulls_and_booleans_are_read(tmp_path):
    """A CSV's true/false words with gaps, and an all-null column, still evaluate."""
    t = table(tmp_path, ".t.parquet")
    df = pl.read_parquet(t)
    words = pl.Series("planner_label", ["true", "false", None] * df.height)[: df.height]
    df = df.with_columns(words, pl.lit(None).alias("label_objects_of_interest"))
    csv = tmp_path / "tab.csv"
    df.write_csv(csv)
    result = CliRunner().invoke(main, [
        "evaluate", str(csv), "-o", str(tmp_path / "ev"), "--bootstrap", "0", "--no-plots",
        "--no-progress",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output


# ---------------------------------------------------------------------- the AOT build key
def test_the_aot_build_key_follows_the_cpu_numba_is_asked_for(monkeypatch):
    """A module built for the host must not be loaded by a process asked for generic code
    (NUMBA_CPU_NAME / NUMBA_CPU_FEATURES), nor the other way round; the build compiles
    for the CPU named."""
    from risk import kernel_aot

    for name in kernel_aot.CPU_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    host = kernel_aot.build_key()
    assert kernel_aot.target_cpu() == "host"
    monkeypatch.setenv("NUMBA_CPU_NAME", "generic")
    generic = kernel_aot.build_key()
    assert generic != host and kernel_aot.target_cpu() == "generic"
    monkeypatch.setenv("NUMBA_CPU_FEATURES", "+sse2")
    assert kernel_aot.build_key() not in (host, generic)


# ---------------------------------------------------------------------- the smaller ones
def test_a_full_stdout_after_the_outputs_says_what_was_kept(tmp_path):
    """``replay run -o out.rrd > /dev/full``: the recording is complete and kept, and the
    error says so (it said only "cannot write to standard output")."""
    import subprocess

    from reliability_cases import REPLAY

    s = scene(tmp_path)
    with open("/dev/full", "wb") as full:
        done = subprocess.run(
            [*REPLAY, "run", str(s), "-o", "out.rrd", "--no-progress"], cwd=tmp_path,
            stdout=full, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
    assert done.returncode == 1, done.stderr
    errors = [ln for ln in done.stderr.splitlines() if ln.startswith("Error:")]
    assert len(errors) == 1 and "standard output" in errors[0], done.stderr
    assert "complete and kept: out.rrd" in errors[0]
    assert (tmp_path / "out.rrd").stat().st_size > 0


def test_two_outputs_onto_one_file_name_their_options(tmp_path):
    import subprocess

    from reliability_cases import REPLAY

    s = scene(tmp_path)
    done = subprocess.run(
        [*REPLAY, "run", str(s), "-o", "out", "--table", "out", "--no-progress"],
        cwd=tmp_path, capture_output=True, text=True,
    )  # fmt: skip
    assert "(-o and --table)" in done.stderr, done.stderr


def test_a_very_long_scenario_id_makes_a_short_file_name(tmp_path):
    """A 300-character id failed with "File name too long": cut, with a hash."""
    import pickle

    from test_convert_scenarionet import scenario

    from outputs.atomic import MAX_STEM, safe_name

    for k, long_id in enumerate(["x" * 300, "x" * 299 + "y"]):
        sd = scenario(id=long_id)
        sd["metadata"]["scenario_id"] = long_id
        (tmp_path / f"{k}.pkl").write_bytes(pickle.dumps(sd))
    out = tmp_path / "out"
    result = CliRunner().invoke(
        main, ["convert", "scenarionet", str(tmp_path), "-o", str(out), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in out.iterdir())
    assert len(names) == 2 and all(len(n) <= MAX_STEM + 10 for n in names), names
    assert safe_name("x" * 300) != safe_name("x" * 299 + "y")  # the hash keeps them apart
    assert safe_name("short id") == "short_id"


def test_a_map_the_writer_refuses_names_the_file(tmp_path):
    from converters.errors import ConversionError
    from converters.scene.writer import SceneWriter
    from risk.frame import Lane, LaneMap

    bad = LaneMap(lanes=(Lane(0, np.array([[0.0, 0.0], [np.nan, 1.0]])),))
    with pytest.raises(ConversionError, match=r"x\.mcap: the map: lane 0: centre line"):
        SceneWriter(tmp_path / "x.mcap", bad, frame_period_s=0.1)
    assert list(tmp_path.iterdir()) == []


def test_error_lines_are_capped_keeping_start_and_end():
    from replay.cli.app import MAX_ERROR_CHARS, capped

    line = capped("start " + "9" * 5000 + " what to do")
    assert len(line) == MAX_ERROR_CHARS and line.startswith("start 999")
    assert line.endswith(" what to do") and " … " in line
    assert capped("a\nb  c") == "a b c"


# ---------------------------------------------------------------------- generated inputs
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_ODD_VALUES = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70), st.floats(allow_nan=True),
    st.booleans(), st.text(max_size=4), st.none(), st.binary(max_size=3),
    st.lists(st.integers(0, 3), max_size=2),
)  # fmt: skip
_FIELDS = ("xy", "heading", "speed", "length", "width", "ids", "kinds", "valid", "ego", "t")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(field=st.sampled_from(_FIELDS), values=st.lists(_ODD_VALUES, min_size=0, max_size=3),
       scalar=_ODD_VALUES, as_scalar=st.booleans())  # fmt: skip
def test_the_api_under_300_generated_odd_inputs_raises_only_frame_errors(
    field, values, scalar, as_scalar
):
    """Any mix of odd values in any field: a frame, or a FrameError naming that field;
    never numpy's or Python's own exception, never a silent coercion of text or None."""
    change = {field: scalar if as_scalar or field in ("ego", "t") else values}
    if change[field] is None and field in ("ids", "kinds", "valid"):
        return  # (None: the documented default)
    try:
        frame = risk.Frame.from_arrays(**{**TWO, **change})
    except FrameError as exc:
        assert exc.field in (field, "paths", "valid", "ego"), (exc.field, field, str(exc))
        return
    given_values = [scalar] if as_scalar or field in ("ego", "t") else values
    flat = [x for v in given_values for x in (v if isinstance(v, list) else [v])]
    text_ok = (str,) if field == "kinds" else ()  # (kinds may be names: "vehicle")
    odd = (bytes, type(None)) if text_ok else (str, bytes, type(None))
    assert not any(isinstance(v, odd) for v in flat), frame
