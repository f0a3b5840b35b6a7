"""The sensitivity sweep (``replay.analysis.evaluation.sensitivity``) on a small synthetic corpus, the
``--set`` option of every command, and ``replay evaluate --sensitivity --report``."""

from __future__ import annotations

import json
import math

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from converters.scene.writer import write_scene
from replay.analysis.evaluation.collect import collect_agents, evaluate_inputs
from replay.analysis.evaluation.corpus import EvaluationSettings
from replay.analysis.evaluation.sensitivity import (
    Variant,
    affected_models,
    default_variants,
    run_sweep,
    sweep_subset,
    sweep_table,
)
from replay.cli.app import main
from risk.cascade import CascadeConfig
from risk.frame import Frame, LaneMap, Scene
from risk.registry import MODELS
from risk.settings import parse_settings

FAST = EvaluationSettings(n_boot=20, groupings=("kind",))


def scene(crossing: bool, duration_s: float = 7.0) -> Scene:
    """The ego (id 0) drives east at 10 m/s; a car on the next lane; a slow car 150 m ahead
    in the ego's lane (still closing at the 12 s horizon); with ``crossing`` one more car
    drives north through the ego's path 0.5 s after it."""
    dt, frames = 0.1, []
    for k in range(round(duration_s / dt) + 1):
        t = k * dt
        xy = [(10.0 * t, 0.0), (10.0 * t, 5.0), (150.0 + 2.0 * t, 0.0)]
        heading = [0.0, 0.0, 0.0]
        speed = [10.0, 10.0, 2.0]
        if crossing:
            xy.append((30.5, 10.0 * (t - 4.05)))
            heading.append(math.pi / 2)
            speed.append(10.0)
        xy_a, h = np.array(xy), np.array(heading)
        paths = [
            np.array([p, p + 300 * np.array([math.cos(a), math.sin(a)])])
            for p, a in zip(xy_a, h, strict=True)
        ]
        n = len(xy_a)
        frames.append(
            Frame.from_arrays(
                xy_a, h, np.array(speed), np.full(n, 4.0), np.full(n, 2.0), paths, ego=0, t=t
            )
        )
    return Scene(map=LaneMap(), frames=frames, frame_period_s=dt, metadata={"dataset": "test"})


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    (root / "setA").mkdir()
    (root / "setB").mkdir()
    write_scene(root / "setA" / "S_A-1_1.mcap", scene(crossing=True))
    write_scene(root / "setA" / "S_A-1_2.mcap", scene(crossing=False))
    write_scene(root / "setB" / "S_B-1_1.mcap", scene(crossing=True))
    return root


def paths(corpus):
    return [corpus / "setA", corpus / "setB"]


def aucs(summary):
    # A reference without positives is left out of the models (and named in
    # summary["references_without_positives"]): its AUC is undefined.
    return {
        (m, ref): summary["models"][m].get(ref, {"auc": {"value": None}})["auc"]["value"]
        for m in summary["models"]
        for ref in ("survival", "hindsight")
    }


def sweep_aucs(result, label):
    rows = result.rows.filter(pl.col("variant") == label)
    return {(r["model"], r["reference"]): r["auc"] for r in rows.iter_rows(named=True)}


def same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        x, y = a[k], b[k]
        assert (x is None or math.isnan(x)) == (y is None or math.isnan(y)), k
        if x is not None and not math.isnan(x):
            assert x == pytest.approx(y, abs=1e-12), k


def test_affected_models_hand_cases():
    assert affected_models({"baseline.threshold": 1e-4}) == []
    assert affected_models({"survival.escape_time_s": 0.8}) == ["survival"]
    assert affected_models({"prediction.vehicle.growth_lon": 0.2}) == [
        "circles",
        "gaussian",
        "survival",
    ]
    assert affected_models({"prediction.horizon_s": 8}) == [
        m for m in MODELS if m != "current_distance"
    ]
    assert affected_models({"headway.encounter_time_max_s": math.inf, "circles.n_circles": 2}) == [
        "headway", "circles",
    ]  # fmt: skip


def test_rethreshold_equals_a_recompute(corpus):
    result = run_sweep(
        paths(corpus), settings=FAST,
        variants=[Variant("baseline threshold", "1e-4", {"baseline.threshold": 1e-4})],
    )  # fmt: skip
    recomputed = evaluate_inputs(
        paths(corpus), cascade=CascadeConfig.default().with_settings(["baseline.threshold=1e-4"]),
        settings=EvaluationSettings(n_boot=20, groupings=("kind",), baseline_threshold=1e-4),
    )  # fmt: skip
    same(sweep_aucs(result, "1e-4"), aucs(recomputed))
    assert (
        result.variants.filter(pl.col("variant") == "1e-4")["recomputed"][0]
        == "none (re-threshold)"
    )
    # and the threshold matters here: the survival reference has fewer positives
    assert (
        recomputed["references"]["survival"]["positive_agent_frames"]
        < evaluate_inputs(paths(corpus), settings=FAST)["references"]["survival"][
            "positive_agent_frames"
        ]
    )


@pytest.mark.parametrize(
    "settings",
    [{"survival.escape_time_s": 1.6}, {"prediction.horizon_s": 4.0},
     {"closest_encounter.encounter_time_max_s": math.inf}],
)  # fmt: skip
def test_recomputing_only_the_changed_models_equals_a_full_recompute(corpus, settings):
    result = run_sweep(paths(corpus), settings=FAST, variants=[Variant("g", "v", settings)])
    parsed = parse_settings(settings)
    full = evaluate_inputs(
        paths(corpus), params=parsed.params_or_none(), prediction=parsed.prediction_or_none(),
        settings=FAST,
    )  # fmt: skip
    same(sweep_aucs(result, "v"), aucs(full))


def test_each_variant_changes_its_models_and_no_other(corpus):
    base, _, _ = collect_agents(paths(corpus))
    for variant in default_variants():
        changed = affected_models(variant.settings)
        if not changed:
            continue
        cascade = CascadeConfig.default().with_settings(variant.settings)
        agents, _, _ = collect_agents(paths(corpus), cascade=cascade)
        differs = []
        for m in MODELS:
            a = base[f"risk_{m}"].to_numpy()
            b = agents[f"risk_{m}"].to_numpy()
            if not np.array_equal(a, b, equal_nan=True):
                differs.append(m)
        assert set(differs) <= set(changed), (variant, differs)
        assert differs, f"{variant.group} {variant.label} changed nothing"


def test_findings_flip_and_rank_correlation_on_hand_made_summaries():
    def summary(values):
        return {
            "models": {
                m: {ref: {"auc": {"value": v, "ci": [v - 0.01, v + 0.01]}} for ref in ("survival", "hindsight")}
                for m, v in values.items()
            }
        }  # fmt: skip

    order = [m for m in MODELS if m != "survival"]
    base = {m: 0.5 + 0.05 * i for i, m in enumerate(order)}  # current distance worst, gaussian best
    base["survival"] = 1.0
    swapped = dict(base)
    swapped["current_distance"], swapped["path_distance"] = (
        base["path_distance"],
        base["current_distance"],
    )
    _, per_variant, findings = sweep_table(
        [
            (Variant("defaults", "paper"), summary(base), []),
            (Variant("g", "swap"), summary(swapped), ["x"]),
        ]
    )
    v = per_variant.filter(pl.col("variant") == "swap").row(0, named=True)
    n = len(order)
    assert v["spearman"] == pytest.approx(1 - 6 * 2 / (n * (n * n - 1)))  # one adjacent swap
    flipped = findings.filter(
        pl.col("flipped") & (pl.col("variant") == "swap") & (pl.col("reference") == "hindsight")
    )
    names = set(flipped["finding"].to_list())
    assert "current distance is the worst" in names
    assert "path_distance above current_distance, intervals apart" in names
    assert "2D Gaussians are closest to survival (best of the others)" not in names
    d = per_variant.filter(pl.col("variant") == "paper").row(0, named=True)
    assert d["spearman"] == pytest.approx(1.0) and d["flips"] == 0


def test_sweep_subset_keeps_every_folder(tmp_path):
    files = [tmp_path / d / f"s{i}.mcap" for d in ("a", "b") for i in range(5)]
    chosen = sweep_subset(files, 2)
    assert [f"{p.parent.name}/{p.name}" for p in chosen] == [
        "a/s0.mcap", "a/s2.mcap", "a/s4.mcap", "b/s0.mcap", "b/s2.mcap", "b/s4.mcap",
    ]  # fmt: skip


# ---------------------------------------------------------------------- CLI
def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_evaluate_sensitivity_and_report(corpus, tmp_path):
    out, report = tmp_path / "out", tmp_path / "docs" / "recorded-evaluation.md"
    report.parent.mkdir()  # the output guard wants the report's folder to exist
    r = invoke("evaluate", *paths(corpus), "-o", out, "--bootstrap", 20, "--sensitivity",
               "--sensitivity-bootstrap", 10, "--sensitivity-every", "1s", "--report", report,
               "--workers", 1, "--no-progress")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "Sensitivity (rank correlation" in r.output
    ranking = pl.read_parquet(out / "sensitivity_ranking.parquet")
    groups = set(ranking["group"].to_list())
    assert groups == {"defaults", "baseline threshold", "tau_esc", "uncertainty growth", "horizon",
                      "closest-encounter rule", "circle radii"}  # fmt: skip
    assert (out / "sensitivity.png").stat().st_size > 0
    text = report.read_text()
    assert "## The paper's findings against what actually happened" in text
    assert "Current distance is the worst model" in text
    assert "(recorded-evaluation/roc_hindsight.png)" in text
    for png in ("roc_hindsight.png", "miss_rate_by_kind.png", "sensitivity.png"):
        assert (tmp_path / "docs" / "recorded-evaluation" / png).exists()
    assert "$" not in text.replace("$$", "")  # every template field filled


def test_evaluate_set_changes_the_models(corpus, tmp_path):
    r = invoke("evaluate", *paths(corpus), "-o", tmp_path / "o", "--bootstrap", 0, "--no-plots",
               "--workers", 1, "--no-progress", "--set", "baseline.threshold=1e-4")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["baseline"]["threshold"] == 1e-4


@pytest.mark.parametrize("command", ["run", "stats", "evaluate", "batch"])
@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("survival.tau=1", "Error: unknown setting 'survival.tau'; the keys of survival are: "),
        ("circles.radius_rule=huge", "Error: circles: radius_rule must be 'spec' or 'width'"),
        ("nokey", "Error: 'nokey' is not KEY=VALUE"),
    ],
)
def test_set_errors_are_one_line_for_every_command(corpus, tmp_path, command, item, message):
    scene = corpus / "setA" / "S_A-1_2.mcap"
    args = {
        "run": (scene, "--table", tmp_path / "t.parquet", "--no-rrd"),
        "stats": (scene, "-o", tmp_path / "o"),
        "evaluate": (scene, "-o", tmp_path / "o"),
        "batch": (scene, "-o", tmp_path / "o"),
    }[command]
    r = invoke(command, *args, "--set", item, "--no-progress")
    assert r.exit_code != 0
    assert r.output.count("\n") == 1 and r.output.startswith(message), r.output
    assert not (tmp_path / "o").exists() and not (tmp_path / "t.parquet").exists()


def test_sensitivity_refuses_tables(corpus, tmp_path):
    table = tmp_path / "t.parquet"
    assert invoke("run", corpus / "setA" / "S_A-1_1.mcap", "--table", table, "--no-rrd",
                  "--no-progress").exit_code == 0  # fmt: skip
    r = invoke("evaluate", table, "-o", tmp_path / "o", "--sensitivity", "--bootstrap", 0,
               "--no-progress")  # fmt: skip
    assert r.exit_code != 0 and "give .mcap scenes, not tables" in r.output, r.output
