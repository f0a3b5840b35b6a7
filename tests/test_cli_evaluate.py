"""``replay evaluate`` through click's CliRunner, and its library entry points."""

from __future__ import annotations

import json
import math

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from converters.scene.writer import write_scene
from replay.analysis.evaluation.collect import collect_agents, evaluate_inputs
from replay.analysis.evaluation.corpus import EvaluationSettings, site_of
from replay.cli.app import main
from risk.frame import Frame, LaneMap, Scene


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def straight_scene(lanes=(0.0, 5.0, 10.0), duration_s=8.0, crossing=False) -> Scene:
    """Agents driving east at 10 m/s on parallel lanes (never close); with ``crossing``
    one more agent drives north through the ego's path 0.5 s after it left."""
    dt, frames = 0.1, []
    for k in range(round(duration_s / dt) + 1):
        t = k * dt
        xy = [(10.0 * t, y) for y in lanes]
        heading = [0.0] * len(lanes)
        if crossing:
            # The ego's box last overlaps this agent's column (x in [29.5, 31.5]) at frame
            # t = 3.3 s (until 3.35 s); the agent's box first overlaps the ego's lane (y in
            # [-1, 1]) at frame t = 3.8 s (from 3.75 s): PET 0.5 s on the frame grid.
            xy.append((30.5, 10.0 * (t - 4.05)))
            heading.append(math.pi / 2)
        xy = np.array(xy)
        h = np.array(heading)
        paths = [
            np.array([p, p + 200 * np.array([math.cos(a), math.sin(a)])])
            for p, a in zip(xy, h, strict=True)
        ]
        n = len(xy)
        frames.append(
            Frame.from_arrays(
                xy, h, np.full(n, 10.0), np.full(n, 4.0), np.full(n, 2.0), paths, ego=0, t=t
            )
        )
    return Scene(map=LaneMap(), frames=frames, frame_period_s=dt, metadata={"dataset": "test"})


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("corpus")
    (root / "setA").mkdir()
    (root / "setB").mkdir()
    write_scene(root / "setA" / "S_SiteA-1_1.mcap", straight_scene(crossing=True))
    write_scene(root / "setA" / "S_SiteA-1_2.mcap", straight_scene())
    write_scene(root / "setB" / "S_SiteB-2_1.mcap", straight_scene(crossing=True))
    return root


def test_evaluate_writes_summary_tables_and_plots(corpus, tmp_path):
    out = tmp_path / "out"
    r = invoke("evaluate", corpus / "setA", corpus / "setB", "-o", out, "--bootstrap", 50,
               "--workers", 1, "--no-progress")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    h = summary["references"]["hindsight"]
    # The crossing agent (PET 0.5 s) in two scenes: two distinct positive agents.
    assert h["positive_agents"] == 2 and h["scenes_with_positive"] == 2
    assert summary["scenes"] == 3
    assert set(summary["by"]["dataset"]) == {"setA", "setB"}
    assert summary["by"]["kind"]["vehicle"]["references"]["hindsight"]["positive_agents"] == 2
    auc = summary["models"]["current_distance"]["hindsight"]["auc"]
    assert 0.0 <= auc["value"] <= 1.0 and len(auc["ci"]) == 2
    assert summary["site_transfer"]["current_distance"]["hindsight"]["calibration_sites"] == [
        "S_SiteA"
    ]
    for name in ("roc.parquet", "miss_rates.csv", "positives.parquet", "roc_hindsight.png",
                 "miss_rate_by_dataset.png", "miss_rate_by_kind.png"):  # fmt: skip
        assert (out / name).is_file(), name
    pos = pl.read_parquet(out / "positives.parquet")
    assert pos.height == 2 and set(pos["dataset"]) == {"setA", "setB"}
    assert pos["min_pet_s"].to_list() == pytest.approx([0.5, 0.5])
    assert "2 distinct agents" in r.output


def test_evaluate_reads_run_tables_parquet_and_csv(corpus, tmp_path):
    tables = tmp_path / "tables"
    tables.mkdir()
    for k, scene in enumerate(sorted((corpus / "setA").glob("*.mcap"))):
        suffix = ".csv" if k else ".parquet"
        r = invoke("run", scene, "--table", tables / f"{scene.stem}{suffix}", "--no-rrd",
                   "--no-progress")  # fmt: skip
        assert r.exit_code == 0, r.output
    r = invoke("evaluate", tables, "-o", tmp_path / "out", "--bootstrap", 20, "--no-plots",
               "--no-progress")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["references"]["hindsight"]["positive_agents"] == 1
    # Other truth settings need the scenes (a table holds the truth it was written with).
    r = invoke("evaluate", tables, "-o", tmp_path / "o2", "--truth-pet", 2, "--no-progress")
    assert r.exit_code != 0 and "give the .mcap scenes" in r.output


def test_no_agent_comes_close_is_reported_for_that_reference(corpus, tmp_path):
    """A reference without positives is reported as such (issue 28), not a crash and not
    a silent NaN; the other references are still evaluated."""
    out = tmp_path / "out"
    r = invoke("evaluate", corpus / "setA" / "S_SiteA-1_2.mcap", "-o", out, "--workers", 1,
               "--bootstrap", 5, "--no-progress")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "Reference hindsight: no positive among" in r.output
    summary = json.loads((out / "summary.json").read_text())
    assert "hindsight" in summary["references_without_positives"]
    assert "hindsight" not in summary["reference_names"]
    assert "survival" in summary["reference_names"]
    assert "hindsight" not in summary["models"]["current_distance"]
    assert "planner" in summary["references_missing"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ("--by", "dataset,colour"),
            "unknown grouping 'colour'; valid groupings: dataset, kind, site",
        ),
        (
            ("--calibration-sites", "Nowhere"),
            "unknown calibration site 'Nowhere'; the sites are: S_SiteA, S_SiteB",
        ),
        (("--models", "nonsense"), "unknown risk model 'nonsense'; valid models:"),
        (("--truth-coverage", "2"), "coverage must be in (0, 1]"),
    ],
)
def test_bad_option_values_are_one_line_errors(corpus, tmp_path, args, message):
    r = invoke("evaluate", corpus / "setA", corpus / "setB", "-o", tmp_path / "out", *args,
               "--bootstrap", 5, "--workers", 1, "--no-progress")  # fmt: skip
    assert r.exit_code != 0
    assert r.output.count("\n") == 1 and message in r.output, r.output


def test_scene_shorter_than_the_horizon_has_only_censored_frames(tmp_path):
    short = tmp_path / "d" / "short.mcap"
    short.parent.mkdir()
    write_scene(short, straight_scene(duration_s=4.0, crossing=True))
    r = invoke("evaluate", short, "-o", tmp_path / "out", "--bootstrap", 10, "--workers", 1,
               "--no-progress", "--no-plots")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "1 scene(s) shorter than the 5 s horizon" in r.output
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    # Complete windows (the default): none, so hindsight has no positive, said so ...
    h = summary["references"]["hindsight"]
    assert h["negative_agent_frames"] == 0 and h["positive_agents"] == 0
    assert "hindsight" in summary["references_without_positives"]
    # ... while the old rule, reported beside it, counts the censored positive.
    h_any = summary["references"]["hindsight_any"]
    assert h_any["negative_agent_frames"] == 0 and h_any["positive_agents"] == 1
    assert summary["scenes_shorter_than_horizon"] == ["short"]
    r = invoke("evaluate", short, "-o", tmp_path / "any", "--bootstrap", 10, "--workers", 1,
               "--hindsight-windows", "any", "--no-progress", "--no-plots")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "any" / "summary.json").read_text())
    assert summary["references"]["hindsight"]["positive_agents"] == 1


def test_evaluate_inputs_takes_model_parameters(corpus):
    from risk import MODELS

    base = evaluate_inputs([corpus / "setA"], settings=EvaluationSettings(n_boot=0))
    slow = evaluate_inputs(
        [corpus / "setA"],
        params={"survival": MODELS["survival"].params_type(escape_time_s=2.0)},
        settings=EvaluationSettings(n_boot=0, baseline_threshold=1e-4),
    )
    assert base["baseline"]["threshold"] == 1e-25 and slow["baseline"]["threshold"] == 1e-4
    assert (
        slow["references"]["survival"]["positive_agent_frames"]
        != base["references"]["survival"]["positive_agent_frames"]
    )


def test_site_names():
    assert site_of("C-DEU_AachenBendplatz-1_14320_T-399") == "DEU_AachenBendplatz"
    assert site_of("DEU_LocationALower26-1_26150_T-225") == "DEU_LocationALower"
    assert site_of("CHN_SIND-8021_1654_T-1729") == "CHN_SIND"
    assert site_of("DR_USA_Intersection_EP0") == "DR_USA_Intersection_EP"


def test_every_moving_agent_as_the_ego(corpus, tmp_path):
    out = tmp_path / "out"
    r = invoke("evaluate", corpus / "setA", "-o", out, "--ego", "all", "--every", "0.5s",
               "--bootstrap", 20, "--workers", 1, "--no-progress", "--no-plots")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    # Two scenes: 3 and 4 moving agents, each one an ego. The crossing agent passes the
    # ego's lane 0.5 s after it and the next lane (y = 5) about 0.9 s after the agent
    # there; the lane at y = 10 1.4 s after (> 1 s). Each pair counts from both sides:
    # 4 distinct (scene, ego, agent) positives.
    assert summary["egos"] == 7
    assert summary["references"]["hindsight"]["positive_agents"] == 4
    r = invoke("evaluate", corpus / "setA", "-o", out, "--ego", "nobody", "--no-progress")
    assert r.exit_code != 0 and "neither an agent id" in r.output


def test_dataset_is_the_folder_named_not_where_a_link_points(corpus, tmp_path):
    """Scenes linked into one folder per dataset (e.g. from replay batch's flat
    OUT/scenes/) are grouped by the folder they were named in, not the link target's."""
    linked = tmp_path / "mydata"
    linked.mkdir()
    for scene in (corpus / "setA").glob("*.mcap"):
        (linked / scene.name).symlink_to(scene)
    _, datasets, _ = collect_agents([linked])
    assert set(datasets.values()) == {"mydata"}


def test_the_command_equals_the_full_rows_oracle_within_its_stated_bounds(corpus, tmp_path):
    """``replay evaluate`` (one scene's part at a time) against evaluate_table on every
    row at once: equal, the binned figures within the bound the summary states; the
    report and the printed summary state the largest AUC bound."""
    from test_evaluation_parts import assert_same

    from replay.analysis.evaluation.corpus import evaluate_table
    from replay.analysis.evaluation.files import _jsonable

    out, report = tmp_path / "out", tmp_path / "report.md"
    inputs = [corpus / "setA", corpus / "setB"]
    r = invoke("evaluate", *inputs, "-o", out, "--bootstrap", 40, "--workers", 1,
               "--no-progress", "--no-plots", "--report", report)  # fmt: skip
    assert r.exit_code == 0, r.output
    got = json.loads((out / "summary.json").read_text())
    agents, datasets, hs = collect_agents(inputs)
    full = evaluate_table(agents, settings=EvaluationSettings(n_boot=40), datasets=datasets,
                          hindsight=hs, inputs=[str(p) for p in inputs])  # fmt: skip
    assert_same(got, json.loads(json.dumps(_jsonable(full))))
    assert got["by"]["dataset"] and got["site_transfer"] and got["cascade"]
    assert "AUC ± " in r.output and "AUC ± " in report.read_text()
