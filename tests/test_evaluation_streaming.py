"""replay.analysis.evaluation.streaming: the per-scene pass over part files against the
full-rows evaluation (evaluate_table on every row at once, the slow obvious oracle)."""

from __future__ import annotations

import json
import math

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from replay.analysis.evaluation.corpus import EvaluationSettings, evaluate_table
from replay.analysis.evaluation.streaming import (
    StreamSettings,
    add_counts,
    max_difference,
    streamed_roc,
)


def corpus(seed: int, n_scenes: int = 4, integer_scores: bool = False) -> list[pl.DataFrame]:
    """Random scenes: frames x egos x agents rows with scores, hindsight truth (censored
    windows too), planner labels, cascade flags; rows shuffled inside each scene."""
    rng = np.random.default_rng(seed)
    scenes = []
    for k in range(n_scenes):
        frame, ego, agent = np.meshgrid(np.arange(4), np.arange(2), np.arange(5), indexing="ij")
        n = frame.size
        truth = rng.random(n) < 0.25
        risk = rng.integers(0, 6, n).astype(float) if integer_scores else rng.random(n)
        df = pl.DataFrame(
            {
                "scene": [f"s{k}"] * n,
                "frame": frame.ravel(),
                "ego_id": ego.ravel(),
                "agent_id": agent.ravel(),
                "kind": rng.choice(["vehicle", "pedestrian"], n),
                "t_s": frame.ravel() * 0.1,
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


def both(tmp_path, scenes, n_boot, **stream):
    paths = []
    for i, df in enumerate(scenes):
        paths.append(tmp_path / f"s{i}.parquet")
        df.write_parquet(paths[-1])
    full = evaluate_table(
        pl.concat(scenes, how="diagonal_relaxed"),
        settings=EvaluationSettings(n_boot=n_boot, groupings=()),
    )
    return streamed_roc(paths, StreamSettings(n_boot=n_boot, **stream)), full


@settings(
    max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.integers(0, 10_000), st.booleans())
def test_the_streamed_pass_agrees_with_the_full_rows_evaluation(tmp_path, seed, integer_scores):
    streamed, full = both(tmp_path, corpus(seed, integer_scores=integer_scores), n_boot=30)
    # Exact pieces: reference counts, agreement, budgets (with intervals).
    for name, counts in streamed["references"].items():
        assert {k: full["references"][name][k] for k in counts} == counts
    assert streamed["agreement"] == full["agreement"]
    assert set(streamed["budgets"]) == set(full["budgets"])
    for name, rows in streamed["budgets"].items():
        for got, want in zip(rows, full["budgets"][name], strict=True):
            assert (got["rule"], got["k"], got["radius_m"]) == (
                want["rule"],
                want["k"],
                want["radius_m"],
            )
            assert (got["positives"], got["kept_positives"]) == (
                want["positives"],
                want["kept_positives"],
            )
            assert got["mean_kept"] == pytest.approx(want["mean_kept"], rel=1e-12)
            np.testing.assert_allclose(got["ci"], want["ci"], rtol=1e-12, equal_nan=True)
    # Operating thresholds and miss rates: exact (the crossing bins refined on a pass).
    assert streamed["thresholds"] == full["thresholds"]
    for m, refs in full["models"].items():
        for name, block in refs.items():
            for t, want in block["miss_rate"].items():
                got = streamed["models"][m][name]["miss_rate"][t]
                assert {k: got[k] for k in want if k != "ci"} == pytest.approx(
                    {k: want[k] for k in want if k != "ci"}, nan_ok=True
                )
                np.testing.assert_allclose(got["ci"], want["ci"], rtol=1e-12, equal_nan=True)
    # The ROC: within the stated bound; exact when no bin mixes distinct scores.
    diff = max_difference(streamed, full)
    assert diff["beyond_bound"] == 0
    for m, refs in streamed["models"].items():
        for name, block in refs.items():
            want = full["models"][m][name]
            if block["mixed_bins"] == 0:
                assert block["auc"]["value"] == pytest.approx(want["auc"]["value"], abs=1e-12)
                for f, t in block["tpr_at_fpr"].items():
                    assert t["value"] == pytest.approx(want["tpr_at_fpr"][f]["value"], abs=1e-12)
            if integer_scores and m == "current_distance":  # few distinct scores: exact CI
                np.testing.assert_allclose(block["auc"]["ci"], want["auc"]["ci"], atol=1e-12)


def test_a_scene_without_rows_of_a_reference_adds_nothing(tmp_path):
    scenes = corpus(7, n_scenes=3)
    scenes[1] = scenes[1].drop("planner_label")  # that scene has no planner truth
    streamed, full = both(tmp_path, scenes, n_boot=0)
    assert streamed["references"]["planner"]["agent_frames"] == (
        full["references"]["planner"]["agent_frames"]
        - full["references"]["planner"]["unknown_agent_frames"]
        + streamed["references"]["planner"]["unknown_agent_frames"]
    )
    assert streamed["references"]["hindsight"] == {
        k: full["references"]["hindsight"][k] for k in streamed["references"]["hindsight"]
    }
    assert "ci" not in streamed["models"]["current_distance"]["hindsight"]["auc"]


def test_one_model_per_pass_gives_the_same_intervals(tmp_path, monkeypatch):
    from replay.analysis.evaluation import streaming

    scenes = corpus(11, n_scenes=5)
    together, _ = both(tmp_path, scenes, n_boot=25)
    monkeypatch.setattr(streaming, "MODELS_PER_PASS", 1)
    apart, _ = both(tmp_path, scenes, n_boot=25)
    apart.pop("summary_bytes"), together.pop("summary_bytes")
    assert apart.pop("positives").equals(together.pop("positives"))
    assert json.dumps(apart, sort_keys=True) == json.dumps(together, sort_keys=True)
    assert "ci" in apart["models"]["survival"]["hindsight"]["auc"]


def test_coarsened_curves_keep_exact_thresholds_and_their_auc_bound(tmp_path):
    # At most 8 bins per merged curve: the grid is coarsened many levels, the AUC moves
    # within its (wider) bound, the thresholds and miss rates stay exact.
    streamed, full = both(tmp_path, corpus(3), n_boot=10, max_curve_bins=8)
    block = streamed["models"]["current_distance"]["hindsight"]
    assert block["grid_level"] > 0
    assert max_difference(streamed, full)["beyond_bound"] == 0
    assert streamed["thresholds"] == full["thresholds"]
    want = full["models"]["current_distance"]["hindsight"]["miss_rate"]
    for t, w in want.items():
        assert block["miss_rate"][t]["missed_agent_frames"] == w["missed_agent_frames"]
        assert block["miss_rate"][t]["kept_share"] == w["kept_share"]


def test_add_counts_by_hand():
    a = {"n": 1, "flag": False, "pairs": [{"a": "x", "c": 2}], "only_a": 5}
    b = {"n": 2, "flag": True, "pairs": [{"a": "x", "c": 3}], "only_b": 1.5}
    assert add_counts(a, b) == {"n": 3, "flag": True, "pairs": [{"a": "x", "c": 5}],
                                "only_a": 5, "only_b": 1.5}  # fmt: skip
    assert not math.isnan(add_counts(1.0, 2.0))


@settings(
    max_examples=10, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.integers(0, 10_000))
def test_the_side_blocks_add_up_to_the_full_rows_ones(tmp_path, seed):
    # Stage misses, track flags, composition counts and shares, egos, situations, short
    # scenes and the positives table: exact sums of the scenes' pieces.
    scenes = corpus(seed, n_scenes=4)
    scenes[2] = scenes[2].with_columns(pl.col("t_s") * 20)  # one scene as long as the horizon
    scenes = [
        s.with_columns(speed_mps=pl.Series(np.random.default_rng(seed + i).random(s.height) * 2))
        for i, s in enumerate(scenes)
    ]
    datasets = {"s0": "a", "s1": "b", "s2": "a", "s3": "b"}
    paths = []
    for i, df in enumerate(scenes):
        paths.append(tmp_path / f"s{i}.parquet")
        df.write_parquet(paths[-1])
    rows = pl.concat(scenes, how="diagonal_relaxed")
    full = evaluate_table(
        rows, settings=EvaluationSettings(n_boot=0, groupings=()), datasets=datasets
    )
    streamed = streamed_roc(paths, StreamSettings(n_boot=0), datasets=datasets)
    assert streamed["cascade"] == full["cascade"]
    assert streamed["track_flags"] == full["track_flags"]
    assert (streamed["egos"], streamed["situations"]) == (full["egos"], full["situations"])
    assert streamed["scenes_shorter_than_horizon"] == full["scenes_shorter_than_horizon"]
    assert streamed["scenes_shorter_than_horizon"] == ["s0", "s1", "s3"]
    for name, labels in full["composition"].items():
        for label, want in labels.items():
            got = streamed["composition"][name][label]
            assert got == pytest.approx({k: want[k] for k in got})
    from replay.analysis.evaluation.files import positives_table

    in_order = rows.sort("scene", "frame", "ego_id", maintain_order=True)  # as evaluate reads
    assert streamed["positives"].equals(positives_table(in_order, datasets))
