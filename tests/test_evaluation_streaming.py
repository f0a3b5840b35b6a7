"""replay.analysis.evaluation.streaming: how the per-scene passes hold and merge their
pieces (chunks of curves, coarsened curves, scenes lacking a column, count sums). The
figures against the full-rows oracle: tests/test_evaluation_parts.py."""

from __future__ import annotations

import json
import math

import polars as pl
import pytest
from test_evaluation_parts import both, corpus

from replay.analysis.evaluation.corpus import EvaluationSettings
from replay.analysis.evaluation.streaming import add_counts, max_difference


def test_a_scene_without_a_reference_column_is_unknown_under_it(tmp_path):
    scenes = corpus(7, n_scenes=3)
    scenes[1] = scenes[1].drop("planner_label")  # that scene has no planner truth
    ev = EvaluationSettings(n_boot=0, groupings=())
    streamed, full, _ = both(tmp_path, scenes, ev)
    assert streamed.summary["references"]["planner"] == full["references"]["planner"]
    assert full["references"]["planner"]["unknown_agent_frames"] >= scenes[1].height
    assert "ci" not in streamed.summary["models"]["current_distance"]["hindsight"]["auc"]


def test_one_curve_per_pass_gives_the_same_summary(tmp_path, monkeypatch):
    from replay.analysis.evaluation import streaming

    scenes = corpus(11, n_scenes=5)
    ev = EvaluationSettings(n_boot=25, groupings=("dataset", "kind"))
    together, _, _ = both(tmp_path, scenes, ev)
    monkeypatch.setattr(streaming, "CURVES_PER_PASS", 1)
    apart, _, _ = both(tmp_path, scenes, ev)
    assert apart.roc.equals(together.roc) and apart.positives.equals(together.positives)
    assert json.dumps(apart.summary, sort_keys=True) == json.dumps(together.summary, sort_keys=True)
    assert "ci" in apart.summary["models"]["survival"]["hindsight"]["auc"]


def test_coarsened_curves_keep_exact_thresholds_and_their_auc_bound(tmp_path):
    # At most 8 bins per merged curve: the grid is coarsened many levels, the AUC moves
    # within its (wider) bound, the thresholds and miss rates stay exact.
    ev = EvaluationSettings(n_boot=10, groupings=())
    streamed, full, _ = both(tmp_path, corpus(3), ev, max_curve_bins=8)
    block = streamed.summary["models"]["current_distance"]["hindsight"]
    assert block["grid_level"] > 0
    assert max_difference(streamed.summary, full)["beyond_bound"] == 0
    assert streamed.summary["thresholds"] == full["thresholds"]
    want = full["models"]["current_distance"]["hindsight"]["miss_rate"]
    for t, w in want.items():
        assert block["miss_rate"][t]["missed_agent_frames"] == w["missed_agent_frames"]
        assert block["miss_rate"][t]["kept_share"] == w["kept_share"]


def test_a_part_holding_two_scenes_is_two_bootstrap_clusters(tmp_path):
    # A merged table given as input: one part, several scenes; the clusters are scenes.
    scenes = corpus(17, n_scenes=4)
    ev = EvaluationSettings(n_boot=20, groupings=())
    apart, full, _ = both(tmp_path / "a", scenes, ev)
    merged, _, _ = both(tmp_path / "b", [pl.concat(scenes[:2]), *scenes[2:]], ev)
    assert merged.summary["bootstrap"]["scenes"] == full["bootstrap"]["scenes"] == 4
    assert json.dumps(merged.summary, sort_keys=True) == json.dumps(apart.summary, sort_keys=True)


def test_add_counts_by_hand():
    a = {"n": 1, "flag": False, "pairs": [{"a": "x", "c": 2}], "only_a": 5}
    b = {"n": 2, "flag": True, "pairs": [{"a": "x", "c": 3}], "only_b": 1.5}
    assert add_counts(a, b) == {"n": 3, "flag": True, "pairs": [{"a": "x", "c": 5}],
                                "only_a": 5, "only_b": 1.5}  # fmt: skip
    assert not math.isnan(add_counts(1.0, 2.0))
    with pytest.raises(ValueError):
        add_counts([1, 2], [1])
