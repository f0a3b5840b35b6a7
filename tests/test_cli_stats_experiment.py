"""``replay stats`` and ``replay experiment`` through click's CliRunner."""

from __future__ import annotations

import json

import polars as pl
import pytest
from click.testing import CliRunner

from replay.cli.app import main


def run(args: list[str]):
    return CliRunner().invoke(main, args, catch_exceptions=False)


@pytest.fixture(scope="module")
def experiment_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp")
    result = run(
        ["experiment", "--situations", "6", "--workers", "1", "-o", str(out), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    return out, result.output


@pytest.mark.slow
def test_experiment_writes_report_tables_and_plots(experiment_dir):
    out, output = experiment_dir
    for name in (
        "report.md",
        "summary.json",
        "roc.png",
        "robustness.png",
        "errors.png",
        "cascade_funnel.png",
        "cascade_funnel_calibrated_test_half.png",
        "roc.parquet",
        "per_frame.csv",
        "per_scene.parquet",
    ):
        assert (out / name).is_file(), name
        assert str(out / name) in output  # printed at the end
    report = (out / "report.md").read_text()
    for k in range(1, 8):
        assert f"| {k} |" in report  # every finding in the verdict table
    for link in ("roc.png", "robustness.png", "errors.png", "cascade_funnel.png"):
        assert f"]({link})" in report
    assert "Time per stage" in report and " nan" not in report.lower()


def test_experiment_summary_is_consistent(experiment_dir):
    out, _ = experiment_dir
    s = json.loads((out / "summary.json").read_text())
    sit = s["situations"]
    assert sit["total"] == 6 and sit["with_agents"] + sit["without_agents"] == 6
    assert sit["tpr_defined"] + sit["empty_baseline"] == sit["with_agents"]
    assert sit["fpr_defined"] + sit["full_baseline"] == sit["with_agents"]
    frames = pl.read_csv(out / "per_frame.csv")
    assert frames.height == 6
    assert s["baseline"]["important_agent_frames"] == frames["n_baseline"].sum()
    assert s["baseline"]["agent_frames"] == frames["n_others"].sum()
    assert set(s["models"]) == {
        "current_distance",
        "path_distance",
        "trajectory_distance",
        "closest_encounter",
        "headway",
        "headway_2d",
        "circles",
        "gaussian",
        "survival",
    }
    assert s["models"]["survival"]["auc"] == pytest.approx(1.0)
    for m in s["models"].values():
        p1 = m["points"]["tpr_1"]
        assert p1["mean_tpr"] == pytest.approx(1.0) and p1["std_tpr"] == pytest.approx(0.0)
        assert m["points"]["tpr_0.95"]["mean_kept"] <= p1["mean_kept"] + 1e-9
    c = s["cascade"]
    kept = [st["mean_kept"] for st in c["stages"]]
    assert kept == sorted(kept, reverse=True) and kept[0] <= c["mean_others"]
    assert c["timed_situations"] == 6 and c["compute"]["survival_all_time_s"] > 0
    funnel = pl.read_parquet(out / "funnel.parquet")
    assert funnel["step"][0] == "all other agents" and funnel.height == 1 + 3 + 3


@pytest.mark.slow
def test_experiment_uses_worker_processes(tmp_path):
    result = run(
        [
            "experiment",
            "--situations",
            "4",
            "--workers",
            "2",
            "--no-calibrate-half",
            "-o",
            str(tmp_path),
            "--no-progress",
        ]
    )
    assert result.exit_code == 0, result.output
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["situations"]["total"] == 4
    assert not (tmp_path / "cascade_funnel_calibrated_test_half.png").exists()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Two short synthetic scenes as MCAP, and tables of the first one."""
    from converters.scene.writer import write_scene
    from converters.synthetic import SyntheticSettings, generate_scene

    folder = tmp_path_factory.mktemp("scenes")
    settings = SyntheticSettings(n_agents=20, duration_s=0.3)
    paths = [write_scene(folder / f"s{i}.mcap", generate_scene(settings, seed=i)) for i in (1, 2)]
    tables = folder.parent / f"{folder.name}_tables"
    tables.mkdir()
    for suffix in (".parquet", ".csv"):
        result = run(
            [
                "run",
                str(paths[0]),
                "--no-rrd",
                "--table",
                str(tables / f"s1{suffix}"),
                "--no-progress",
            ]
        )
        assert result.exit_code == 0, result.output
    return folder, paths, tables


@pytest.mark.slow
def test_stats_on_a_folder_of_scenes(scenes, tmp_path):
    folder, paths, _ = scenes
    result = run(
        ["stats", str(folder), "-o", str(tmp_path / "out"), "--workers", "1", "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["inputs"] == [str(p) for p in paths]
    scenes_table = pl.read_csv(tmp_path / "out" / "per_scene.csv")
    assert scenes_table["scene"].to_list() == ["s1", "s2"]
    assert scenes_table["frames"].sum() == s["situations"]["total"] == 6
    assert s["cascade"]["timing_available"]
    assert "Wrote:" in result.output and str(tmp_path / "out" / "roc.png") in result.output


def test_stats_from_tables_equals_stats_from_the_scene(scenes, tmp_path):
    _, paths, tables = scenes
    summaries = {}
    for name, inputs in (
        ("scene", [paths[0]]),
        ("parquet", [tables / "s1.parquet"]),
        ("csv", [tables / "s1.csv"]),
    ):
        out = tmp_path / name
        result = run(["stats", *map(str, inputs), "-o", str(out), "--no-plots", "--no-progress"])
        assert result.exit_code == 0, result.output
        summaries[name] = json.loads((out / "summary.json").read_text())
    for name in ("parquet", "csv"):
        for m, d in summaries["scene"]["models"].items():
            assert summaries[name]["models"][m]["auc"] == pytest.approx(d["auc"], rel=1e-9)
        a, b = summaries["scene"]["cascade"], summaries[name]["cascade"]
        assert a["stages"][0]["mean_kept"] == b["stages"][0]["mean_kept"]
        assert [t["mean_agents"] for t in a["tiers"]] == [t["mean_agents"] for t in b["tiers"]]
        assert not b["timing_available"]  # tables carry no compute times


def test_stats_counts_degenerate_situations_from_a_table(tmp_path):
    rows = {
        "frame": [0, 0, 1, 1, 2, 2],
        "t_s": [0.0, 0.0, 0.1, 0.1, 0.2, 0.2],
        "agent_id": [1, 2, 1, 2, 1, 2],
        "risk_headway_2d": [0.9, 0.1, 0.5, 0.4, 0.3, 0.2],
        "risk_survival": [1e-3, 1e-30, 1e-40, 1e-35, 1e-10, 1e-12],
        "baseline": [True, False, False, False, True, True],
    }
    path = tmp_path / "t.csv"
    pl.DataFrame(rows).write_csv(path)
    result = run(["stats", str(path), "-o", str(tmp_path / "out"), "--no-progress"])
    assert result.exit_code == 0, result.output
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["situations"]["empty_baseline"] == 1 and s["situations"]["full_baseline"] == 1
    assert "baseline empty in 1" in result.output and "full in 1" in result.output


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["notes.txt"], "expected an MCAP scene"),
        (["bad.csv"], "not a 'replay run --table' table"),
        (["good.csv", "--models", "nope"], "unknown risk model 'nope'"),
        (["good.csv", "--errors-model", "nope"], "unknown risk model 'nope'"),
    ],
)
def test_stats_bad_input_is_one_line_error(tmp_path, args, message):
    (tmp_path / "notes.txt").write_text("hello")
    pl.DataFrame({"x": [1]}).write_csv(tmp_path / "bad.csv")
    pl.DataFrame(
        {"frame": [0], "t_s": [0.0], "agent_id": [1], "risk_survival": [1.0], "baseline": [True]}
    ).write_csv(tmp_path / "good.csv")
    args = [str(tmp_path / args[0]), *args[1:]]
    result = CliRunner().invoke(main, ["stats", *args, "-o", str(tmp_path / "out")])
    assert result.exit_code == 1
    assert result.output.startswith("Error: ") and message in result.output
    assert "Traceback" not in result.output and result.output.count("\n") == 1
    assert not (tmp_path / "out").exists()  # nothing half-written


def test_help_texts_explain():
    for cmd in ("stats", "experiment"):
        result = run([cmd, "--help"])
        assert result.exit_code == 0
        assert "summary.json" in result.output and "--output" in result.output


@pytest.mark.slow
@pytest.mark.realdata
def test_stats_on_a_real_argoverse_scene(shared_data, tmp_path):
    (source,) = sorted((shared_data / "av2").glob("scenario_*.parquet"))
    scene = tmp_path / "av2.mcap"
    assert run(["convert", "av2", str(source), "-o", str(scene)]).exit_code == 0
    result = run(["stats", str(scene), "-o", str(tmp_path / "out"), "--no-progress"])
    assert result.exit_code == 0, result.output
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    frames = pl.read_parquet(tmp_path / "out" / "per_frame.parquet")
    sit = s["situations"]
    assert sit["total"] == frames.height > 0
    assert sit["empty_baseline"] == (frames["degenerate"] == "empty baseline").sum()
    assert sit["full_baseline"] == (frames["degenerate"] == "full baseline").sum()
    assert s["baseline"]["important_agent_frames"] == frames["n_baseline"].sum()
    assert s["models"]["survival"]["auc"] == pytest.approx(1.0)
    # Each model's mean TPR at its tpr_1 threshold is 1, and it keeps at least the baseline.
    for m in s["models"].values():
        assert m["points"]["tpr_1"]["mean_tpr"] == pytest.approx(1.0)
        assert m["points"]["tpr_1"]["mean_kept"] >= s["baseline"]["mean_important_per_situation"]


# ---------------------------------------------------------------------- experiment helpers
def test_finding_verdicts():
    from replay.analysis.experiment import Finding

    def f(*met):
        return Finding("claim", "measured", tuple((f"c{k}", m) for k, m in enumerate(met)))

    assert f(True, True).verdict == "agrees"
    assert f(True, False).verdict == "partly agrees"
    assert f(False, False).verdict == "does not agree"


def test_median_ratio_and_its_interval():
    from replay.analysis.experiment import median_ratio

    a = [1.0, 2.0, 3.0, 4.0, 5.0]
    ratio, lo, hi = median_ratio(a, [2.0 * x for x in a])
    assert ratio == lo == hi == 0.5  # every paired ratio is 0.5
    ratio, lo, hi = median_ratio([1.0, 3.0, 2.0], [1.0, 1.0, 1.0])
    assert ratio == 2.0 and lo <= 2.0 <= hi
    assert all(x != x for x in median_ratio([1.0], [1.0]))  # too few: NaN


def test_situation_seeds_chunks_and_relinks(tmp_path):
    from replay.analysis.experiment import calibration_seeds, chunks, relink, situation_seed
    from risk.cascade import CascadeConfig

    seeds = [situation_seed(0, i) for i in range(100)]
    assert len(set(seeds)) == 100 and seeds == [situation_seed(0, i) for i in range(100)]
    assert situation_seed(1, 0) != situation_seed(0, 0)
    parts = chunks(list(range(23)), workers=2, per_worker=3)
    assert [x for p in parts for x in p] == list(range(23)) and len(parts) == 6
    base = CascadeConfig.default()
    made = CascadeConfig(base.stages, base.tiers, provenance="Made by: x\nSeeds: 1000-1049\n")
    assert calibration_seeds(made) == (1000, 1049)
    assert calibration_seeds(CascadeConfig(base.stages, base.tiers, provenance="")) is None
    text = "![a](roc.png) and ![b](errors.png) and (roc.png)"
    out = relink(text, {"roc.png": tmp_path / "x"}, tmp_path / "docs" / "exp", tmp_path / "docs")
    assert out == "![a](exp/roc.png) and ![b](errors.png) and (roc.png)"


def test_stats_models_subset(scenes, tmp_path):
    _, paths, _ = scenes
    out = tmp_path / "out"
    result = run(
        [
            "stats",
            str(paths[1]),
            "-o",
            str(out),
            "--models",
            "gaussian,path_distance",
            "--errors-model",
            "circles",
            "--no-plots",
            "--no-progress",
        ]
    )
    assert result.exit_code == 0, result.output
    s = json.loads((out / "summary.json").read_text())
    assert list(s["models"]) == ["gaussian", "path_distance"]  # the order asked for
    assert s["errors_model"] == "circles"
    assert pl.read_parquet(out / "errors.parquet")["model"].unique().to_list() == ["circles"]
