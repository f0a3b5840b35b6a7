"""Dataset statistics (replay.analysis.stats): hand-computed ROC, FN/FP and cascade answers, the
exact sweep against its oracle (tests/roc_oracle.py), degenerate situations, tables from the engine."""

from __future__ import annotations

import json
import math

import numpy as np
import polars as pl
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from roc_oracle import roc_curve

from replay.analysis.stats import (
    Situations,
    StatsError,
    StatsSink,
    bootstrap_std_difference,
    cascade_summary,
    compute_stats,
    errors_over_threshold,
    frames_from_agents,
    model_stats,
    per_situation_rates,
    read_agents_table,
    situations_of,
    tier_names_of,
    write_stats,
)
from replay.core.engine import run_scene
from replay.core.tables import TableSink
from risk.cascade import CascadeConfig, Stage, Tier
from risk.metrics import exact_sweep


def sweep(scores: np.ndarray, sits: Situations):
    """:func:`risk.metrics.exact_sweep` over the situations of an agents table."""
    return exact_sweep(scores, sits.situation, sits.baseline, n_situations=sits.n)


def table(rows: list[tuple[str, int, float, bool]], model: str = "gaussian") -> pl.DataFrame:
    """An agents table from (scene, frame, score, important) rows."""
    return pl.DataFrame(
        {
            "scene": [r[0] for r in rows],
            "frame": [r[1] for r in rows],
            "t_s": [0.1 * r[1] for r in rows],
            "agent_id": list(range(len(rows))),
            f"risk_{model}": [r[2] for r in rows],
            "baseline": [r[3] for r in rows],
        }
    )


# Situation A: scores 0.9 (important), 0.5, 0.1 (important); situation B: 0.8, 0.3 (important).
HAND = table(
    [
        ("a", 0, 0.9, True),
        ("a", 0, 0.5, False),
        ("a", 0, 0.1, True),
        ("b", 0, 0.8, False),
        ("b", 0, 0.3, True),
    ]
)


# ---------------------------------------------------------------------- hand-computed ROC
def test_exact_sweep_matches_hand_computed_curve():
    sits = situations_of(HAND)
    sw = sweep(HAND["risk_gaussian"].to_numpy(), sits)
    np.testing.assert_allclose(sw.thresholds, [0.1, 0.3, 0.5, 0.8, 0.9])
    # t=0.9: A keeps its 0.9 (TPR 1/2, FPR 0), B nothing; t=0.8: B keeps its negative.
    np.testing.assert_allclose(sw.mean_tpr, [1.0, 0.75, 0.25, 0.25, 0.25])
    np.testing.assert_allclose(sw.mean_fpr, [1.0, 1.0, 1.0, 0.5, 0.0])
    np.testing.assert_allclose(sw.std_tpr, [0.0, 0.25, 0.25, 0.25, 0.25], atol=1e-7)
    np.testing.assert_allclose(sw.mean_kept, [2.5, 2.0, 1.5, 1.0, 0.5])
    # Closed curve (0,0) (0,.25) (.5,.25) (1,.25) (1,.75) (1,1) (1,1): area 0.25.
    assert sw.auc == pytest.approx(0.25)
    assert (sw.n_situations, sw.n_no_positive, sw.n_no_negative) == (2, 0, 0)


def test_operating_points_hand_computed():
    sits = situations_of(HAND)
    ms = model_stats(HAND["risk_gaussian"].to_numpy(), sits, "gaussian")
    p1, p95, p9, yj = (ms.points[k] for k in ("tpr_1", "tpr_0.95", "tpr_0.9", "youden"))
    assert p1.threshold == p95.threshold == p9.threshold == pytest.approx(0.1)
    assert p1.mean_tpr == 1.0 and p1.std_tpr == 0.0 and p1.mean_kept == 2.5
    # Youden J = TPR - FPR: 0.25 at 0.9 is the largest.
    assert yj.threshold == pytest.approx(0.9)
    assert yj.mean_tpr == 0.25 and yj.std_tpr == pytest.approx(0.25) and yj.mean_fpr == 0.0
    assert yj.mean_false_negatives == pytest.approx(1.0)  # A drops 1, B drops 1
    assert yj.situations_missing_any == 2
    np.testing.assert_allclose(ms.per_situation_tpr["youden"], [0.5, 0.0])
    assert ms.zero_score_positive_share == 0.0


def test_per_situation_rates_at_one_threshold():
    rates = per_situation_rates(HAND["risk_gaussian"].to_numpy(), situations_of(HAND), 0.3)
    np.testing.assert_allclose(rates["tpr"], [0.5, 1.0])
    np.testing.assert_allclose(rates["fpr"], [1.0, 1.0])
    np.testing.assert_allclose(rates["kept"], [2, 2])


def test_errors_over_threshold_counts_fn_and_fp():
    sits = situations_of(HAND)
    err = errors_over_threshold(
        HAND["risk_gaussian"].to_numpy(), sits, np.array([0.05, 0.4, 0.85]), "gaussian"
    )
    # 0.05 keeps all (FP 2); 0.4 drops 0.1 and 0.3 (FN 2) keeps 0.5, 0.8 (FP 2); 0.85: FN 2, FP 0.
    assert err["false_negatives"].to_list() == [0, 2, 2]
    assert err["false_positives"].to_list() == [2, 2, 0]
    np.testing.assert_allclose(err["mean_kept"].to_numpy(), [2.5, 1.5, 0.5])


# ---------------------------------------------------------------------- degenerate situations
def test_degenerate_situations_are_counted_not_averaged_in():
    df = table(
        [
            ("s", 0, 0.9, True),
            ("s", 0, 0.2, False),  # normal
            ("s", 1, 0.5, False),
            ("s", 1, 0.4, False),  # empty baseline: TPR undefined
            ("s", 2, 0.1, True),
            ("s", 2, 0.05, True),
        ]  # full baseline: FPR undefined
    )
    sits = situations_of(df)
    sw = sweep(df["risk_gaussian"].to_numpy(), sits)
    assert (sw.n_no_positive, sw.n_no_negative) == (1, 1)
    # At threshold 0.9 only situation 0 keeps an important agent: TPR 1/1 there, 0/2 in
    # situation 2; situation 1 has no TPR. Averaged in as 0 it would read 1/3.
    assert sw.mean_tpr[-1] == pytest.approx(0.5)
    # FPR at 0.4: situation 0 keeps no negative (0), situation 1 keeps both (1) -> 0.5.
    assert sw.mean_fpr[np.searchsorted(sw.thresholds, 0.4)] == pytest.approx(0.5)
    frames = frames_from_agents(df, [], [])
    stats = compute_stats(df, frames, errors_model="gaussian", stage_names=[])
    counts = stats.summary["situations"]
    assert counts["empty_baseline"] == 1 and counts["full_baseline"] == 1
    assert counts["tpr_defined"] == 2 and counts["fpr_defined"] == 2 and counts["total"] == 3
    assert stats.per_frame["degenerate"].to_list() == ["", "empty baseline", "full baseline"]


def test_frames_without_agents_are_counted_apart():
    df = table([("s", 0, 0.9, True), ("s", 0, 0.2, False)])
    frames = frames_from_agents(df, [], [])
    empty = frames.clear(1).with_columns(
        pl.lit("s").alias("scene"),
        pl.lit(1).cast(pl.Int64).alias("frame"),
        pl.lit(0.1).alias("t_s"),
        pl.lit(0).cast(pl.Int64).alias("n_others"),
        pl.lit(0).cast(pl.Int64).alias("n_baseline"),
    )
    stats = compute_stats(df, pl.concat([frames, empty]), errors_model="gaussian", stage_names=[])
    counts = stats.summary["situations"]
    assert counts["total"] == 2 and counts["with_agents"] == 1 and counts["without_agents"] == 1
    assert "no agents" in stats.per_frame["degenerate"].to_list()


# ---------------------------------------------------------------------- the exact sweep
situation = st.lists(
    st.tuples(
        st.one_of(st.sampled_from([0.0, 0.1, 0.5, 1.0]), st.floats(0, 1), st.just(math.nan)),
        st.booleans(),
    ),
    min_size=1,
    max_size=7,
)


@settings(max_examples=60, deadline=None)
@given(st.lists(situation, min_size=1, max_size=6))
def test_exact_sweep_equals_risk_metrics(situations):
    rows = [("x", k, s, b) for k, sit in enumerate(situations) for s, b in sit]
    df = table(rows)
    scores = df["risk_gaussian"].to_numpy()
    if np.isnan(scores).all():
        return
    sits = situations_of(df)
    sw = sweep(scores, sits)
    ref = roc_curve(sits.split(scores), sits.split(sits.baseline), thresholds=sw.thresholds)
    np.testing.assert_allclose(sw.mean_tpr, ref.mean_tpr, atol=1e-12)
    np.testing.assert_allclose(sw.mean_fpr, ref.mean_fpr, atol=1e-12)
    np.testing.assert_allclose(sw.std_tpr, ref.std_tpr, atol=1e-6)
    np.testing.assert_allclose(sw.mean_kept, ref.kept.mean(axis=0), atol=1e-12)
    if math.isnan(ref.auc):
        assert math.isnan(sw.auc)
    else:
        assert sw.auc == pytest.approx(ref.auc, abs=1e-12)
    assert (sw.n_no_positive, sw.n_no_negative) == (ref.n_no_positive, ref.n_no_negative)


@settings(max_examples=40, deadline=None)
@given(st.lists(situation, min_size=1, max_size=6))
def test_raising_the_threshold_never_keeps_more(situations):
    rows = [("x", k, s, b) for k, sit in enumerate(situations) for s, b in sit]
    df = table(rows)
    scores = df["risk_gaussian"].to_numpy()
    if np.isnan(scores).all():
        return
    sw = sweep(scores, situations_of(df))
    for curve in (sw.mean_tpr, sw.mean_fpr, sw.mean_kept):
        c = curve[np.isfinite(curve)]
        assert np.all(np.diff(c) <= 1e-12)  # thresholds ascend, rates descend


def test_baseline_model_has_tpr_one_at_the_baseline_threshold():
    rng = np.random.default_rng(3)
    survival = 10.0 ** rng.uniform(-40, -5, size=200)
    rows = [("x", k // 20, float(r), bool(r >= 1e-25)) for k, r in enumerate(survival)]
    df = table(rows, model="survival")
    ms = model_stats(df["risk_survival"].to_numpy(), situations_of(df), "survival")
    assert ms.points["tpr_1"].mean_fpr == 0.0
    assert ms.points["tpr_1"].threshold >= 1e-25
    assert ms.roc.auc == pytest.approx(1.0)


# ---------------------------------------------------------------------- bootstrap
def test_bootstrap_std_difference():
    rng = np.random.default_rng(0)
    tight = np.clip(0.9 + 0.01 * rng.standard_normal(400), 0, 1)
    wide = np.clip(0.9 + 0.1 * rng.standard_normal(400), 0, 1)
    d, lo, hi = bootstrap_std_difference(tight, wide)
    assert d == pytest.approx(tight.std() - wide.std())
    assert lo <= d <= hi < 0  # clearly lower
    d, lo, hi = bootstrap_std_difference(wide, wide)
    assert d == lo == hi == 0.0
    assert all(math.isnan(x) for x in bootstrap_std_difference(np.array([0.5]), np.array([0.5])))


# ---------------------------------------------------------------------- cascade
CONFIG = CascadeConfig(
    stages=(Stage("path_distance", 0.1), Stage("gaussian", 0.2)),
    tiers=(Tier("behavior", 1e-25), Tier("interactive", 0.3, 2)),
)


def test_frames_from_agents_counts_the_funnel_and_false_negatives():
    df = pl.DataFrame(
        {
            "scene": ["s"] * 4,
            "frame": [0, 0, 0, 0],
            "t_s": [0.0] * 4,
            "risk_gaussian": [0.1, 0.2, 0.3, 0.4],
            "kept_path_distance": [True, True, False, True],
            "kept_gaussian": [True, False, False, True],
            "tier": pl.Series(
                ["interactive", None, None, "behavior"], dtype=pl.Enum(["behavior", "interactive"])
            ),
            "baseline": [True, True, True, False],
        }
    )
    frames = frames_from_agents(df, ["path_distance", "gaussian"], tier_names_of(df))
    row = frames.row(0, named=True)
    assert row["n_others"] == 4 and row["n_baseline"] == 3
    assert row["kept_path_distance"] == 3 and row["kept_gaussian"] == 2
    assert row["fn_path_distance"] == 1 and row["fn_gaussian"] == 2  # cumulative
    assert row["tier_behavior"] == 2 and row["tier_interactive"] == 1  # nested
    assert row["survival_all_time_s"] is None


def test_tier_order_of_a_csv_table_needs_the_cascade():
    df = pl.DataFrame({"tier": ["interactive", None, "behavior"]})
    assert tier_names_of(df, fallback=["behavior", "interactive"]) == ["behavior", "interactive"]
    with pytest.raises(StatsError, match="--cascade"):
        tier_names_of(df, fallback=["behavior"])


def test_cascade_summary_compute_and_false_negatives():
    frames = pl.DataFrame(
        {
            "scene": ["s", "s"],
            "frame": [0, 1],
            "t_s": [0.0, 0.1],
            "n_others": [10, 20],
            "n_baseline": [4, 6],
            "kept_path_distance": [8, 12],
            "fn_path_distance": [0, 1],
            "tier_behavior": [4, 5],
            "time_path_distance_s": [0.002, 0.004],
            "sort_time_s": [0.001, 0.001],
            "survival_all_time_s": [0.004, 0.008],
        }
    )
    c = cascade_summary(frames, ["path_distance"], ["behavior"])
    assert c["mean_others"] == 15 and c["baseline_agent_frames"] == 10
    (stage,) = c["stages"]
    assert stage["mean_kept"] == 10 and stage["false_negatives"] == 1
    assert stage["fn_share"] == pytest.approx(0.1) and stage["situations_with_fn"] == 1
    comp = c["compute"]
    assert comp["cascade_time_s"] == pytest.approx(0.008)
    assert comp["survival_all_time_s"] == pytest.approx(0.012)
    assert comp["cascade_over_survival_all"] == pytest.approx(2 / 3)
    assert comp["median_cascade_time_s"] == pytest.approx(0.004)
    untimed = frames.with_columns(pl.lit(None, dtype=pl.Float64).alias("survival_all_time_s"))
    c = cascade_summary(untimed, ["path_distance"], ["behavior"])
    assert not c["timing_available"] and "compute" not in c


# ---------------------------------------------------------------------- with the engine
@pytest.fixture(scope="module")
def small_scene():
    from converters.synthetic import SyntheticSettings, generate_scene

    return generate_scene(SyntheticSettings(n_agents=14, duration_s=0.3), seed=5)


def test_stats_sink_tables_agree_with_the_table_sink(small_scene, tmp_path):
    sink = StatsSink("demo")
    table_sink = TableSink(tmp_path / "t.parquet")
    run_scene(small_scene, sinks=[sink, table_sink], cascade=CONFIG, progress=False)
    agents, frames = sink.agents(), sink.frames()
    written = pl.read_parquet(tmp_path / "t.parquet")
    assert agents.drop("scene").equals(written)
    assert agents["scene"].unique().to_list() == ["demo"]
    assert frames.height == len(small_scene.frames)
    # The frames table the sink measured equals the one derived from the agents table.
    derived = frames_from_agents(agents, CONFIG.stage_names, [t.name for t in CONFIG.tiers])
    counts = [c for c in derived.columns if not c.endswith("_s")]
    assert frames.select(counts).equals(derived.select(counts))
    assert frames["survival_all_time_s"].min() > 0


def test_read_tables_parquet_and_csv_give_the_same_statistics(small_scene, tmp_path):
    sinks = [TableSink(tmp_path / "t.parquet"), TableSink(tmp_path / "t.csv")]
    run_scene(small_scene, sinks=sinks, cascade=CONFIG, progress=False)
    tiers = [t.name for t in CONFIG.tiers]
    results = []
    for suffix in (".parquet", ".csv"):
        agents = read_agents_table(tmp_path / f"t{suffix}", scene="demo")
        frames = frames_from_agents(agents, CONFIG.stage_names, tier_names_of(agents, tiers))
        results.append(compute_stats(agents, frames, tier_names=tiers))
    a, b = (r.summary for r in results)
    for m in a["models"]:
        assert a["models"][m]["auc"] == pytest.approx(b["models"][m]["auc"], rel=1e-12)
    assert a["cascade"] == b["cascade"]


def test_read_agents_table_rejects_other_files(tmp_path):
    bad = tmp_path / "other.csv"
    pl.DataFrame({"x": [1]}).write_csv(bad)
    with pytest.raises(StatsError, match="not a 'replay run --table' table"):
        read_agents_table(bad)
    junk = tmp_path / "junk.parquet"
    junk.write_bytes(b"not parquet")
    with pytest.raises(StatsError, match="not a readable table"):
        read_agents_table(junk)


def test_unknown_model_is_an_error():
    frames = frames_from_agents(HAND, [], [])
    with pytest.raises(StatsError, match="no risk_survival column"):
        compute_stats(HAND, frames, models=["survival"], errors_model="gaussian")


def test_write_stats_files_and_summary(tmp_path):
    frames = frames_from_agents(HAND, [], [])
    stats = compute_stats(HAND, frames, errors_model="gaussian", stage_names=[], inputs=["hand"])
    files = write_stats(stats, tmp_path / "out")
    names = {p.name for p in files.values()}
    for base in ("roc", "errors", "funnel", "per_frame", "per_scene"):
        assert {f"{base}.parquet", f"{base}.csv"} <= names
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["models"]["gaussian"]["auc"] == pytest.approx(0.25)
    assert summary["situations"]["total"] == 2
    assert summary["baseline"]["important_agent_frames"] == 3
    assert sorted(summary["files"]) == sorted(n for n in names if n != "summary.json")
    roc = pl.read_parquet(tmp_path / "out" / "roc.parquet")
    assert roc.height == 5 and set(roc.columns) >= {"threshold", "mean_tpr", "mean_fpr", "std_tpr"}
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]
