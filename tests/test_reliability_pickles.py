"""Pickles that cannot hurt (issue 36): the safe loader under hostile files.

The measured cases (a 158-byte object array that segfaulted numpy, a nested tuple key that
overflowed the C stack, a 64-level shared tuple key that hashed for ever, a 40-level
shared list whose ``str()`` flooded memory) and 300 generated ones of the same kinds run
in a child process, so that a crash fails the test instead of killing the suite; each must
load or be refused with one line, within 1 s and with the child under 1 GiB. Real
scenarios re-pickled in every protocol 0-5 load back identical.
"""

from __future__ import annotations

import json
import os
import pathlib
import pickle
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from click.testing import CliRunner
from hostile_pickles import measured, object_array

from converters import safe_pickle
from converters.errors import ConversionError
from replay.cli.app import main

TESTS = pathlib.Path(__file__).resolve().parent
REAL = TESTS.parent / ".." / "shared" / "data" / "scenarionet"

_CHILD = textwrap.dedent(
    """
    import json, resource, sys, time
    sys.path[:0] = [{tests!r}, {root!r}]
    from hostile_pickles import measured, generated
    from converters import safe_pickle
    from converters.errors import ConversionError
    out = {{}}
    for name, data in measured() + generated({count}):
        start = time.monotonic()
        try:
            safe_pickle.loads(data, where=name)
            result = "loaded"
        except ConversionError as exc:
            result = str(exc)
        out[name] = [result, time.monotonic() - start]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({{"cases": out, "peak_bytes": peak}}))
    """
)


def _run_child(count: int) -> dict:
    code = _CHILD.format(tests=str(TESTS), root=str(TESTS.parent), count=count)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"the loader crashed: {proc.returncode} {proc.stderr[-800:]}"
    return json.loads(proc.stdout)


@pytest.fixture(scope="module")
def hostile_outcomes() -> dict:
    return _run_child(300)


def test_the_measured_hostile_pickles_are_refused_in_one_line(hostile_outcomes):
    cases = hostile_outcomes["cases"]
    for name, _ in measured():
        result, seconds = cases[name]
        assert result != "loaded", name
        assert result.startswith(f"{name}: ") and "\n" not in result, result
        assert seconds < 1.0, (name, seconds)
    assert "whose state holds 3 items" in cases["object-array-claims-1e6-holds-3"][0]
    assert "nests deeper than" in cases["dict-key-tuple-nested-100000"][0]
    assert "shared parts counted" in cases["frozenset-key-shared-tuple-64"][0]
    assert "shared parts counted" in cases["list-shared-40"][0]
    assert "container holds itself" in cases["list-holds-itself"][0]
    assert "after placing it inside another" in cases["list-grows-after-use"][0]
    assert "dict key or set item is a list" in cases["dict-keyed-by-list"][0]


def test_300_generated_hostile_pickles_end_in_time_and_memory(hostile_outcomes):
    """No crash (the child lived), no hang: every case within 1 s (wall, on a shared
    machine) and the whole child below 1 GiB; every refusal one line naming the case."""
    cases = hostile_outcomes["cases"]
    assert len(cases) >= 300 + len(measured())
    slow = {n: s for n, (_, s) in cases.items() if s >= 1.0}
    assert not slow, slow
    assert hostile_outcomes["peak_bytes"] < 2**30
    for name, (result, _) in cases.items():
        assert result == "loaded" or (result.startswith(f"{name}: ") and "\n" not in result)
    refused = sum(r != "loaded" for r, _ in cases.values())
    assert refused >= 290  # a damaged copy may still be a valid pickle


def test_the_limits_can_fail():
    """Each bound refuses just above its limit and accepts at it."""
    from hostile_pickles import nested_list, shared_list

    safe_pickle.loads(nested_list(safe_pickle.MAX_DEPTH))
    with pytest.raises(ConversionError, match="nests deeper"):
        safe_pickle.loads(nested_list(safe_pickle.MAX_DEPTH + 2))
    safe_pickle.loads(shared_list(20))  # 2**21 items: under the bound
    with pytest.raises(ConversionError, match="shared parts"):
        safe_pickle.loads(shared_list(23))
    value = {"k": np.arange(3, dtype=object)}
    assert safe_pickle.loads(pickle.dumps(value))["k"].tolist() == [0, 1, 2]
    with pytest.raises(ConversionError, match="holds 3 items"):
        safe_pickle.loads(object_array(4, 3))


@pytest.mark.parametrize("protocol", range(6))
def test_plain_values_load_in_every_protocol(protocol):
    value = {
        "bytes": b"ab\x00\xff", "bytearray": bytearray(b"xy"), "complex": 1 + 2j,
        "frozenset": frozenset({1, "a"}), "set": {(1, 2), None},
        "f4": np.arange(6, dtype=np.float32).reshape(2, 3), "b1": np.array([True, False]),
        "fortran": np.asfortranarray(np.ones((2, 3))), "strided": np.ones((4, 4))[::2],
        "text": np.array(["ab", "c"]), "scalar": np.array(3.0),
        "objects": np.array([1, "a", None], dtype=object), "nested": [1, (2, [3.5, "x"])],
    }  # fmt: skip
    got = safe_pickle.loads(pickle.dumps(value, protocol=protocol))
    for key, want in value.items():
        if isinstance(want, np.ndarray):
            assert got[key].dtype == want.dtype and got[key].shape == want.shape, key
            assert got[key].tolist() == want.tolist(), key
        else:
            assert got[key] == want and type(got[key]) is type(want), key


def _same(a, b) -> None:
    if isinstance(a, dict):
        assert type(b) is dict and list(a) == list(b)
        for k in a:
            _same(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _same(x, y)
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b)
        assert a.dtype == b.dtype
    else:
        assert a == b or (a != a and b != b)


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/scenarionet is absent")
def test_real_scenarios_load_back_in_every_protocol():
    """What ScenarioNet files use, pickled by Python 3.14's default (5) or an old one."""
    for path in sorted(REAL.rglob("sd_*.pkl"))[:3]:
        sd = safe_pickle.load(path)
        for protocol in range(6):
            _same(sd, safe_pickle.loads(pickle.dumps(sd, protocol=protocol)))


def test_batch_keeps_the_good_scenario_beside_a_hostile_one(tmp_path):
    """The 158-byte pickle beside a good scenario: the good one is converted and
    replayed, the bad one is one failure line; a stray pickle that is no scenario is
    named too (issue 36)."""
    from test_convert_scenarionet import scenario

    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "good.pkl").write_bytes(pickle.dumps(scenario()))
    (folder / "bad.pkl").write_bytes(object_array(10**6, 3))
    result = CliRunner().invoke(
        main, ["batch", str(folder), "-o", str(tmp_path / "out"), "--no-progress"]
    )
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    assert "in/bad [convert] ConversionError" in result.output
    assert "whose state holds 3 items" in result.output
    assert list((tmp_path / "out" / "scenes").rglob("*.mcap")), result.output


def test_batch_names_a_stray_pickle_it_does_not_read(tmp_path):
    from replay.batch.driver import discover

    (tmp_path / "notes.pkl").write_bytes(pickle.dumps({"x": 1}))
    (tmp_path / "s.mcap").write_bytes(b"")
    found = discover([tmp_path])
    stray = [f for f in found if f.path.name == "notes.pkl"]
    assert stray and stray[0].problem and "notes.pkl" in stray[0].problem
    assert "\n" not in stray[0].problem


#: Put on the path of a child: in every process, loading a file whose name starts with
#: "crash" kills that process with SIGSEGV, as a loader bug would.
_CRASH_ON_LOAD = """
import os
if os.environ.get("RISKREPLAY_TEST_CRASH"):
    import converters.safe_pickle as _sp
    _load = _sp.load
    def load(path, **options):
        if os.path.basename(str(path)).startswith("crash"):
            os.kill(os.getpid(), 11)
        return _load(path, **options)
    _sp.load = load
"""


def test_a_crash_while_loading_one_scenario_loses_not_the_others(tmp_path):
    """Crashes are made impossible by the loader's checks; should one happen anyway, it
    ends the forked child that loads that file: ``batch`` reports that scenario in one
    line and converts and replays the good one beside it (a worker's death lost both)."""
    from test_convert_scenarionet import scenario

    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "good.pkl").write_bytes(pickle.dumps(scenario()))
    (folder / "crash.pkl").write_bytes(pickle.dumps(scenario(id="other")))
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_CRASH_ON_LOAD)
    root = str(TESTS.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(hook), root]),
           "RISKREPLAY_TEST_CRASH": "1"}  # fmt: skip
    done = subprocess.run(
        [sys.executable, "-m", "replay", "batch", str(folder), "-o", str(tmp_path / "out"),
         "--no-progress", "--workers", "1"],
        capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600,
    )  # fmt: skip
    assert "Traceback" not in done.stderr, done.stderr
    assert "crash.pkl: reading it stopped the loader's process (signal SIGSEGV)" in done.stdout
    assert "replayed 1" in done.stdout, done.stdout
    assert [p.name for p in (tmp_path / "out" / "scenes").rglob("*.mcap")] == ["hand-1.mcap"]


@pytest.mark.parametrize("protocol", range(6))
def test_a_scenario_in_any_protocol_is_recognised_and_converted(tmp_path, protocol):
    """``batch`` finds scenarios by their first bytes: protocols 0 and 1 have no PROTO
    opcode (they start with MARK or EMPTY_DICT) and were not recognised."""
    from test_convert_scenarionet import scenario

    from converters import scenarionet

    path = tmp_path / "s.pkl"
    path.write_bytes(pickle.dumps(scenario(), protocol=protocol))
    assert scenarionet.is_scenario_file(path)
    scene = scenarionet.read_scene(path)
    assert scene.frames
