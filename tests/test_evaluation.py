"""risk.evaluation: pooled ROC, miss rates, clustered bootstrap, counts, site transfer."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from risk.errors import RiskError
from risk.evaluation import (
    bootstrap_weights,
    cluster_bootstrap,
    evaluate_references,
    evaluate_scores,
    pooled_roc,
    reference_counts,
    site_transfer,
    stage_misses,
    threshold_for_recall,
    tpr_at_fpr,
)
from risk.metrics import trapezoid_auc


def test_pooled_roc_by_hand():
    scores = np.array([0.9, 0.8, 0.7, 0.6, np.nan, 0.5])
    ref = np.array([1, 0, 1, -1, 1, 0])  # the unknown and the NaN score are left out
    roc = pooled_roc(scores, ref)
    assert roc.n_positive == 2 and roc.n_negative == 2
    np.testing.assert_allclose(roc.thresholds, [0.5, 0.7, 0.8, 0.9])
    np.testing.assert_allclose(roc.tpr, [1.0, 1.0, 0.5, 0.5])
    np.testing.assert_allclose(roc.fpr, [1.0, 0.5, 0.5, 0.0])
    # Points (0,0) (0,.5) (.5,.5) (.5,1) (1,1): area 0.75.
    assert roc.auc == pytest.approx(0.75)
    assert threshold_for_recall(scores, ref, 1.0) == pytest.approx(0.7)
    assert tpr_at_fpr(roc.tpr[::-1], roc.fpr[::-1], 0.0) == 0.5
    assert tpr_at_fpr(roc.tpr[::-1], roc.fpr[::-1], 0.5) == 1.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.booleans()), min_size=2, max_size=40))
def test_pooled_roc_matches_brute_force(rows):
    s = np.array([r[0] for r in rows], dtype=float)
    ref = np.array([r[1] for r in rows])
    roc = pooled_roc(s, ref)
    for t, tpr, fpr in zip(roc.thresholds, roc.tpr, roc.fpr, strict=True):
        keep = s >= t
        if ref.any():
            assert tpr == pytest.approx((keep & ref).sum() / ref.sum())
        if (~ref).any():
            assert fpr == pytest.approx((keep & ~ref).sum() / (~ref).sum())
    if ref.any() and (~ref).any():  # AUC = P(score_pos > score_neg) + ties / 2
        p, n = s[ref][:, None], s[~ref][None, :]
        assert roc.auc == pytest.approx(np.mean((p > n) + 0.5 * (p == n)))


def _binomial_quantile(n: int, p: float, q: float) -> int:
    cdf = 0.0
    for k in range(n + 1):
        cdf += math.comb(n, k) * p**k * (1 - p) ** (n - k)
        if cdf >= q - 1e-12:
            return k
    return n


def test_cluster_bootstrap_known_answer():
    # 40 scenes of 5 identical agent-frames each; 12 scenes are "hits". The weighted
    # share of hits in a replicate is (hit scenes drawn) / 40 ~ Binomial(40, 0.3) / 40.
    n_scenes, hits = 40, 12
    x_scene = np.r_[np.ones(hits), np.zeros(n_scenes - hits)]
    clusters = np.repeat(np.arange(n_scenes), 5)
    x = x_scene[clusters]
    res = cluster_bootstrap(lambda w: float((w * x).sum() / w.sum()), clusters,
                            n_boot=20000, seed=1)  # fmt: skip
    assert res["value"] == pytest.approx(0.3)
    lo = _binomial_quantile(n_scenes, 0.3, 0.025) / n_scenes
    hi = _binomial_quantile(n_scenes, 0.3, 0.975) / n_scenes
    assert res["lo"] == pytest.approx(lo, abs=1 / n_scenes + 1e-9)
    assert res["hi"] == pytest.approx(hi, abs=1 / n_scenes + 1e-9)
    # Resampling scenes, five copies of a frame carry no more information than one: the
    # interval is the one of one frame per scene (same draws), not sqrt(5) narrower.
    single = cluster_bootstrap(lambda w: float((w * x_scene).sum() / w.sum()),
                               np.arange(n_scenes), n_boot=20000, seed=1)  # fmt: skip
    assert (res["lo"], res["hi"]) == pytest.approx((single["lo"], single["hi"]))


def test_bootstrap_weights_draw_whole_scenes():
    codes, counts = bootstrap_weights(np.array(["b", "a", "b", "c"]), n_boot=50, seed=0)
    assert codes.tolist() == [1, 0, 1, 2]
    assert counts.shape == (50, 3) and (counts.sum(axis=1) == 3).all()


def test_evaluate_scores_counts_misses_and_distinct_agents():
    scores = np.array([0.9, 0.1, 0.1, 0.8, 0.2, 0.05])
    ref = np.array([1, 1, 1, 0, 0, -1])
    clusters = np.array([0, 0, 1, 1, 2, 2])
    agents = np.array([10, 11, 11, 12, 13, 14])  # agent 11 is positive in two frames
    _, draws = bootstrap_weights(clusters, n_boot=200, seed=0)
    out = evaluate_scores(scores, ref, clusters, agents, thresholds={"t": 0.5}, draws=draws)
    miss = out["miss_rate"]["t"]
    assert out["positives"] == 3 and out["agent_frames"] == 5
    assert miss["value"] == pytest.approx(2 / 3)
    assert miss["missed_agent_frames"] == 2 and miss["missed_agents"] == 1
    assert miss["kept_share"] == pytest.approx(2 / 5)
    lo, hi = miss["ci"]
    assert 0.0 <= lo <= miss["value"] <= hi <= 1.0
    assert out["auc"]["ci"][0] <= out["auc"]["value"] <= out["auc"]["ci"][1]


def test_counts_stage_misses_and_site_transfer():
    ref = np.array([1, 1, 0, -1, 1, 0])
    agents = np.array([1, 1, 2, 3, 4, 5])
    counts = reference_counts(ref, agents, np.array([0, 0, 0, 1, 1, 1]))
    assert counts["positive_agent_frames"] == 3 and counts["positive_agents"] == 2
    assert counts["unknown_agent_frames"] == 1 and counts["scenes_with_positive"] == 2
    kept = np.array([[1, 1], [1, 0], [1, 0], [0, 0], [0, 0], [1, 1]], dtype=bool)
    stages = stage_misses(kept, ref, agents, ["a", "b"])
    assert [s["missed_agent_frames"] for s in stages] == [1, 2]
    assert [s["missed_agents"] for s in stages] == [1, 2]
    scores = np.array([0.9, 0.5, 0.1, 0.3, 0.4, 0.2])
    sites = np.array(["x", "x", "x", "y", "y", "y"])
    tr = site_transfer(scores, ref, sites, calibration_sites=["x"], target_tpr=1.0)
    assert tr["threshold"] == pytest.approx(0.5)
    assert tr["test"]["tpr"] == 0.0 and tr["test"]["positives"] == 1
    with pytest.raises(RiskError, match="calibration and on test"):
        site_transfer(scores, ref, sites, calibration_sites=["x", "y"])


def test_evaluate_references_overall_groups_cascade_and_sites():
    rng = np.random.default_rng(0)
    a = 400
    scenes = rng.integers(0, 20, a)
    truth = np.where(rng.random(a) < 0.1, 1, np.where(rng.random(a) < 0.2, -1, 0))
    baseline = rng.random(a) < 0.3
    good = np.where(truth == 1, 0.6, 0.0) + rng.random(a) * 0.5  # separates truth well
    kind = np.where(rng.random(a) < 0.5, "vehicle", "pedestrian")
    kept = np.column_stack([good > 0.2, good > 0.4])
    out = evaluate_references(
        {"good": good, "noise": rng.random(a)},
        {"survival": baseline, "hindsight": truth},
        scenes=scenes,
        agents=np.arange(a) // 2,
        groups={"kind": kind},
        kept=kept,
        stage_names=["s1", "s2"],
        sites=np.where(scenes < 10, "x", "y"),
        calibration_sites=["x"],
        n_boot=100,
    )
    h = out["models"]["good"]["hindsight"]
    assert h["auc"]["value"] > 0.9 > out["models"]["noise"]["hindsight"]["auc"]["value"]
    assert h["auc"]["ci"][0] <= h["auc"]["value"] <= h["auc"]["ci"][1]
    assert out["references"]["hindsight"]["unknown_agent_frames"] == int((truth == -1).sum())
    # Misses at one threshold add up over the kinds.
    name = "tpr0.95_survival"
    total = h["miss_rate"][name]["missed_agent_frames"]
    parts = [
        out["by"]["kind"][k]["models"]["good"]["hindsight"]["miss_rate"][name][
            "missed_agent_frames"
        ]
        for k in ("pedestrian", "vehicle")
    ]
    assert sum(parts) == total
    # The baseline-calibrated threshold keeps >= 95 % of the baseline.
    assert out["models"]["good"]["survival"]["miss_rate"][name]["value"] <= 0.05 + 1e-12
    assert [s["stage"] for s in out["cascade"]["hindsight"]] == ["s1", "s2"]
    assert out["site_transfer"]["good"]["hindsight"]["test_sites"] == ["y"]


def test_vectorised_replicates_match_one_at_a_time(monkeypatch):
    import risk.evaluation as ev

    rng = np.random.default_rng(5)
    a = 300
    scores = np.round(rng.random(a), 2)  # ties
    ref = rng.random(a) < 0.2
    clusters = rng.integers(0, 15, a)
    srt = ev.SortedScores.build(scores, ref, clusters)
    _, draws = bootstrap_weights(clusters, n_boot=30, seed=2)
    cuts = [srt.kept_before(0.5), srt.kept_before(0.9)]
    monkeypatch.setattr(ev, "BOOT_BLOCK_ELEMENTS", 7 * a)  # several blocks
    auc, tpr, miss = ev._replicates(srt, draws, cuts, (0.05, 0.2))
    for b in range(30):
        w = draws[b][srt.cluster].astype(float)
        t, f = srt.rates(w)
        assert auc[b] == pytest.approx(trapezoid_auc(f, t))
        assert tpr[b].tolist() == pytest.approx([tpr_at_fpr(t, f, x) for x in (0.05, 0.2)])
        wp = np.cumsum(w * srt.positive)
        assert miss[b].tolist() == pytest.approx([1 - wp[c - 1] / wp[-1] for c in cuts])


def test_situation_mean_auc_is_replay_stats_sweep():
    from risk.metrics import exact_sweep

    scores = np.array([0.9, 0.2, 0.5, 0.4, 0.8, 0.1, 0.3])
    ref = np.array([1, 0, 0, 1, -1, 0, 1])
    sit = np.array([0, 0, 1, 1, 1, 2, 2])
    out = evaluate_scores(scores, ref, sit, np.arange(7), situations=sit)
    keep = ref >= 0  # the censored one is left out
    want = exact_sweep(scores[keep], sit[keep], ref[keep] == 1).auc
    assert out["auc_situation_mean"] == pytest.approx(want)
    assert evaluate_scores(scores, ref, sit, np.arange(7))["auc_situation_mean"] is None
