"""Calibration against planner truth (replay.analysis.planner_calibration and
``replay calibrate --reference planner``): the per-scene table, the site split that
never leaks, and the command end to end on a prepared score cache."""

from __future__ import annotations

import dataclasses
import json
import pathlib

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from planner_scenes import STOPPED, write_road_scene

from replay.analysis.planner_calibration import (
    SCORES,
    ScoreSettings,
    cascade_keeps,
    planner_calibration,
    scene_scores,
    scores_job,
    site_of,
    site_split,
    with_corridor,
)
from replay.cli.app import main
from replay.jobs import Inputs, SceneOutput, run_jobs, scene_refs
from risk import MODELS
from risk.cascade import CascadeConfig, CorridorSettings

TIERS = CascadeConfig.named("survival").tiers


def fake_scores(n_scenes: int, *, seed: int = 0) -> pl.DataFrame:
    """A scores table of ``n_scenes`` scenes over two datasets and five sites, each scene
    with a few ego-frames of a few agents; every scene has a planner-important agent."""
    rng = np.random.default_rng(seed)
    rows = []
    sites = {
        "highd": ["DEU_LocationA", "DEU_LocationB"],
        "ind": ["DEU_AachenBendplatz", "DEU_AachenAseag", "DEU_AachenHeckstrasse"],
    }
    for s in range(n_scenes):
        dataset = "highd" if s % 2 else "ind"
        site = sites[dataset][(s // 2) % len(sites[dataset])] if s % 7 else sites[dataset][-1]
        scene = f"{dataset}/{site}-{s}_1_T-1.mcap"
        for frame in range(3):
            for agent in range(4):
                label = agent == 0 and frame == 0
                rows.append({
                    "scene": scene, "dataset": dataset, "site": site, "ego_id": 1, "frame": frame,
                    "t_s": float(frame), "agent_id": agent, "kind": 0, "distance_m": 10.0 * agent,
                    **{f"risk_{m}": float(rng.random() * (2.0 if label else 1.0)) for m in MODELS},
                    "reachable": True, "corridor": bool(agent == 1), "label_idm": label,
                    "label_fop": bool(agent == 2 and frame == 1) if s % 3 else None,
                })  # fmt: skip
    return pl.DataFrame(rows)


def test_site_names():
    assert site_of("highd/DEU_LocationALower26-1_26150_T-225.mcap") == "DEU_LocationA"
    assert site_of("mona/C-DEU_MONAEast-2_1040_T-1119.mcap") == "DEU_MONAEast"
    assert site_of("sind/CHN_SIND-831_2256_T-2331.mcap") == "CHN_SIND"
    assert site_of("ngsim/USA_US101-14_1_T-1.mcap") == "USA_US101"


@pytest.mark.parametrize(
    "holdout", ["auto", ["DEU_LocationB"], ["DEU_AachenAseag", "DEU_LocationA"]]
)
def test_the_site_split_never_leaks(holdout):
    df = fake_scores(120)
    calibrate, report = site_split(df, holdout)
    assert (calibrate ^ report).all()
    cal_scenes = set(df.filter(pl.Series(calibrate))["scene"])
    rep_scenes = set(df.filter(pl.Series(report))["scene"])
    assert cal_scenes and rep_scenes and not cal_scenes & rep_scenes
    assert not set(df.filter(pl.Series(calibrate))["site"]) & set(
        df.filter(pl.Series(report))["site"]
    )
    result = planner_calibration(
        df, ["gaussian"], planners=["idm", "fop"], miss_rate=0.1, confidence=0.8, unit="scene",
        corridor=CorridorSettings(), tiers=TIERS, holdout=holdout, n_boot=50,
    )  # fmt: skip
    assert result.calibrated_on["scenes"] == len(cal_scenes)
    assert set(result.calibrated_on["sites"]).isdisjoint(result.held_out_sites)
    assert result.held_out is not None and result.held_out["all"]["scenes"] == len(rep_scenes)


def test_auto_holds_out_one_site_per_dataset_with_several():
    df = fake_scores(60)
    _, report = site_split(df, "auto")
    held = df.filter(pl.Series(report)).select("dataset", "site").unique()
    assert sorted(held["dataset"].to_list()) == ["highd", "ind"]


def test_the_union_of_planners_and_the_corridor_in_the_thresholds():
    df = fake_scores(80)
    result = planner_calibration(
        df, ["gaussian"], planners=["idm", "fop"], miss_rate=0.1, confidence=0.8, unit="scene",
        corridor=CorridorSettings(), tiers=TIERS, n_boot=20,
    )  # fmt: skip
    keep = cascade_keeps(df, result.config)
    assert keep[df["corridor"].to_numpy()].all()  # the corridor's agents are always kept
    g = result.config.guarantee
    assert g["miss_rate"] == 0.1 and g["confidence"] == 0.8 and g["unit"] == "scene"
    assert g["planners"] == ["idm", "fop"] and g["units"] == 80
    assert result.calibrated_on["positives"]["union"] > result.calibrated_on["positives"]["idm"]


def _populate_cache(tmp_path: pathlib.Path, n: int, settings: ScoreSettings) -> list[pathlib.Path]:
    """The cache (the scores job's parts and markers) filled with fake scores, as a run
    with ``settings`` would leave it."""
    df = fake_scores(n)
    parts = {}
    for name, part in df.group_by("scene"):
        path = tmp_path / "scenes" / str(name[0])
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"not read: the cache has its scores")
        parts[path] = part
    scenes = sorted(parts)
    refs = scene_refs(Inputs(tuple(scenes), ()))

    def fake(ref, _settings):  # in this process (one worker): no pickling
        part = parts[ref.path]
        return SceneOutput({SCORES: part.with_columns(pl.lit(ref.key).alias("scene"))})

    job = dataclasses.replace(scores_job(settings), run=fake)
    run_jobs(job, refs, tmp_path / "cache", workers=1, progress=False)
    return scenes


def test_cli_end_to_end_on_a_cache(tmp_path):
    settings = ScoreSettings(planners=("idm", "fop"), corridor=None)  # (the cache's key)
    scenes = _populate_cache(tmp_path, 60, settings)
    out = tmp_path / "planner.toml"
    report = tmp_path / "report.json"
    args = [
        "calibrate", *map(str, scenes), "--reference", "planner", "--planner", "idm",
        "--planner", "fop", "--miss-rate", "0.1", "--confidence", "0.8", "--stages", "gaussian",
        "--scores-cache", str(tmp_path / "cache"), "--holdout", "auto", "--no-corridor",
        "--leave-one-dataset-out", "--report", str(report), "-o", str(out), "--no-progress",
    ]  # fmt: skip
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "Guarantee: with probability >= 0.8" in res.output and "Held out" in res.output
    config = CascadeConfig.from_toml(out)
    assert config.corridor is None and config.stage_names == ("gaussian",)
    assert config.guarantee["units"] > 0 and "Made by: replay calibrate" in config.provenance
    payload = json.loads(report.read_text())
    assert set(payload["held_out_sites"]).isdisjoint(payload["calibrated_on"]["sites"])
    assert set(payload["leave_one_dataset_out"]) == {"highd", "ind"}


def test_cli_refuses_too_few_scenes_saying_how_many(tmp_path):
    settings = ScoreSettings(planners=("idm",), corridor=None)
    scenes = _populate_cache(tmp_path, 30, settings)
    out = tmp_path / "planner.toml"
    res = CliRunner().invoke(main, [
        "calibrate", *map(str, scenes), "--reference", "planner", "--planner", "idm",
        "--stages", "gaussian", "--scores-cache", str(tmp_path / "cache"), "-o", str(out),
        "--no-corridor",
        "--no-progress",
    ])  # fmt: skip
    assert res.exit_code != 0
    assert "needs at least 299 scenes" in res.output and "has 30" in res.output
    assert "Traceback" not in res.output and not out.exists()


def test_scene_scores_on_a_hand_made_scene(tmp_path):
    """The pure per-scene function on issue 32's road: the car standing ahead matters to
    IDM and the corridor stage keeps it."""
    (tmp_path / "road").mkdir()
    path = write_road_scene(tmp_path / "road" / "road.mcap")
    df = scene_scores(path, ScoreSettings(planners=("idm",)))
    assert {"scene", "site", "label_idm", "corridor", "risk_gaussian", "reachable"} <= set(
        df.columns
    )
    stopped = df.filter(pl.col("agent_id") == STOPPED)
    assert stopped["label_idm"].all() and stopped["corridor"].all()


def test_the_corridor_column_is_computed_afresh(tmp_path):
    """The cached scores do not depend on the corridor: its column comes from the scene."""
    (tmp_path / "road").mkdir()
    path = write_road_scene(tmp_path / "road" / "road.mcap")
    df = scene_scores(path, ScoreSettings(planners=("idm",), corridor=None))
    assert not df["corridor"].any()
    again = with_corridor(df, path, CorridorSettings())
    assert again.filter(pl.col("agent_id") == STOPPED)["corridor"].all()
    assert not with_corridor(df, path, None)["corridor"].any()


def test_two_roots_are_two_scene_units_and_their_caches_apart(tmp_path):
    """The guarantee counts scenes: d1/road/x.mcap and d2/road/x.mcap are two units (they
    were one, keyed by folder and file name) and never share a cached table."""
    from replay.analysis.planner_calibration import cached_scores, collect_scores

    paths = []
    for root in ("d1", "d2"):
        (tmp_path / root / "road").mkdir(parents=True)
        paths.append(write_road_scene(tmp_path / root / "road" / "x.mcap"))
    settings = ScoreSettings(planners=("idm",))
    df = collect_scores(paths, settings, progress=False)
    assert sorted(df["scene"].unique().to_list()) == ["d1/road/x", "d2/road/x"]
    cached = cached_scores(paths, settings, tmp_path / "cache", progress=False)
    assert cached["scene"].n_unique() == 2 and cached.equals(df)
    parts = sorted((tmp_path / "cache" / "parts" / SCORES).rglob("*.parquet"))
    assert [p.relative_to(tmp_path / "cache" / "parts" / SCORES) for p in parts] == [
        pathlib.Path("d1/road/x.parquet"), pathlib.Path("d2/road/x.parquet"),
    ]  # fmt: skip
