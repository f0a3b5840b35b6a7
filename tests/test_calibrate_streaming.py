"""``replay calibrate`` in bounded driver memory (issue 38): the calibration streamed over
the scenes' parts, one scene at a time, gives what the whole table gives (today's path,
kept as the oracle): the same thresholds, guarantee, held-out and leave-one-dataset-out
figures (the same bootstrap draws), the same survival thresholds, tiers and counts, in
any order of the parts; a sample too small is still refused saying how many are needed."""

from __future__ import annotations

import dataclasses
import json
import pathlib
import random

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from replay.analysis.planner_calibration import (
    SCORES,
    ScorePart,
    ScoreSettings,
    format_report,
    planner_calibration,
    scores_job,
    streamed_planner_calibration,
)
from replay.analysis.planner_eval.study import json_safe
from replay.analysis.scene_calibration import (
    DEFAULT_TIERS,
    RiskPart,
    calibrated_config,
    gather,
    streamed_calibration,
    tier_means,
)
from replay.cli.app import main
from replay.errors import ReplayError
from replay.jobs import Inputs, SceneOutput, run_jobs, scene_refs
from risk import MODELS
from risk.calibration import (
    CalibrationError,
    GuaranteedCalibration,
    calibrate_thresholds,
    calibrate_unit_minima,
    calibrate_with_guarantee,
    calibration_from_counts,
    fn_budget,
    important_dropped,
    sequential_thresholds,
    stage_counts,
    unit_minimum,
    with_agents_dropped,
)
from risk.cascade import CascadeConfig, CorridorSettings

TIERS = CascadeConfig.named("survival").tiers
SITES = {
    "highd": ["DEU_LocationA", "DEU_LocationB"],
    "ind": ["DEU_AachenBendplatz", "DEU_AachenAseag", "DEU_AachenHeckstrasse"],
    "mona": ["DEU_MONAEast"],
}


# ---------------------------------------------------------------------- planner reference
def planner_table(n_scenes: int, *, seed: int = 0) -> pl.DataFrame:
    """A scores table of ``n_scenes`` scenes over three datasets and six sites, two egos
    per scene and a varying number of frames and agents; planner truth for two planners
    (with unknowns), agents the bound drops, the corridor keeps or drops, NaN risks, and
    some scenes without any planner-important agent."""
    rng = np.random.default_rng(seed)
    names = list(SITES)
    columns: dict[str, list] = {c: [] for c in ["scene", "dataset", "site", "ego_id", "frame",
                                                 "agent_id", "reachable", "corridor", "behind",
                                                 "label_idm", "label_fop"]}  # fmt: skip
    risks: dict[str, list[float]] = {m: [] for m in MODELS}
    for s in range(n_scenes):
        dataset = names[s % 3]
        site = SITES[dataset][(s // 3) % len(SITES[dataset])]
        scene = f"{dataset}/{site}-{s}_1_T-1"
        quiet = s % 5 == 4  # no planner-important agent at all
        for ego in (1, 2):
            for frame in range(int(rng.integers(1, 4))):
                for agent in range(int(rng.integers(1, 7))):
                    idm = bool(not quiet and rng.random() < 0.3)
                    fop = None if s % 4 == 1 else bool(not quiet and rng.random() < 0.2)
                    columns["scene"].append(scene)
                    columns["dataset"].append(dataset)
                    columns["site"].append(site)
                    columns["ego_id"].append(ego)
                    columns["frame"].append(frame)
                    columns["agent_id"].append(agent + 10)
                    matters = idm or bool(fop)
                    # what matters is rarely dropped ahead of the stages (that is refused)
                    columns["reachable"].append(bool(matters or rng.random() > 0.05))
                    columns["corridor"].append(bool(rng.random() < 0.1))
                    columns["behind"].append(bool(not matters and rng.random() < 0.1))
                    columns["label_idm"].append(idm)
                    columns["label_fop"].append(fop)
                    for m in MODELS:
                        value = float(rng.random() * (3.0 if matters else 1.0))
                        risks[m].append(np.nan if not matters and rng.random() < 0.02 else value)
    return pl.DataFrame(
        {**columns, **{f"risk_{m}": v for m, v in risks.items()}},
        schema_overrides={"label_fop": pl.Boolean},
    )


def write_parts(df: pl.DataFrame, folder: pathlib.Path, *, split_corridor: bool) -> list[ScorePart]:
    """One scores part per scene, as the scores job writes them; with ``split_corridor``
    the corridor's two columns in a separate part, as the corridor job writes them."""
    parts = []
    for n, ((scene,), table) in enumerate(df.group_by("scene", maintain_order=True)):
        scores = folder / "scores" / f"{n}.parquet"
        scores.parent.mkdir(parents=True, exist_ok=True)
        corridor = None
        if split_corridor:
            corridor = folder / "corridor" / f"{n}.parquet"
            corridor.parent.mkdir(parents=True, exist_ok=True)
            table.select("corridor", "behind").write_parquet(corridor)
            table = table.with_columns(
                pl.lit(False).alias("corridor"), pl.lit(False).alias("behind")
            )
        table.write_parquet(scores)
        parts.append(ScorePart(str(scene), scores, corridor))
    return parts


def payload(result) -> str:
    """Everything the command writes or prints from a calibration, as one text."""
    return json.dumps(
        json_safe(
            {
                "toml": result.config.to_toml_string(),
                "calibration": repr(result.calibration),
                "calibrated_on": result.calibrated_on,
                "held_out": result.held_out,
                "held_out_sites": list(result.held_out_sites),
                "lodo": result.leave_one_dataset_out,
                "report": format_report(result, ["idm", "fop"]),
            }
        ),
        indent=1,
    )


PLANNER_CASES = [
    # unit, holdout, corridor, leave one dataset out
    ("scene", None, CorridorSettings(), False),
    ("scene", "auto", CorridorSettings(), True),
    ("ego", "auto", None, True),
    ("ego", ["DEU_LocationB", "DEU_AachenAseag"], CorridorSettings(), False),
]


@pytest.fixture(scope="module")
def table() -> pl.DataFrame:
    return planner_table(90)


@pytest.mark.parametrize(("unit", "holdout", "corridor", "lodo"), PLANNER_CASES)
def test_streamed_planner_calibration_equals_the_whole_table(
    table, tmp_path, unit, holdout, corridor, lodo
):
    options = dict(planners=["idm", "fop"], miss_rate=0.2, confidence=0.8, unit=unit,
                   corridor=corridor, tiers=TIERS, holdout=holdout, lodo=lodo, n_boot=200)  # fmt: skip
    oracle = planner_calibration(table, ["gaussian", "trajectory_distance"], **options)
    parts = write_parts(table, tmp_path, split_corridor=corridor is not None)
    streamed = streamed_planner_calibration(parts, ["gaussian", "trajectory_distance"], **options)
    assert payload(streamed) == payload(oracle)
    assert streamed.calibration == oracle.calibration  # agents_dropped counted in pass 2 too
    assert any(s.agents_dropped > 0 for s in oracle.calibration.stages)
    if holdout is not None:
        assert streamed.held_out is not None and streamed.held_out["all"]["union"]["positives"]
        assert streamed.held_out["all"]["union"]["dropped"]["ci95"] is not None
    if lodo:
        assert set(streamed.leave_one_dataset_out or {}) == set(SITES)


def test_the_order_of_the_parts_does_not_matter(table, tmp_path):
    options = dict(planners=["idm", "fop"], miss_rate=0.2, confidence=0.8, unit="scene",
                   corridor=CorridorSettings(), tiers=TIERS, holdout="auto", lodo=True,
                   n_boot=100)  # fmt: skip
    parts = write_parts(table, tmp_path, split_corridor=True)
    first = payload(streamed_planner_calibration(parts, ["gaussian"], **options))
    shuffled = parts[:]
    random.Random(3).shuffle(shuffled)
    assert shuffled != parts
    assert payload(streamed_planner_calibration(shuffled, ["gaussian"], **options)) == first
    assert payload(streamed_planner_calibration(parts[::-1], ["gaussian"], **options)) == first


def test_too_few_units_is_refused_saying_how_many(table, tmp_path):
    parts = write_parts(table.filter(pl.col("dataset") == "mona"), tmp_path, split_corridor=False)
    options = dict(planners=["idm"], miss_rate=0.01, confidence=0.95, unit="scene",
                   corridor=None, tiers=TIERS)  # fmt: skip
    with pytest.raises(ReplayError) as streamed:
        streamed_planner_calibration(parts, ["gaussian"], **options)
    with pytest.raises(ReplayError) as oracle:
        planner_calibration(table.filter(pl.col("dataset") == "mona"), ["gaussian"], **options)
    assert "needs at least 299 scenes" in str(streamed.value)
    assert str(streamed.value) == str(oracle.value)


def test_the_leave_one_dataset_out_error_is_the_oracles(tmp_path):
    """A dataset whose others are too few to calibrate on: the same error entry."""
    df = planner_table(24, seed=5)
    options = dict(planners=["idm", "fop"], miss_rate=0.1, confidence=0.8, unit="scene",
                   corridor=None, tiers=TIERS, lodo=True, n_boot=50)  # fmt: skip
    oracle = planner_calibration(df, ["gaussian"], **options)
    assert any("error" in e for e in (oracle.leave_one_dataset_out or {}).values())
    parts = write_parts(df, tmp_path, split_corridor=False)
    assert payload(streamed_planner_calibration(parts, ["gaussian"], **options)) == payload(oracle)


def test_the_command_reports_what_the_whole_table_gives(table, tmp_path):
    """``replay calibrate --reference planner`` end to end on a prepared cache of parts:
    its TOML's thresholds and guarantee and its --report JSON are the whole-table
    oracle's."""
    score_settings = ScoreSettings(planners=("idm", "fop"), corridor=None)  # the cache key
    tables = {}
    for (scene,), part in table.group_by("scene", maintain_order=True):
        path = tmp_path / "scenes" / f"{scene}.mcap"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"not read: the cache has its scores")
        tables[path] = part
    scenes = sorted(tables)
    refs = scene_refs(Inputs(tuple(scenes), ()))
    assert {r.key for r in refs} == set(table["scene"])

    def fake(ref, _settings):  # in this process (one worker): no pickling
        return SceneOutput({SCORES: tables[ref.path]})

    job = dataclasses.replace(scores_job(score_settings), run=fake)
    run_jobs(job, refs, tmp_path / "cache", workers=1, progress=False)
    out, report = tmp_path / "planner.toml", tmp_path / "report.json"
    res = CliRunner().invoke(main, [
        "calibrate", *map(str, scenes), "--reference", "planner", "--planner", "idm",
        "--planner", "fop", "--miss-rate", "0.2", "--confidence", "0.8", "--stages",
        "gaussian,trajectory_distance", "--scores-cache", str(tmp_path / "cache"),
        "--holdout", "auto", "--no-corridor", "--leave-one-dataset-out", "--report",
        str(report), "-o", str(out), "--no-progress",
    ])  # fmt: skip
    assert res.exit_code == 0, res.output
    oracle = planner_calibration(
        table, ["gaussian", "trajectory_distance"], planners=["idm", "fop"], miss_rate=0.2,
        confidence=0.8, unit="scene", corridor=None, tiers=TIERS, holdout="auto", lodo=True,
    )  # fmt: skip
    assert format_report(oracle, ["idm", "fop"]) in res.output
    config = CascadeConfig.from_toml(out)
    assert config.stages == oracle.config.stages and config.guarantee == oracle.config.guarantee
    expected = {
        "guarantee": oracle.config.guarantee,
        "thresholds": {s.model: s.threshold for s in oracle.config.stages},
        "calibrated_on": oracle.calibrated_on,
        "held_out_sites": list(oracle.held_out_sites),
        "held_out": oracle.held_out,
        "leave_one_dataset_out": oracle.leave_one_dataset_out,
    }
    assert json.loads(report.read_text()) == json.loads(json.dumps(json_safe(expected)))


# ---------------------------------------------------------------------- the pure pieces
@settings(max_examples=60, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 3),
    st.integers(1, 12),
    st.floats(0.05, 0.5),
)
def test_unit_minima_of_the_scenes_side_by_side_give_the_guarantee(seed, stages, scenes, rate):
    """calibrate_with_guarantee on every agent-frame == calibrate_unit_minima on the
    scenes' unit minima side by side (any split, any order) and the summed drops."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(scenes, 80))
    scene = np.sort(rng.integers(0, scenes, n))
    units = np.array([f"s{k}#{e}" for k, e in zip(scene, rng.integers(0, 2, n), strict=True)])
    important = rng.random(n) < 0.4
    scores = rng.choice([0.0, 0.1, 0.5, 1.0, 2.0, np.inf, -np.inf, np.nan], size=(stages, n))
    models = [f"m{k}" for k in range(stages)]
    options = dict(models=models, miss_rate=rate, confidence=0.5, unit="scene")
    whole: GuaranteedCalibration | CalibrationError
    try:
        whole = calibrate_with_guarantee(scores, important, units, **options)
    except CalibrationError as exc:  # the same refusal, below
        whole = exc
    order = rng.permutation(scenes)
    minima = [
        np.stack(
            [
                unit_minimum(scores[s][scene == k], important[scene == k], units[scene == k])
                for s in range(stages)
            ]
        )
        for k in order
    ]
    try:
        cal = calibrate_unit_minima(
            np.concatenate(minima, axis=1), positives=int(important.sum()), **options
        )
    except CalibrationError as exc:
        assert str(exc) == str(whole)
        return
    dropped = sum(
        important_dropped(scores[:, scene == k], important[scene == k], cal.thresholds)
        for k in range(scenes)
    )
    assert with_agents_dropped(cal, list(dropped)) == whole


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 3), st.sampled_from([0.0, 0.1, 0.3, 1.0]))
def test_survival_thresholds_from_the_baseline_rows_and_summed_counts(seed, stages, rate):
    """calibrate_thresholds on every agent-frame == sequential thresholds of the
    baseline-important rows alone (shuffled) + stage counts summed over scenes."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 120))
    risks = rng.choice([0.0, 1e-3, 0.2, 0.7, 1.0, np.inf, np.nan], size=(stages, n))
    base = rng.random(n) < 0.5
    frames = np.sort(rng.integers(0, 30, n))
    models = [f"m{k}" for k in range(stages)]
    try:
        whole = calibrate_thresholds(risks, base, frames, models=models, max_fn_rate=rate)
    except CalibrationError:
        with pytest.raises(CalibrationError):
            fn_budget(rate, int(np.unique(frames).size), int(base.sum()))
        return
    allowed = fn_budget(rate, int(np.unique(frames).size), int(base.sum()))
    shuffled = rng.permutation(np.flatnonzero(base))
    thresholds = sequential_thresholds(risks[:, shuffled], allowed)
    scene = frames // 7
    counts = sum(
        stage_counts(risks[:, scene == k], base[scene == k], thresholds) for k in np.unique(scene)
    )
    streamed = calibration_from_counts(
        models, thresholds, counts, frames=int(np.unique(frames).size), agent_frames=n,
        baseline_agents=int(base.sum()), max_fn_rate=rate,
    )  # fmt: skip
    assert repr(streamed) == repr(whole)  # repr: NaN shares compare equal


# ---------------------------------------------------------------------- survival reference
def risk_parts_on_disk(folder: pathlib.Path, n_scenes: int, *, seed: int = 0) -> list[RiskPart]:
    """Risks parts as the risks job writes them: per scene, frames of a varying number
    of agents (some frames without any, one scene without a table), three stage risks
    and survival, some of it baseline-important, NaN now and then."""
    rng = np.random.default_rng(seed)
    parts = []
    for s in range(n_scenes):
        frames = int(rng.integers(1, 12))
        partial = {"frames": frames, "skipped_frames": int(rng.integers(0, 3)),
                   "source": ["highD", "inD"][s % 2], "seed": s if s % 3 else None}  # fmt: skip
        if s == 4:
            parts.append(RiskPart(f"scene{s:02d}", None, {**partial, "frames": 0}))
            continue
        per_frame = rng.integers(0, 9, frames)
        frame = np.repeat(np.arange(frames), per_frame)
        n = frame.size
        table = {"frame": frame}
        for k in range(3):
            table[f"stage_{k}"] = np.where(rng.random(n) < 0.03, np.nan, rng.random(n) ** (k + 1))
        table["survival"] = np.where(rng.random(n) < 0.4, rng.random(n) * 1e-3, 1e-30)
        path = folder / f"scene{s:02d}.parquet"
        pl.DataFrame(table).write_parquet(path)
        parts.append(RiskPart(f"scene{s:02d}", path, partial))
    return parts


@pytest.mark.parametrize("max_fn_rate", [0.0, 0.05])
def test_streamed_survival_calibration_equals_the_whole_data(tmp_path, max_fn_rate):
    parts = risk_parts_on_disk(tmp_path, 30)
    models = ["path_distance", "trajectory_distance", "gaussian"]
    data = gather(parts, models)
    config, cal = calibrated_config(data, models, max_fn_rate=max_fn_rate, tiers=DEFAULT_TIERS,
                                    tier_counts=(5, 2))  # fmt: skip
    means = tier_means(config, data)
    for order in (parts, parts[::-1], random.Random(1).sample(parts, len(parts))):
        s_config, s_cal, corpus, s_means = streamed_calibration(
            order, models, max_fn_rate=max_fn_rate, tiers=DEFAULT_TIERS, tier_counts=(5, 2)
        )
        assert s_config.to_toml_string() == config.to_toml_string()
        assert repr(s_cal) == repr(cal) and s_means == means
        assert (corpus.frames, corpus.scenes, corpus.skipped_frames, corpus.sources,
                corpus.seeds) == (data.frames, data.scenes, data.skipped_frames, data.sources,
                                  data.seeds)  # fmt: skip
    assert cal.stages[0].false_negatives > 0 or max_fn_rate == 0.0


def test_streamed_survival_refuses_what_the_whole_data_refuses(tmp_path):
    """No baseline-important agent: the same one-line error."""
    parts = risk_parts_on_disk(tmp_path, 3)
    quiet = []
    for part in parts:
        if part.table is not None:
            df = pl.read_parquet(part.table).with_columns(pl.lit(0.0).alias("survival"))
            df.write_parquet(part.table)
        quiet.append(part)
    models = ["gaussian", "path_distance", "trajectory_distance"]
    with pytest.raises(Exception) as whole:
        calibrated_config(gather(quiet, models), models, max_fn_rate=0.0, tiers=DEFAULT_TIERS,
                          tier_counts=(5, 2))  # fmt: skip
    with pytest.raises(Exception) as streamed:
        streamed_calibration(quiet, models, max_fn_rate=0.0, tiers=DEFAULT_TIERS,
                             tier_counts=(5, 2))  # fmt: skip
    assert str(streamed.value) == str(whole.value)
    assert "no baseline-important agent" in str(streamed.value)
