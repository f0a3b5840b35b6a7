"""replay.analysis.evaluation.streaming.evaluate_parts, the evaluation ``replay evaluate``
runs (one part file at a time), against the full-rows evaluation (evaluate_table on every
row at once: the slow obvious oracle). Every figure is equal, except the binned ones,
which must lie within the bound the streamed summary states for each."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from replay.analysis.evaluation.corpus import EvaluationError, EvaluationSettings, evaluate_table
from replay.analysis.evaluation.files import positives_table
from replay.analysis.evaluation.streaming import StreamSettings, evaluate_parts
from risk.evaluation import pooled_roc

#: Scene names over three recording sites (site_of: the part before "-", digits off).
NAMES = ("DEU_A1-1", "DEU_B1-2", "DEU_A2-3", "DEU_C1-4", "DEU_B2-5")
#: Keys of binned figures: compared within their stated bound, not equal.
BINNED = {"auc", "tpr_at_fpr", "auc_situation_mean"}
#: Keys only the streamed summary has (the bounds) or whose text differs by design.
ONLY_STREAMED: set[str] = set()


def corpus(seed: int, n_scenes: int = 5, integer_scores: bool = False) -> list[pl.DataFrame]:
    """Random scenes: frames x egos x agents rows with scores, hindsight truth (censored
    windows too), planner labels, cascade flags, kinds; rows shuffled inside each scene."""
    rng = np.random.default_rng(seed)
    scenes = []
    for k in range(n_scenes):
        frame, ego, agent = np.meshgrid(np.arange(4), np.arange(2), np.arange(5), indexing="ij")
        n = frame.size
        truth = rng.random(n) < 0.25
        risk = rng.integers(0, 6, n).astype(float) if integer_scores else rng.random(n)
        df = pl.DataFrame(
            {
                "scene": [NAMES[k]] * n,
                "frame": frame.ravel(),
                "ego_id": ego.ravel(),
                "agent_id": agent.ravel(),
                "kind": rng.choice(["vehicle", "pedestrian", "bicycle"], n),
                "t_s": frame.ravel() * (0.1 if k % 2 else 2.0),
                "speed_mps": np.where(rng.random(n) < 0.1, np.nan, rng.random(n) * 2),
                "risk_current_distance": risk + truth * rng.integers(0, 3, n),
                "risk_survival": np.where(rng.random(n) < 0.5, 0.0, rng.random(n)),
                "distance_m": rng.random(n) * 60,
                "truth_label": truth,
                "truth_gap_m": rng.random(n),
                "truth_pet_s": rng.random(n),
                "truth_complete": rng.random(n) < 0.8,
                "truth_yielded": rng.random(n) < 0.2,
                "track_ok": rng.random(n) < 0.9,
                "planner_label": rng.random(n) < 0.3,
                "kept_a": rng.random(n) < 0.7,
            }
        ).with_columns(
            pl.col("kept_a").alias("kept_b") & (pl.col("distance_m") < 40),
            pl.when(pl.col("track_ok")).then(pl.col("truth_label")).alias("truth_label"),
        )  # fmt: skip
        scenes.append(df.sample(fraction=1.0, shuffle=True, seed=seed + k))
    return scenes


def both(tmp_path, scenes, ev: EvaluationSettings, datasets=None, **stream):
    paths = []
    for i, df in enumerate(scenes):
        tmp_path.mkdir(parents=True, exist_ok=True)
        paths.append(tmp_path / f"part{i}.parquet")
        df.write_parquet(paths[-1])
    rows = pl.concat(scenes, how="diagonal_relaxed").sort(
        "scene", "frame", "ego_id", maintain_order=True
    )  # in the order the command reads them
    full = evaluate_table(rows, settings=ev, datasets=datasets, presorted=True)
    streamed = evaluate_parts(
        paths, StreamSettings.of(ev, None).__class__(**{**StreamSettings.of(ev).__dict__, **stream}),
        datasets=datasets, evaluation=ev,
    )  # fmt: skip
    return streamed, full, rows


def assert_same(got: Any, want: Any, path: str = "") -> None:
    """Equal, with binned figures within the bound stated beside them."""
    if isinstance(want, dict):
        assert isinstance(got, dict), path
        for key, value in want.items():
            if key in ONLY_STREAMED:
                continue
            assert key in got, f"{path}/{key} missing"
            if key in BINNED:
                assert_within_bound(got, key, value, f"{path}/{key}")
            else:
                assert_same(got[key], value, f"{path}/{key}")
        return
    if isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), path
        for i, (a, b) in enumerate(zip(got, want, strict=True)):
            assert_same(a, b, f"{path}[{i}]")
        return
    if isinstance(want, float):
        if math.isnan(want):
            assert isinstance(got, float) and math.isnan(got), f"{path}: {got} != nan"
        else:
            assert got == pytest.approx(want, rel=1e-12, abs=1e-15), f"{path}: {got} != {want}"
        return
    assert got == want, f"{path}: {got!r} != {want!r}"


def assert_within_bound(parent: dict[str, Any], key: str, want: Any, path: str) -> None:
    got = parent[key]
    if key == "auc_situation_mean":
        bound = parent["auc_situation_mean_error_bound"]
        check(got, want, bound, 1e-9, path)  # weights summed in another order
    elif key == "auc":
        check(got["value"], want["value"], got["error_bound"], 1e-12, path)
        assert ("ci" in got) == ("ci" in want), path  # the interval itself is binned
    else:  # tpr at fpr
        for f, w in want.items():
            g = got[f]
            check(g["value"], w["value"], g["error_bound"], 1e-12, f"{path}/{f}")
            assert w["value"] - g["value"] >= -1e-12, path  # never above the exact one


def check(got: float, want: float, bound: float, rounding: float, path: str) -> None:
    if math.isnan(want):
        assert math.isnan(got), path
        return
    assert abs(got - want) <= bound + rounding, f"{path}: {got} vs {want}, bound {bound}"


@settings(
    max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.integers(0, 10_000), st.booleans(), st.sampled_from([0, 20]))
def test_evaluate_parts_equals_the_full_rows_evaluation(tmp_path, seed, integer_scores, n_boot):
    ev = EvaluationSettings(n_boot=n_boot, groupings=("dataset", "kind"))
    datasets = {n: ("one" if i % 2 else "two") for i, n in enumerate(NAMES)}
    streamed, full, rows = both(tmp_path, corpus(seed, integer_scores=integer_scores), ev,
                                datasets)  # fmt: skip
    summary = streamed.summary
    assert "site_transfer" in full and "by" in full and full["by"]["kind"]
    assert_same(summary, full)
    assert set(summary) == set(full) | {"auc_binning"}
    assert streamed.positives.equals(positives_table(rows, datasets))


def test_binned_figures_are_exact_when_every_bin_holds_one_score(tmp_path):
    ev = EvaluationSettings(n_boot=30, groupings=("kind",))
    streamed, full, _ = both(tmp_path, corpus(5, integer_scores=True), ev)
    got = streamed.summary["models"]["current_distance"]["hindsight"]
    want = full["models"]["current_distance"]["hindsight"]
    assert got["mixed_bins"] == 0 and got["auc"]["error_bound"] == 0
    assert got["auc"]["value"] == pytest.approx(want["auc"]["value"], abs=1e-12)
    assert got["auc_situation_mean"] == pytest.approx(want["auc_situation_mean"], abs=1e-9)
    np.testing.assert_allclose(got["auc"]["ci"], want["auc"]["ci"], atol=1e-12)


def test_the_roc_table_is_the_binned_curve_of_the_exact_one(tmp_path):
    # Integer scores: one score per bin, so the binned curve is the exact curve.
    ev = EvaluationSettings(n_boot=0, groupings=())
    streamed, _, rows = both(tmp_path, corpus(9, integer_scores=True), ev)
    roc = streamed.roc.filter(
        (pl.col("model") == "current_distance") & (pl.col("reference") == "hindsight")
    )
    ok = rows["truth_complete"].fill_null(False).to_numpy()
    truth = np.where(ok, rows["truth_label"].cast(pl.Int8).fill_null(-1).to_numpy(), -1)
    exact = pooled_roc(rows["risk_current_distance"].to_numpy(), truth)
    np.testing.assert_allclose(roc["threshold"].to_numpy(), exact.thresholds)
    np.testing.assert_allclose(roc["tpr"].to_numpy(), exact.tpr)
    np.testing.assert_allclose(roc["fpr"].to_numpy(), exact.fpr)


def test_medians_are_exact_on_coarse_grids(tmp_path):
    # At most 4 bins per merged histogram: the middle bins hold many values, which the
    # last pass reads back.
    ev = EvaluationSettings(n_boot=0, groupings=())
    streamed, full, _ = both(tmp_path, corpus(13), ev, max_curve_bins=4)
    assert streamed.summary["composition"] == full["composition"]


def test_errors_are_the_full_evaluations(tmp_path):
    scenes = [
        s.with_columns(truth_label=pl.lit(False), risk_survival=pl.lit(0.0))
        for s in corpus(1, n_scenes=2)
    ]
    ev = EvaluationSettings(n_boot=0, groupings=())
    paths = []
    for i, df in enumerate(scenes):
        paths.append(tmp_path / f"p{i}.parquet")
        df.drop("planner_label").write_parquet(paths[-1])
    with pytest.raises(EvaluationError) as streamed:
        evaluate_parts(paths, StreamSettings.of(ev), evaluation=ev)
    with pytest.raises(EvaluationError) as full:
        evaluate_table(pl.concat([s.drop("planner_label") for s in scenes]), settings=ev)
    assert str(streamed.value) == str(full.value)
    with pytest.raises(EvaluationError, match="unknown calibration site 'X'"):
        evaluate_parts(paths, StreamSettings(calibration_sites=("X",)))
    with pytest.raises(EvaluationError, match="no risk_gaussian column"):
        evaluate_parts(paths, StreamSettings(models=("gaussian",)))
