"""Outcome evaluation of a risk filter against a boolean reference, with scene bootstrap.

Pure numpy, arrays first, options keyword-only. The reference is either the survival
baseline (``R_S >= 1e-25``) or the hindsight truth (:mod:`risk.hindsight`); it is given
as label codes ``(A,)`` int: 1 positive, 0 negative, -1 unknown (censored). Unknown
agent-frames are left out of every rate and counted.

**Pooled** rates over agent-frames: at a threshold the filter keeps the agents with
``score >= threshold``; ``TPR = kept positives / positives``, ``FPR = kept negatives /
negatives`` over all included agent-frames together. Why pooled, unlike the paper's mean
over situations (:mod:`risk.metrics`): against hindsight most frames have no positive, so a
per-frame TPR is undefined almost everywhere, and the mean over the few frames that have
one weighs a frame with one positive like a frame with five. The **miss rate** of a
filter is ``1 - TPR`` at its threshold: the share of positives it drops.

**Clustered bootstrap**: the agent-frames of one scene are not independent (the same
agents, frame after frame), so intervals resample whole scenes: each replicate draws ``S``
scenes with replacement out of ``S`` and weighs every agent-frame by how often its scene
was drawn; the interval is the percentile interval of the replicates. All models and
references share the same draws (paired).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from risk.errors import RiskError
from risk.metrics import SortedScores, exact_sweep, trapezoid_auc, trapezoid_auc_rows

POSITIVE, NEGATIVE, UNKNOWN = 1, 0, -1
#: FPRs at which the TPR is reported.
FPR_POINTS = (0.01, 0.05, 0.1)
#: Rounding tolerance on rates.
RATE_TOLERANCE = 1e-12


# ---------------------------------------------------------------------- the sweep
@dataclass(frozen=True, eq=False)
class PooledRoc:
    """A pooled ROC curve: ``thresholds (K,)`` ascending, ``tpr``, ``fpr (K,)`` (keep
    ``score >= threshold``), ``auc`` (trapezoids closed with (0, 0) and (1, 1)),
    ``n_positive``, ``n_negative`` (included agent-frames)."""

    thresholds: np.ndarray
    tpr: np.ndarray
    fpr: np.ndarray
    auc: float
    n_positive: int
    n_negative: int


def pooled_roc(scores: np.ndarray, reference: np.ndarray) -> PooledRoc:
    """The pooled ROC of ``scores (A,)`` (NaN: not an agent) against ``reference (A,)``
    label codes (1, 0, -1 = unknown, left out) or booleans. Exact: every distinct score is
    a threshold."""
    include, positive = reference_mask(reference)
    s = np.where(include, np.asarray(scores, dtype=np.float64), np.nan)
    srt = SortedScores.build(s, positive)
    tpr, fpr = srt.rates()
    return PooledRoc(
        thresholds=srt.scores[srt.group_end][::-1],
        tpr=tpr[::-1],
        fpr=fpr[::-1],
        auc=trapezoid_auc(fpr, tpr),
        n_positive=int(srt.positive.sum()),
        n_negative=int((~srt.positive).sum()),
    )


def reference_mask(reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(included, positive)`` ``(A,)`` bool from label codes (1, 0, -1) or booleans."""
    r = np.asarray(reference)
    if r.dtype == bool:
        return np.ones(r.shape, dtype=bool), r.copy()
    if not np.issubdtype(r.dtype, np.integer) or not np.isin(r, (-1, 0, 1)).all():
        raise RiskError("a reference must be booleans or label codes 1, 0, -1 (unknown)")
    return r >= 0, r == POSITIVE


def tpr_at_fpr(tpr_desc: np.ndarray, fpr_desc: np.ndarray, fpr: float) -> float:
    """The best TPR of a sweep (strictest first) whose FPR is at most ``fpr``; 0 when even
    the strictest threshold exceeds it; NaN when the FPR is undefined (no negative)."""
    if fpr_desc.size == 0 or np.isnan(fpr_desc).any() or np.isnan(tpr_desc).any():
        return math.nan
    idx = int(np.searchsorted(fpr_desc, fpr + RATE_TOLERANCE, side="right")) - 1
    return float(tpr_desc[idx]) if idx >= 0 else 0.0


def threshold_for_recall(scores: np.ndarray, reference: np.ndarray, target: float) -> float:
    """The highest threshold whose pooled TPR against ``reference`` reaches ``target``
    (keeps the fewest agents); -inf when there is no positive."""
    if not 0.0 <= target <= 1.0:
        raise RiskError(f"target TPR must be in [0, 1], got {target}")
    roc = pooled_roc(scores, reference)
    ok = roc.tpr >= target - RATE_TOLERANCE
    return float(roc.thresholds[ok].max()) if ok.any() else -math.inf


# ---------------------------------------------------------------------- bootstrap
def bootstrap_weights(
    clusters: np.ndarray, *, n_boot: int = 1000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Scene draws for a clustered bootstrap: ``(codes (A,), counts (B, S))``.

    ``clusters (A,)``: any labels (scene names); ``codes`` maps each agent-frame to its
    cluster ``0 .. S-1``; ``counts[b, s]``: how often replicate ``b`` drew cluster ``s``
    (``S`` draws with replacement, so each row sums to ``S``).
    """
    if n_boot < 1:
        raise RiskError(f"n_boot must be >= 1, got {n_boot}")
    _, codes = np.unique(np.asarray(clusters), return_inverse=True)
    n = int(codes.max()) + 1 if codes.size else 0
    return codes.astype(np.int64), scene_draws(n, n_boot=n_boot, seed=seed)


def scene_draws(n_scenes: int, *, n_boot: int = 1000, seed: int = 0) -> np.ndarray:
    """``(B, S)`` int64: how often each replicate draws each of ``S`` clusters (``S``
    draws with replacement). Cluster ``s`` is the ``s``-th in a fixed order (sorted
    names, or the key order of a run's scenes): the draws depend on ``seed`` and ``S``
    only, never on the order in which the scenes were computed."""
    if n_boot < 1:
        raise RiskError(f"n_boot must be >= 1, got {n_boot}")
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, max(n_scenes, 1), size=(n_boot, n_scenes))
    counts = np.zeros((n_boot, n_scenes), dtype=np.int64)
    np.add.at(counts, (np.repeat(np.arange(n_boot), n_scenes), draws.ravel()), 1)
    return counts


def percentile_interval(replicates: np.ndarray, *, level: float = 0.95) -> tuple[float, float]:
    """The central ``level`` percentile interval of bootstrap replicates (NaN ones left
    out; NaN when none is finite)."""
    r = np.asarray(replicates, dtype=np.float64)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return (math.nan, math.nan)
    tail = (1.0 - level) / 2.0
    lo, hi = np.quantile(r, [tail, 1.0 - tail])
    return (float(lo), float(hi))


def cluster_bootstrap(
    statistic: Callable[[np.ndarray], float],
    clusters: np.ndarray,
    *,
    n_boot: int = 1000,
    level: float = 0.95,
    seed: int = 0,
) -> dict[str, float]:
    """A statistic of weighted agent-frames and its clustered-bootstrap interval.

    ``statistic(weights (A,))`` -> float, called once with unit weights (the estimate)
    and once per replicate with each agent-frame weighted by its cluster's draw count.
    Returns ``value``, ``lo``, ``hi`` and ``replicates_defined`` (replicates where the
    statistic was finite).
    """
    codes, counts = bootstrap_weights(clusters, n_boot=n_boot, seed=seed)
    value = float(statistic(np.ones(codes.size)))
    reps = np.array([statistic(counts[b][codes].astype(np.float64)) for b in range(n_boot)])
    lo, hi = percentile_interval(reps, level=level)
    return {"value": value, "lo": lo, "hi": hi, "replicates_defined": int(np.isfinite(reps).sum())}


# ---------------------------------------------------------------------- one filter
def _interval(value: float, reps: np.ndarray, level: float) -> dict[str, Any]:
    lo, hi = percentile_interval(reps, level=level)
    return {"value": value, "ci": [lo, hi]}


def evaluate_scores(
    scores: np.ndarray,
    reference: np.ndarray,
    clusters: np.ndarray,
    agents: np.ndarray,
    *,
    thresholds: Mapping[str, float] | None = None,
    fpr_points: Sequence[float] = FPR_POINTS,
    draws: np.ndarray | None = None,
    level: float = 0.95,
    situations: np.ndarray | None = None,
) -> dict[str, Any]:
    """ROC, AUC, TPR at fixed FPRs and miss rates of one model against one reference.

    With ``situations (A,)`` (int situation codes) the summary also holds
    ``auc_situation_mean``: the AUC of the curve averaged over situations, as
    ``replay stats`` computes it (:func:`risk.metrics.exact_sweep`), over the included
    agent-frames (no interval).

    ``scores (A,)`` (NaN: not an agent); ``reference (A,)`` label codes (1, 0, -1) or
    bool; ``clusters (A,)`` int scene codes ``0 .. S-1`` (see :func:`bootstrap_weights`);
    ``agents (A,)`` int64 identity of the agent (distinct agents are counted by it, e.g.
    a hash of scene, ego and agent id); ``thresholds``: named filter thresholds whose miss
    rate is reported; ``draws (B, S)``: bootstrap counts (none: no intervals).
    """
    include, positive = reference_mask(reference)
    s = np.asarray(scores, dtype=np.float64)
    srt = SortedScores.build(np.where(include, s, np.nan), positive, clusters)
    tpr, fpr = srt.rates()
    out: dict[str, Any] = {
        "agent_frames": int(srt.scores.size),
        "positives": int(srt.positive.sum()),
        "auc": {"value": trapezoid_auc(fpr, tpr)},
        "auc_situation_mean": _situation_mean_auc(s, include, positive, situations),
        "tpr_at_fpr": {f"{f:g}": {"value": tpr_at_fpr(tpr, fpr, f)} for f in fpr_points},
        "miss_rate": {},
    }
    cuts = {name: srt.kept_before(t) for name, t in (thresholds or {}).items()}
    agents = np.asarray(agents, dtype=np.int64)
    pos_all = include & positive & ~np.isnan(s)
    for name, thr in (thresholds or {}).items():
        missed = pos_all & ~(s >= thr)
        n_pos = int(srt.positive.sum())
        out["miss_rate"][name] = {
            "threshold": float(thr),
            "value": float(missed.sum() / n_pos) if n_pos else math.nan,
            "missed_agent_frames": int(missed.sum()),
            "missed_agents": int(np.unique(agents[missed]).size),
            "kept_share": cuts[name] / srt.scores.size if srt.scores.size else math.nan,
        }
    if draws is None or srt.scores.size == 0:
        return out
    auc_r, tpr_r, miss_r = _replicates(srt, draws, list(cuts.values()), fpr_points)
    out["auc"] = _interval(out["auc"]["value"], auc_r, level)
    for k, f in enumerate(fpr_points):
        key = f"{f:g}"
        out["tpr_at_fpr"][key] = _interval(out["tpr_at_fpr"][key]["value"], tpr_r[:, k], level)
    for k, name in enumerate(cuts):
        lo, hi = percentile_interval(miss_r[:, k], level=level)
        out["miss_rate"][name]["ci"] = [lo, hi]
    return out


#: Score bins of the bootstrap replicates' curves (see :func:`_replicates`).
BOOT_BINS = 512
#: Elements of one (replicates x bins) block of the bootstrap.
BOOT_BLOCK_ELEMENTS = 4_000_000


def _replicates(
    srt: SortedScores, draws: np.ndarray, cuts: Sequence[int], fpr_points: Sequence[float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """AUC ``(B,)``, TPR at each FPR ``(B, P)`` and miss rate at each cut ``(B, C)`` of
    every bootstrap replicate.

    A replicate weighs cluster ``c`` by ``draws[b, c]``, so every count it needs is a
    matrix product of the draws with per-cluster counts: positives and negatives per
    (score bin, cluster) for the curve, positives kept per cluster for the miss rates
    (exact). The curve of a replicate is taken at no more than :data:`BOOT_BINS` score
    bins (consecutive distinct scores merged, ties never split); with fewer distinct
    scores it is exact. Cost ``O(A + B * S * bins)``, with BLAS doing the products.
    """
    present, cluster = np.unique(srt.cluster, return_inverse=True)  # clusters seen here
    draws = draws[:, present]
    n_clusters = present.size
    n_groups = srt.group_end.size
    group = np.repeat(np.arange(n_groups), np.diff(np.r_[-1, srt.group_end]))
    n_bins = min(n_groups, BOOT_BINS)
    bins = group * n_bins // max(n_groups, 1)
    flat = bins * n_clusters + cluster
    pos = (
        np.bincount(flat[srt.positive], minlength=n_bins * n_clusters)
        .reshape(n_bins, n_clusters)
        .astype(np.float64)
    )
    neg = np.bincount(flat[~srt.positive], minlength=n_bins * n_clusters).reshape(
        n_bins, n_clusters
    )
    kept_pos = np.array(
        [np.bincount(cluster[:cut][srt.positive[:cut]], minlength=n_clusters) for cut in cuts]
    ).reshape(len(cuts), n_clusters)
    all_pos = pos.sum(axis=0)
    d = draws.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        tot_p = d @ all_pos
        miss = np.where(tot_p[:, None] > 0, 1.0 - (d @ kept_pos.T) / tot_p[:, None], np.nan)
    auc, tpr_at = replicate_curves(pos, neg, d, fpr_points)
    return auc, tpr_at, miss


def replicate_curves(
    pos: np.ndarray, neg: np.ndarray, draws: np.ndarray, fpr_points: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """AUC ``(B,)`` and TPR at each FPR ``(B, P)`` of every bootstrap replicate, from the
    positives and negatives per (score bin, cluster) ``pos``, ``neg (bins, C)`` (bins
    strictest first) and the draws ``(B, C)``: a replicate's counts per bin are the
    draw-weighted sums over clusters. Blocks of replicates keep the (B, bins) matrices
    small."""
    n_boot, n_bins = draws.shape[0], pos.shape[0]
    d = np.asarray(draws, dtype=np.float64)
    pos = np.asarray(pos, dtype=np.float64)
    neg = np.asarray(neg, dtype=np.float64)
    auc = np.empty(n_boot)
    tpr_at = np.empty((n_boot, len(fpr_points)))
    step = max(1, BOOT_BLOCK_ELEMENTS // max(n_bins, 1))
    for start in range(0, n_boot, step):
        blk = d[start : start + step]
        wp = np.cumsum(blk @ pos.T, axis=1)  # (b, bins)
        wn = np.cumsum(blk @ neg.T, axis=1)
        tp, tn = wp[:, -1:], wn[:, -1:]
        with np.errstate(invalid="ignore", divide="ignore"):
            tpr = np.where(tp > 0, wp / tp, np.nan)
            fpr = np.where(tn > 0, wn / tn, np.nan)
        auc[start : start + step] = trapezoid_auc_rows(fpr, tpr)
        rows = np.arange(blk.shape[0])
        for k, f in enumerate(fpr_points):
            with np.errstate(invalid="ignore"):
                idx = (fpr <= f + RATE_TOLERANCE).sum(axis=1) - 1
            val = np.where(idx >= 0, tpr[rows, np.maximum(idx, 0)], 0.0)
            tpr_at[start : start + step, k] = np.where(np.isnan(fpr[:, 0]), np.nan, val)
    return auc, tpr_at


def _situation_mean_auc(
    scores: np.ndarray, include: np.ndarray, positive: np.ndarray, situations: np.ndarray | None
) -> float | None:
    if situations is None:
        return None
    ok = include & ~np.isnan(scores)
    if not ok.any():
        return math.nan
    _, sit = np.unique(np.asarray(situations)[ok], return_inverse=True)
    return float(exact_sweep(scores[ok], sit.astype(np.int64), positive[ok]).auc)


# ---------------------------------------------------------------------- counts
def distinct(keys: np.ndarray, mask: np.ndarray) -> int:
    """Distinct ``keys (A,)`` among the agent-frames where ``mask (A,)`` holds."""
    return int(np.unique(np.asarray(keys)[np.asarray(mask, dtype=bool)]).size)


def reference_counts(
    reference: np.ndarray, agents: np.ndarray, clusters: np.ndarray
) -> dict[str, int]:
    """Agent-frames positive / negative / unknown, distinct positive agents, and clusters
    (scenes) with a positive."""
    r = np.asarray(reference)
    include, positive = reference_mask(r)
    return {
        "agent_frames": int(r.size),
        "positive_agent_frames": int(positive.sum()),
        "negative_agent_frames": int((include & ~positive).sum()),
        "unknown_agent_frames": int((~include).sum()),
        "positive_agents": distinct(agents, positive),
        "agents": distinct(agents, np.ones(r.size, dtype=bool)),
        "scenes_with_positive": distinct(clusters, positive),
    }


def stage_misses(
    kept: np.ndarray, reference: np.ndarray, agents: np.ndarray, stage_names: Sequence[str]
) -> list[dict[str, Any]]:
    """The cascade's misses per stage: positives of ``reference`` that stage ``k`` (or an
    earlier one) dropped. ``kept (A, K)`` bool: kept after each stage (the table's
    ``kept_<stage>``, already cumulative)."""
    k = np.asarray(kept, dtype=bool)
    include, positive = reference_mask(reference)
    pos = include & positive
    n_pos = int(pos.sum())
    out = []
    for j, name in enumerate(stage_names):
        missed = pos & ~k[:, j]
        out.append(
            {
                "stage": name,
                "missed_agent_frames": int(missed.sum()),
                "miss_rate": float(missed.sum() / n_pos) if n_pos else math.nan,
                "missed_agents": distinct(agents, missed),
                "kept_share": float(k[:, j].mean()) if k.shape[0] else math.nan,
            }
        )
    return out


def site_transfer(
    scores: np.ndarray,
    reference: np.ndarray,
    sites: np.ndarray,
    *,
    calibration_sites: Sequence[Any],
    target_tpr: float = 0.95,
) -> dict[str, Any]:
    """Calibrate a threshold on some recording sites, test it on the others.

    The threshold is the highest one whose pooled TPR against ``reference`` reaches
    ``target_tpr`` on the agent-frames of ``calibration_sites``; returns it with the TPR
    (1 - miss rate) and the kept share it gives on the calibration and on the test sites.
    """
    site = np.asarray(sites)
    calib = np.isin(site, np.asarray(list(calibration_sites), dtype=site.dtype))
    if not calib.any() or calib.all():
        raise RiskError("site transfer needs agent-frames on calibration and on test sites")
    s = np.asarray(scores, dtype=np.float64)
    r = np.asarray(reference)
    thr = threshold_for_recall(s[calib], r[calib], target_tpr)
    result: dict[str, Any] = {
        "calibration_sites": sorted(str(x) for x in np.unique(site[calib])),
        "test_sites": sorted(str(x) for x in np.unique(site[~calib])),
        "target_tpr": target_tpr,
        "threshold": thr,
    }
    for part, mask in (("calibration", calib), ("test", ~calib)):
        include, positive = reference_mask(r[mask])
        pos = include & positive & ~np.isnan(s[mask])
        agent = include & ~np.isnan(s[mask])
        keep = s[mask] >= thr
        result[part] = {
            "positives": int(pos.sum()),
            "tpr": float((keep & pos).sum() / pos.sum()) if pos.any() else math.nan,
            "kept_share": float((keep & agent).sum() / agent.sum()) if agent.any() else math.nan,
        }
    return result


# ---------------------------------------------------------------------- everything
#: Target TPRs of the named operating thresholds, calibrated on each reference.
TPR_TARGETS = (0.95, 1.0)


def operating_thresholds(
    scores: np.ndarray,
    references: Mapping[str, np.ndarray],
    *,
    targets: Sequence[float] = TPR_TARGETS,
) -> dict[str, float]:
    """Named thresholds of one model: ``tpr<target>_<reference>``, the highest threshold
    whose pooled TPR against that reference reaches the target (the filter a user would
    calibrate on it)."""
    return {
        f"tpr{t:g}_{name}": threshold_for_recall(scores, ref, t)
        for name, ref in references.items()
        for t in targets
    }


def evaluate_references(
    scores: Mapping[str, np.ndarray],
    references: Mapping[str, np.ndarray],
    *,
    scenes: np.ndarray,
    agents: np.ndarray,
    groups: Mapping[str, np.ndarray] | None = None,
    kept: np.ndarray | None = None,
    stage_names: Sequence[str] = (),
    sites: np.ndarray | None = None,
    calibration_sites: Sequence[Any] | None = None,
    situations: np.ndarray | None = None,
    targets: Sequence[float] = TPR_TARGETS,
    fpr_points: Sequence[float] = FPR_POINTS,
    n_boot: int = 1000,
    level: float = 0.95,
    seed: int = 0,
) -> dict[str, Any]:
    """Every model against every reference, overall and per group, with scene-bootstrap
    intervals; the cascade's misses per stage; thresholds moved between sites.

    ``scores``: model -> ``(A,)`` risks (NaN: not an agent); ``references``: name ->
    ``(A,)`` label codes (1, 0, -1 unknown) or bool; ``scenes (A,)``: the bootstrap
    clusters; ``agents (A,)`` int64: agent identity for distinct counts; ``groups``:
    grouping name -> ``(A,)`` labels (e.g. dataset, kind); ``kept (A, K)``: the cascade's
    kept-after-stage flags with ``stage_names``; ``sites (A,)`` and
    ``calibration_sites``: for :func:`site_transfer` (at the first target, per model
    and reference); ``situations (A,)``: situation codes for the situation-mean AUC of
    ``replay stats`` beside the pooled one. ``n_boot = 0``: no intervals.
    """
    if not scores:
        raise RiskError("no model scores to evaluate")
    codes, draws = (
        bootstrap_weights(scenes, n_boot=n_boot, seed=seed)
        if n_boot > 0
        else (np.unique(np.asarray(scenes), return_inverse=True)[1], None)
    )
    refs = dict(references)
    thresholds = {m: operating_thresholds(s, refs, targets=targets) for m, s in scores.items()}

    def block(mask: np.ndarray | None) -> dict[str, Any]:
        sel = slice(None) if mask is None else mask
        return {
            "references": {
                name: reference_counts(r[sel], agents[sel], codes[sel]) for name, r in refs.items()
            },
            "models": {
                m: {
                    name: evaluate_scores(
                        s[sel],
                        r[sel],
                        codes[sel],
                        agents[sel],
                        thresholds=thresholds[m],
                        fpr_points=fpr_points,
                        draws=draws,
                        level=level,
                        situations=None if situations is None else situations[sel],
                    )
                    for name, r in refs.items()
                }
                for m, s in scores.items()
            },
        }

    agents = np.asarray(agents, dtype=np.int64)
    situations = None if situations is None else np.asarray(situations)
    refs = {k: np.asarray(v) for k, v in refs.items()}
    scores = {k: np.asarray(v, dtype=np.float64) for k, v in scores.items()}
    out: dict[str, Any] = {
        "bootstrap": {
            "n_boot": n_boot,
            "level": level,
            "seed": seed,
            "scenes": int(codes.max()) + 1,
        },
        "thresholds": thresholds,
        **block(None),
        "by": {},
    }
    for gname, labels in (groups or {}).items():
        lab = np.asarray(labels)
        out["by"][gname] = {str(g): block(lab == g) for g in np.unique(lab)}
    if kept is not None:
        out["cascade"] = {
            name: stage_misses(kept, r, agents, stage_names) for name, r in refs.items()
        }
    if sites is not None and calibration_sites:
        site_arr = np.asarray(sites)
        cal = np.isin(site_arr, np.asarray(list(calibration_sites), dtype=site_arr.dtype))
        if cal.any() and not cal.all():
            out["site_transfer"] = {
                m: {
                    name: site_transfer(
                        s, r, site_arr, calibration_sites=calibration_sites, target_tpr=targets[0]
                    )
                    for name, r in refs.items()
                }
                for m, s in scores.items()
            }
    return out
