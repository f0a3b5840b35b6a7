"""The clock check (converters.clock): a scene's time step against its motion.

Hand-made tracks with a known factor (positions moving 5x / 2x what their recorded speeds
allow at the labelled step) are corrected and recorded; a consistent scene is untouched;
noisy data without a clean factor converts with a warning naming its bad rows; the CLI's
``--time-step`` and ``inspect --check``; real SinD and highD files; and a property: a
consistent scene whose time base is scaled by a clean factor k is found off by k.
"""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from converters import commonroad
from converters.clock import (
    BAD_ROW_LIMIT,
    CLEAN_FACTORS,
    Motion,
    accel_steps,
    check_motion,
    clean_factor,
    motion_from_frames,
    parse_time_step,
    window_steps,
)
from converters.errors import ConversionError
from converters.lanegraph import PathSettings
from converters.scene.reader import read_scene as read_mcap
from converters.tracks import TrackTable, build_scene
from replay.cli.app import main
from risk.frame import Kind, LaneMap

V, P, C = int(Kind.VEHICLE), int(Kind.PEDESTRIAN), int(Kind.CYCLIST)


# ---------------------------------------------------------------------- hand-made tracks
def tracks(
    speeds: list[float],
    *,
    factor: float = 1.0,
    n_steps: int = 60,
    step_s: float = 0.1,
    kinds: list[int] | None = None,
    turn_rad_s: float = 0.0,
    noise_m: float = 0.0,
    seed: int = 0,
) -> TrackTable:
    """Agents driving at the recorded ``speeds`` (constant), whose positions move
    ``factor`` times as far per labelled step ``step_s`` as those speeds allow (a file
    whose true step is ``factor * step_s``); optionally turning and with position noise."""
    n = len(speeds)
    rng = np.random.default_rng(seed)
    v = np.asarray(speeds, dtype=float)
    true_t = np.arange(n_steps)[:, None] * step_s * factor  # (T, 1)
    start_heading = rng.uniform(-math.pi, math.pi, n)
    heading = start_heading + turn_rad_s * true_t  # (T, N)
    if abs(turn_rad_s) > 1e-6:
        radius = v / turn_rad_s
        x = radius * (np.sin(heading) - np.sin(start_heading))
        y = -radius * (np.cos(heading) - np.cos(start_heading))
    else:
        x, y = v * true_t * np.cos(heading), v * true_t * np.sin(heading)
    xy = np.stack([x + 50.0 * np.arange(n), y], axis=2)
    xy = xy + rng.normal(0.0, noise_m, xy.shape) if noise_m else xy
    shape = (n_steps, n)
    return TrackTable(
        ids=np.arange(1, n + 1, dtype=np.int64),
        kinds=np.array(kinds or [V] * n, dtype=np.int8),
        t_s=np.arange(n_steps) * step_s,
        xy=xy,
        heading=heading,
        speed=np.broadcast_to(v, shape).copy(),
        length=np.full(shape, 4.0),
        width=np.full(shape, 2.0),
        valid=np.ones(shape, dtype=bool),
    )


def motion(table: TrackTable, measured: bool = True) -> Motion:
    return Motion(
        table.t_s, table.xy, table.heading, table.speed, table.valid, table.kinds,
        np.full(table.valid.shape, measured),
    )  # fmt: skip


def scene_of(table: TrackTable, time_step: str | float = "auto", step_s: float = 0.1):
    return build_scene(
        table, 0, LaneMap(), paths="hindsight", settings=PathSettings(),
        frame_period_s=step_s, metadata={"dataset": "test"}, source="hand.xml",
        time_step=time_step,
    )  # fmt: skip


SPEEDS = [8.0, 12.0, 5.0, 15.0, 3.0, 10.0]


@pytest.mark.parametrize("factor", [5.0, 2.0])
def test_a_clean_factor_is_corrected_and_recorded(factor):
    scene = scene_of(tracks(SPEEDS, factor=factor))
    meta = scene.metadata
    assert scene.frame_period_s == pytest.approx(0.1 * factor)
    assert meta["time_step_corrected_from"] == "0.1"
    assert meta["frame_period_s"] == f"{0.1 * factor:g}"
    assert scene.frames[3].t == pytest.approx(3 * 0.1 * factor)
    check = json.loads(meta["clock_check"])
    assert check["ratio_file"] == pytest.approx(factor, rel=1e-6)
    assert check["ratio"] == pytest.approx(1.0, rel=1e-6)
    assert check["factor"] == factor and check["corrected"] and not check["fails"]
    warning = meta["clock_warning"]
    assert "\n" not in warning
    assert warning.startswith(f"warning: hand.xml: time step 0.1 s -> {0.1 * factor:g} s:")
    assert f"positions move {factor:.2f}x the recorded speeds" in warning
    assert "median over 6 agents" in warning and "100% of them" in warning
    # The recorded speeds are kept: they were the plausible ones.
    assert scene.frames[5].speed.tolist() == pytest.approx(SPEEDS)


def test_a_consistent_scene_is_untouched_and_not_warned_about():
    table = tracks(SPEEDS, turn_rad_s=0.2, noise_m=0.02)
    scene = scene_of(table)
    meta = scene.metadata
    assert scene.frame_period_s == 0.1
    assert "time_step_corrected_from" not in meta and "clock_warning" not in meta
    check = json.loads(meta["clock_check"])
    assert check["ratio_file"] == pytest.approx(1.0, abs=0.02)
    assert not check["fails"] and check["bad_row_share"] == 0.0
    assert [f.t for f in scene.frames] == pytest.approx(table.t_s.tolist())


def test_noisy_data_without_a_clean_factor_converts_with_the_bad_row_share():
    # Positions move 1.37x (no clean factor), and every other agent's heading is across
    # its motion: inconsistent, not correctable.
    table = tracks(SPEEDS, factor=1.37, noise_m=0.05)
    table.heading[:, ::2] += math.pi / 2
    scene = scene_of(table)
    meta = scene.metadata
    assert scene.frame_period_s == 0.1 and "time_step_corrected_from" not in meta
    check = json.loads(meta["clock_check"])
    assert check["ratio_file"] == pytest.approx(1.37, rel=0.03) and check["factor"] is None
    assert check["fails"] and check["bad_row_share"] > BAD_ROW_LIMIT
    assert check["heading_mismatch_share"] == pytest.approx(0.5, abs=0.05)
    warning = meta["clock_warning"]
    assert "no clean factor" in warning
    assert f"{check['bad_row_share']:.1%} of rows bad" in warning
    assert "converted with the time step 0.1 s" in warning


def test_time_step_file_keeps_the_label_and_still_warns():
    scene = scene_of(tracks(SPEEDS, factor=5.0), time_step="file")
    meta = scene.metadata
    assert scene.frame_period_s == 0.1 and "time_step_corrected_from" not in meta
    assert "kept the file's 0.1 s (--time-step file)" in meta["clock_warning"]
    assert "a clean factor 5: --time-step auto corrects it" in meta["clock_warning"]
    assert json.loads(meta["clock_check"])["fails"]


def test_time_step_seconds_forces_the_step():
    scene = scene_of(tracks(SPEEDS, factor=5.0), time_step=0.2)
    meta = scene.metadata
    assert scene.frame_period_s == 0.2 and meta["time_step_corrected_from"] == "0.1"
    check = json.loads(meta["clock_check"])
    assert check["choice"] == "forced" and check["ratio"] == pytest.approx(2.5)
    assert meta["clock_warning"].startswith("warning: hand.xml: time step 0.1 s -> 0.2 s")
    # Forcing the right value: no complaint beyond the change itself.
    right = scene_of(tracks(SPEEDS, factor=5.0), time_step=0.5).metadata
    assert "clock check" not in right["clock_warning"]


def test_derived_speeds_give_no_ratio_and_are_scaled_with_a_forced_step():
    table = tracks(SPEEDS, factor=5.0)
    no_speeds = TrackTable(**{**table.__dict__, "speed_measured": np.zeros_like(table.valid)})
    scene = scene_of(no_speeds)
    check = json.loads(scene.metadata["clock_check"])
    assert check["ratio_file"] is None and not check["speeds_recorded"]
    assert scene.frame_period_s == 0.1  # nothing to correct from
    forced = scene_of(no_speeds, time_step=0.5)
    # A speed derived from positions at 0.1 s is 5x too high at 0.5 s.
    assert forced.frames[5].speed.tolist() == pytest.approx([v / 5 for v in SPEEDS])


# ---------------------------------------------------------------------- each figure by hand
def test_heading_teleport_and_bounds_by_hand():
    table = tracks([10.0, 10.0, 1.0], kinds=[V, V, P], n_steps=20)
    table.heading[:, 0] += math.pi / 2  # the car drives sideways: every window mismatches
    h = table.heading[0, 1]  # the second car jumps 50 m ahead in one 0.1 s step
    table.xy[10:, 1] += 50.0 * np.array([math.cos(h), math.sin(h)])
    table.speed[:, 2] = 20.0  # a pedestrian "walking" 20 m/s (over 12)
    c = check_motion(motion(table), 0.1, "file")
    k = window_steps(motion(table))
    assert k == 2  # the cars' median step is 1 m: 2 steps cover WINDOW_M = 2 m
    # Vehicles moving by position: car 0 all 18 windows, car 1 all of them too (the
    # jump along its heading only lengthens two windows); the pedestrian is not checked.
    assert c.heading_windows == 2 * (20 - k)
    assert c.heading_mismatch_share == pytest.approx(0.5)
    assert c.teleports == 1
    assert c.speed_violations == 20  # the pedestrian's rows
    # Accelerations: none (constant speeds).
    assert c.accel_violations == 0


def test_acceleration_bound():
    table = tracks([10.0, 10.0], n_steps=20)
    table.speed[10:, 0] = 30.0  # +20 m/s in 0.1 s: 20 / 0.4 = 50 m/s^2 over each window
    c = check_motion(motion(table), 0.1, "file")
    assert accel_steps(table.t_s) == 4  # 0.4 s
    assert c.accel_violations == 4  # the 4 windows across the jump


def test_clean_factor_and_parse_time_step():
    assert clean_factor(5.02) == 5.0 and clean_factor(0.51) == 0.5 and clean_factor(2.45) == 2.5
    assert clean_factor(1.37) is None and clean_factor(7.0) is None
    assert clean_factor(0.0) is None and clean_factor(float("nan")) is None
    assert clean_factor(1 / 3.6) is None  # km/h read as m/s: flagged, not corrected
    assert parse_time_step("auto") == "auto" and parse_time_step("FILE") == "file"
    assert parse_time_step("0.2") == 0.2
    for bad in ("abc", "0", "-1", "nan", "inf"):
        with pytest.raises(ConversionError, match="time step"):
            parse_time_step(bad)


def _slow_agent_ratios(table: TrackTable, k: int) -> list[float]:
    """The oracle: per agent, the median over its windows of chord / covered distance."""
    out = []
    for a in range(table.n_tracks):
        ratios = []
        for i in range(table.n_steps - k):
            if not table.valid[i : i + k + 1, a].all():
                continue
            v = table.speed[i : i + k + 1, a]
            t = table.t_s[i : i + k + 1]
            covered = float(np.sum(0.5 * (v[1:] + v[:-1]) * np.diff(t)))
            if covered / (t[-1] - t[0]) <= 2.0:
                continue
            ratios.append(float(np.linalg.norm(table.xy[i + k, a] - table.xy[i, a])) / covered)
        if len(ratios) >= 3:
            out.append(float(np.median(ratios)))
    return out


def test_the_vectorised_ratio_matches_the_slow_oracle():
    rng = np.random.default_rng(3)
    table = tracks([1.0, 2.5, 6.0, 12.0, 20.0], factor=1.3, noise_m=0.3, n_steps=40)
    table.speed[:] *= rng.uniform(0.7, 1.3, table.speed.shape)
    table.valid[rng.random(table.valid.shape) < 0.1] = False
    oracle = _slow_agent_ratios(table, window_steps(motion(table)))
    c = check_motion(motion(table), 0.1, "file")
    assert c.agents_measured == len(oracle)
    assert c.ratio_file == pytest.approx(float(np.median(oracle)), rel=1e-12)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    k=st.sampled_from(CLEAN_FACTORS),
    true_step=st.sampled_from([0.04, 0.1, 0.2, 0.5]),
    speeds=st.lists(st.floats(3.0, 35.0), min_size=3, max_size=8),
    turn=st.floats(-0.3, 0.3),
    seed=st.integers(0, 1000),
)
def test_property_a_time_base_scaled_by_a_clean_factor_is_found_as_that_factor(
    k, true_step, speeds, turn, seed
):
    # A consistent scene (true step), labelled with a step k times too short.
    table = tracks(speeds, factor=k, step_s=true_step / k, turn_rad_s=turn, seed=seed,
                   n_steps=80)  # fmt: skip
    c = check_motion(motion(table), true_step / k)
    assert c.ratio_file == pytest.approx(k, rel=0.02)
    assert c.factor == k and c.corrected
    assert c.step_s == pytest.approx(true_step)
    assert c.ratio == pytest.approx(1.0, rel=0.02) and not c.fails


def test_motion_from_frames_matches_ids_across_frames():
    scene = scene_of(tracks(SPEEDS[:3], n_steps=10))
    m = motion_from_frames(scene.frames)
    assert m.valid.shape == (10, 3) and m.valid.all()
    assert m.t_s.tolist() == pytest.approx([f.t for f in scene.frames])
    np.testing.assert_allclose(m.xy[4], scene.frames[4].xy)


# ---------------------------------------------------------------------- the CLI
def _xml(factor: float, n_steps: int = 40, step_s: float = 0.1) -> str:
    """A CommonRoad scenario of four cars whose positions move ``factor`` times what
    their recorded speeds allow per labelled step."""
    obstacles = []
    for i, v in enumerate([8.0, 12.0, 10.0, 6.0]):
        states = []
        for t in range(n_steps):
            x, y = v * t * step_s * factor, 5.0 * i
            states.append(
                f"<position><point><x>{x:.4f}</x><y>{y}</y></point></position>"
                f"<orientation><exact>0.0</exact></orientation><time><exact>{t}</exact></time>"
                f"<velocity><exact>{v}</exact></velocity>"
            )
        traj = "".join(f"<state>{s}</state>" for s in states[1:])
        obstacles.append(
            f'<dynamicObstacle id="{i + 1}"><type>car</type><shape><rectangle><length>4'
            f"</length><width>2</width></rectangle></shape><initialState>{states[0]}"
            f"</initialState><trajectory>{traj}</trajectory></dynamicObstacle>"
        )
    return (
        f'<commonRoad timeStepSize="{step_s}" commonRoadVersion="2020a" '
        f'benchmarkID="ZAM_Clock-1_1_T-1">{"".join(obstacles)}</commonRoad>'
    )


@pytest.fixture
def clock_files(tmp_path):
    five = tmp_path / "five.xml"
    five.write_text(_xml(5.0))
    one = tmp_path / "one.xml"
    one.write_text(_xml(1.0))
    return five, one


def _convert(runner, src, out, *options):
    return runner.invoke(
        main, ["convert", "commonroad", str(src), "-o", str(out), "--no-progress", *options]
    )


def test_cli_convert_corrects_warns_and_obeys_time_step(clock_files, tmp_path):
    five, one = clock_files
    runner = CliRunner()
    res = _convert(runner, five, tmp_path / "a.mcap")
    assert res.exit_code == 0, res.output
    lines = [x for x in res.stderr.splitlines() if x.startswith("warning:")]
    assert len(lines) == 1
    assert f"warning: {five}: time step 0.1 s -> 0.5 s: positions move 5.00x" in lines[0]
    scene = read_mcap(tmp_path / "a.mcap")
    assert scene.frame_period_s == 0.5 and scene.metadata["time_step_corrected_from"] == "0.1"
    assert scene.frames[2].t == pytest.approx(1.0)

    res = _convert(runner, five, tmp_path / "b.mcap", "--time-step", "file")
    assert res.exit_code == 0 and "kept the file's 0.1 s (--time-step file)" in res.stderr
    assert read_mcap(tmp_path / "b.mcap").frame_period_s == 0.1

    res = _convert(runner, five, tmp_path / "c.mcap", "--time-step", "0.2")
    assert res.exit_code == 0 and "time step 0.1 s -> 0.2 s (--time-step 0.2)" in res.stderr
    assert read_mcap(tmp_path / "c.mcap").frame_period_s == 0.2

    res = _convert(runner, one, tmp_path / "d.mcap")
    assert res.exit_code == 0 and "warning" not in res.stderr
    assert "time_step_corrected_from" not in read_mcap(tmp_path / "d.mcap").metadata

    res = _convert(runner, five, tmp_path / "e.mcap", "--time-step", "soon")
    assert res.exit_code == 2 and "time step must be 'auto', 'file' or seconds" in res.output
    assert not (tmp_path / "e.mcap").exists()


def test_cli_inspect_check_exit_codes_and_json(clock_files, tmp_path):
    five, _one = clock_files
    runner = CliRunner()
    good, kept = tmp_path / "set" / "good.mcap", tmp_path / "set" / "kept.mcap"
    assert _convert(runner, five, good).exit_code == 0
    assert _convert(runner, five, kept, "--time-step", "file").exit_code == 0

    res = runner.invoke(main, ["inspect", "--check", str(good)])
    assert res.exit_code == 0, res.output
    assert "good" in res.output and "ok" in res.output and "per dataset" in res.output

    res = runner.invoke(main, ["inspect", "--check", str(good), str(kept), "--json"])
    assert res.exit_code == 1
    assert "Error: 1 of 2 scene(s) fail the clock check" in res.stderr
    report = json.loads(res.stdout)
    by_name = {pathlib.Path(r["path"]).stem: r for r in report["scenes"]}
    assert by_name["good"]["ratio"] == pytest.approx(1.0, abs=1e-3)
    assert by_name["good"]["ratio_at_file_step"] == pytest.approx(5.0, abs=1e-3)
    assert by_name["good"]["time_step_corrected_from"] == 0.1 and not by_name["good"]["fails"]
    assert by_name["kept"]["ratio"] == pytest.approx(5.0, abs=1e-3) and by_name["kept"]["fails"]
    [dataset] = report["datasets"]
    assert dataset["dataset"] == "set" and dataset["scenes"] == 2
    assert dataset["corrected"] == 1 and dataset["corrections"] == ["0.1 -> 0.5 s"]
    assert dataset["failing"] == 1 and report["failing"] == 1

    res = runner.invoke(main, ["inspect", str(good), str(kept)])
    assert res.exit_code == 2 and "several only with --check" in res.output


# ---------------------------------------------------------------------- real data
def _first(shared_data: pathlib.Path, dataset: str) -> pathlib.Path:
    folder = shared_data / "recorded" / dataset
    files = sorted(folder.glob("*.cr.xml"))
    if not files:
        pytest.skip(f"no {dataset} files at {folder}")
    return files[0]


@pytest.mark.realdata
@pytest.mark.parametrize(("dataset", "factor"), [("sind", 5.0), ("highd", 2.0)])
def test_real_sind_and_highd_files_are_corrected(shared_data, dataset, factor):
    src = _first(shared_data, dataset)
    scene = commonroad.read_scene(src, paths="hindsight")
    check = json.loads(scene.metadata["clock_check"])
    assert check["file_step_s"] == 0.1
    assert check["ratio_file"] == pytest.approx(factor, rel=0.02)
    assert check["factor"] == factor and check["agents_agreeing"] >= 0.9
    assert scene.frame_period_s == pytest.approx(0.1 * factor)
    assert scene.metadata["time_step_corrected_from"] == "0.1"
    assert check["ratio"] == pytest.approx(1.0, rel=0.02) and not check["fails"]
    assert check["bad_row_share"] < BAD_ROW_LIMIT
    # The recorded speeds stay as they were (the plausible ones).
    kept = commonroad.read_scene(src, paths="hindsight", time_step="file")
    assert kept.frames[3].speed.tolist() == scene.frames[3].speed.tolist()
    assert json.loads(kept.metadata["clock_check"])["fails"]


# ---------------------------------------------------------------------- batch
def test_batch_converts_with_auto_by_default_and_obeys_time_step(clock_files, tmp_path, capfd):
    from replay.batch import BatchSettings, ConvertTask, convert_one
    from risk.cascade import CascadeConfig

    five, _ = clock_files
    periods = {}
    for choice in ("auto", "file", 0.2):
        out = tmp_path / f"out-{choice}"
        task = ConvertTask(
            input=str(five), name="five", kind="commonroad", paths="map", map_osm=None,
            scenes_dir=str(out), marker=str(out / "marker.json"), digest="d",
            time_step=choice,
        )  # fmt: skip
        outcome = convert_one(task)
        assert not outcome.failures, outcome.failures
        [(_, path)] = outcome.scenes
        periods[choice] = read_mcap(path).frame_period_s
    assert periods == {"auto": 0.5, "file": 0.1, 0.2: 0.2}
    assert "time step 0.1 s -> 0.5 s" in capfd.readouterr().err  # the worker's warning
    # The choice is part of a conversion's identity: another choice converts again.
    cascade = CascadeConfig.default()
    assert BatchSettings(cascade).time_step == "auto"
    assert (
        BatchSettings(cascade).convert_digest()
        != BatchSettings(cascade, time_step="file").convert_digest()
    )
    res = CliRunner().invoke(main, ["batch", "--help"])
    assert "--time-step" in res.output


def test_blocks_of_agents_measure_the_same_as_one(monkeypatch):
    import converters.clock as clock

    table = tracks([1.0, 2.5, 6.0, 12.0, 20.0, 9.0, 4.0], factor=2.0, noise_m=0.2, n_steps=50,
                   kinds=[V, P, C, V, V, P, V])  # fmt: skip
    table.xy[30:, 3] += 40.0  # a teleport
    whole = check_motion(motion(table), 0.1)
    monkeypatch.setattr(clock, "BLOCK_CELLS", 100)  # two agents per block
    assert check_motion(motion(table), 0.1) == whole
