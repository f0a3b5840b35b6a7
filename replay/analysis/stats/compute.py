"""Dataset statistics: how well each risk model filters against the survival baseline.

Everything here works on two polars tables (see ``docs/statistics.md``):

- the **agents** table, one row per situation and agent: the columns that
  ``replay run --table`` writes (:mod:`replay.core.tables`) plus ``scene`` (a name of the
  scene the row comes from); a **situation** is one frame of one scene, identified by
  ``(scene, frame)``;
- the **frames** table, one row per situation: agent and baseline counts, the cascade's
  agents after each stage, its cumulative false negatives, its tier sizes and (when the
  frames were replayed, not read from tables) its compute times.
  :class:`replay.core.stats_sink.StatsSink` builds both while the engine runs;
  :func:`replay.analysis.stats.files.frames_from_agents` derives the frames table from an agents
  table read from disk (without times: tables do not store them).

:func:`compute_stats` turns them into the ROC curves of every model (the paper's Fig. 4),
the false negatives and false positives over the threshold of one model (Fig. 5), the
cascade funnel (Fig. 6) and per-scene and per-frame tables;
:func:`replay.analysis.stats.files.write_stats` writes them (Parquet + CSV, ``summary.json``).
Plots are in :mod:`replay.analysis.stats.plots`.

Choices the spec leaves open (documented here and in ``docs/statistics.md``):

- **Sweep**: exact. The thresholds of a model's curve are every distinct score it gives
  in the data, so each situation's TPR and FPR are evaluated at every point where they
  change. :func:`risk.metrics.exact_sweep` gets the mean curves and the std of TPR from
  cumulative sums over the agents sorted once by score (O(A log A), no situations x
  thresholds matrix); the tests check it against a plain loop over situations
  (``tests/roc_oracle.py``) with the same thresholds.
- **Undefined rates**: a situation whose baseline set is empty has no TPR, one whose
  baseline set holds every agent has no FPR; each mean is taken over the situations where
  the rate is defined and the excluded situations are counted (``situations`` in
  ``summary.json``). Frames without any other agent have neither and are counted apart.
- **Operating points** (where robustness is reported): ``tpr_0.9`` and ``tpr_0.95``,
  the highest threshold at which the mean TPR reaches 0.9 / 0.95 ("first reaches" in a
  sweep from high to low thresholds); ``tpr_1``, the highest threshold at which the mean
  TPR is 1 (every situation keeps all its important agents, so the std of TPR there is
  0 by construction; what matters there is how many agents are kept); ``youden``, the
  threshold with the largest mean TPR - mean FPR (the curve's point nearest the ideal
  corner). Besides, ``std_tpr_curve`` averages the std of TPR along the whole curve,
  weighted by the FPR span of each step, and ``std_tpr_high_tpr`` gives its range over
  mean TPR 0.8-1. The std of TPR depends strongly on the mean TPR where it is taken
  (it is 0 at TPR 1 and largest mid-curve), so compare models at the same mean TPR.
- **Std**: population standard deviation (``ddof = 0``) over the situations where TPR is
  defined. The paper does not say which; for hundreds of situations the two differ by
  less than 0.5 %.
- **Kept agents**: mean over the situations with agents (degenerate ones included:
  keeping an agent is defined everywhere) of the number of agents with
  ``score >= threshold``.
"""

from __future__ import annotations

import math
import pathlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from replay.core.stats_sink import (
    SITUATION_KEY,
    model_names_of,
    stage_names_of,
    time_columns,
    with_ego_column,
)
from replay.errors import StatsError
from risk.metrics import Sweep, confusion_counts, exact_sweep
from risk.registry import BASELINE_MODEL

#: The model of the FN/FP-over-threshold export by default (the paper's Fig. 5).
DEFAULT_ERRORS_MODEL = "headway_2d"
#: Target mean TPRs of the named operating points.
TPR_TARGETS = (0.9, 0.95, 1.0)
#: Mean TPRs within this of a target count as reaching it (sums of 1/P_s round).
TPR_TOLERANCE = 1e-9
#: Mean TPRs over which the std of TPR is reported as a range (the filtering region).
HIGH_TPR_RANGE = (0.8, 1.0)


# ---------------------------------------------------------------------- situations
@dataclass(frozen=True, eq=False)
class Situations:
    """The agent-frames of the agents table, grouped by situation.

    ``A`` agent-frames, ``S`` situations with at least one other agent (sorted by scene,
    then frame); ``situation (A,)`` maps each agent-frame to its situation.
    """

    keys: pl.DataFrame  # (S,) scene, frame
    situation: np.ndarray  # (A,) int64
    baseline: np.ndarray  # (A,) bool
    n_positive: np.ndarray  # (S,) baseline-important agents
    n_agents: np.ndarray  # (S,) other agents

    @property
    def n(self) -> int:
        return int(self.n_agents.size)

    @property
    def n_negative(self) -> np.ndarray:
        return self.n_agents - self.n_positive

    @property
    def no_positive(self) -> np.ndarray:
        """(S,) bool: empty baseline set (TPR undefined)."""
        return self.n_positive == 0

    @property
    def no_negative(self) -> np.ndarray:
        """(S,) bool: every agent is in the baseline set (FPR undefined)."""
        return self.n_negative == 0

    def split(self, values: np.ndarray) -> list[np.ndarray]:
        """(A,) values as S per-situation arrays."""
        bounds = np.flatnonzero(np.diff(self.situation)) + 1
        return np.split(values, bounds)


def situations_of(agents: pl.DataFrame) -> Situations:
    """Group an agents table, sorted by scene and frame (:func:`sort_agents`), by situation."""
    agents = with_ego_column(agents)
    if agents.height == 0:
        raise StatsError("no agent-frames: every frame is empty (no agent besides the ego)")
    for col in (*SITUATION_KEY, "baseline"):
        if col not in agents.columns:
            raise StatsError(f"the agents table has no {col!r} column")
    sit = (
        agents.select(*SITUATION_KEY)
        .with_columns(pl.struct(SITUATION_KEY).rank("dense").cast(pl.Int64).alias("_s"))["_s"]
        .to_numpy()
        - 1
    )
    if np.any(np.diff(sit) < 0):
        raise StatsError("the agents table must be sorted by scene and frame (use sort_agents)")
    base = agents["baseline"].to_numpy().astype(bool)
    keys = agents.select(*SITUATION_KEY).unique(maintain_order=True)
    return Situations(
        keys=keys,
        situation=sit,
        baseline=base,
        n_positive=np.bincount(sit, weights=base, minlength=keys.height).astype(np.int64),
        n_agents=np.bincount(sit, minlength=keys.height).astype(np.int64),
    )


def sort_agents(agents: pl.DataFrame) -> pl.DataFrame:
    """The agents table sorted by situation (stable within a situation)."""
    return with_ego_column(agents).sort(SITUATION_KEY, maintain_order=True)


def per_situation_rates(
    scores: np.ndarray, sits: Situations, threshold: float
) -> dict[str, np.ndarray]:
    """TPR, FPR (NaN where undefined) and kept count of each situation at one threshold.

    ``scores (A,)``; returns ``(S,)`` arrays ``tpr``, ``fpr``, ``kept``.
    """
    keep = np.nan_to_num(scores, nan=-np.inf) >= threshold
    s = sits.situation
    tp = np.bincount(s, weights=keep & sits.baseline, minlength=sits.n)
    fp = np.bincount(s, weights=keep & ~sits.baseline, minlength=sits.n)
    with np.errstate(invalid="ignore", divide="ignore"):
        tpr = np.where(sits.no_positive, np.nan, tp / sits.n_positive)
        fpr = np.where(sits.no_negative, np.nan, fp / sits.n_negative)
    return {"tpr": tpr, "fpr": fpr, "kept": np.bincount(s, weights=keep, minlength=sits.n)}


# ---------------------------------------------------------------------- per model
@dataclass(frozen=True)
class OperatingPoint:
    """A model's filter at one threshold, over all situations."""

    name: str  # "tpr_0.9", "tpr_0.95", "tpr_1", "youden"
    threshold: float  # in the model's units; -inf when no threshold reaches the target
    mean_tpr: float
    std_tpr: float  # over situations with a defined TPR (ddof = 0)
    mean_fpr: float
    mean_kept: float  # agents kept per situation
    mean_false_negatives: float  # baseline agents dropped per situation
    situations_missing_any: int  # situations with at least one false negative


@dataclass(frozen=True, eq=False)
class ModelStats:
    """The ROC curve of one model against the baseline and its operating points."""

    model: str
    roc: Sweep
    points: dict[str, OperatingPoint]
    std_tpr_curve: float  # std of TPR averaged along the curve, weighted by FPR span
    std_tpr_high: tuple[float, float]  # min, max std of TPR where mean TPR is in [0.8, 1)
    mean_tpr_above_min: float  # best mean TPR at a threshold that still drops an agent
    per_situation_tpr: dict[str, np.ndarray]  # point name -> (S,) TPR (NaN: undefined)
    per_situation_kept: dict[str, np.ndarray]  # point name -> (S,) kept agents
    zero_score_positive_share: float  # baseline agents this model scores <= 0

    def curve(self) -> pl.DataFrame:
        """The mean ROC curve: threshold, mean/std TPR, mean FPR (one row per threshold)."""
        return pl.DataFrame(
            {
                "model": [self.model] * self.roc.thresholds.size,
                "threshold": self.roc.thresholds,
                "mean_tpr": self.roc.mean_tpr,
                "std_tpr": self.roc.std_tpr,
                "mean_fpr": self.roc.mean_fpr,
                "mean_kept": self.roc.mean_kept,
            }
        )


def model_stats(scores: np.ndarray, sits: Situations, model: str) -> ModelStats:
    """ROC curve, AUC and operating points of one model; ``scores (A,)`` in table order."""
    scores = np.asarray(scores, dtype=np.float64)
    roc = exact_sweep(scores, sits.situation, sits.baseline, n_situations=sits.n)
    thresholds = {f"tpr_{_fmt(t)}": _threshold_for(roc, t) for t in TPR_TARGETS}
    thresholds["youden"] = _youden_threshold(roc)
    points: dict[str, OperatingPoint] = {}
    tprs: dict[str, np.ndarray] = {}
    kept: dict[str, np.ndarray] = {}
    for name, thr in thresholds.items():
        rates = per_situation_rates(scores, sits, thr)
        fn = np.nan_to_num(sits.n_positive * (1.0 - rates["tpr"]), nan=0.0)
        points[name] = OperatingPoint(
            name=name,
            threshold=thr,
            mean_tpr=_nanmean(rates["tpr"]),
            std_tpr=_nanstd(rates["tpr"]),
            mean_fpr=_nanmean(rates["fpr"]),
            mean_kept=float(rates["kept"].mean()),
            mean_false_negatives=float(fn.mean()),
            situations_missing_any=int((fn > 0.5).sum()),
        )
        tprs[name], kept[name] = rates["tpr"], rates["kept"]
    positive = scores[sits.baseline]
    return ModelStats(
        model=model,
        roc=roc,
        points=points,
        std_tpr_curve=_curve_mean_std(roc),
        std_tpr_high=_std_range(roc, HIGH_TPR_RANGE),
        mean_tpr_above_min=_tpr_above_min(roc),
        per_situation_tpr=tprs,
        per_situation_kept=kept,
        zero_score_positive_share=float(np.mean(positive <= 0)) if positive.size else math.nan,
    )


def _fmt(x: float) -> str:
    return f"{x:g}"


def _threshold_for(roc: Sweep, target: float) -> float:
    """The highest threshold at which the mean TPR reaches ``target`` (within
    :data:`TPR_TOLERANCE`); -inf (keep everything) when none does."""
    ok = roc.mean_tpr >= target - TPR_TOLERANCE
    if not ok.any():
        return -math.inf
    return float(np.max(roc.thresholds[ok]))


def _youden_threshold(roc: Sweep) -> float:
    j = np.nan_to_num(roc.mean_tpr - roc.mean_fpr, nan=-np.inf)
    best = np.flatnonzero(j == j.max())
    return float(np.max(roc.thresholds[best]))  # the highest of ties keeps the fewest agents


def _curve_mean_std(roc: Sweep) -> float:
    """Std of TPR along the curve, weighted by the FPR span of each step."""
    order = np.argsort(roc.mean_fpr, kind="stable")
    fpr, std = roc.mean_fpr[order], roc.std_tpr[order]
    span = np.diff(fpr, prepend=0.0)
    ok = np.isfinite(std) & np.isfinite(span)
    total = span[ok].sum()
    return float((std[ok] * span[ok]).sum() / total) if total > 0 else math.nan


def _std_range(roc: Sweep, tpr_range: tuple[float, float]) -> tuple[float, float]:
    """(min, max) of the std of TPR over the thresholds whose mean TPR is in the range."""
    lo, hi = tpr_range
    sel = (roc.mean_tpr >= lo) & (roc.mean_tpr < hi - TPR_TOLERANCE) & np.isfinite(roc.std_tpr)
    if not sel.any():
        return (math.nan, math.nan)
    return (float(roc.std_tpr[sel].min()), float(roc.std_tpr[sel].max()))


def _tpr_above_min(roc: Sweep) -> float:
    """The highest mean TPR at a threshold above the lowest score (which keeps everyone)."""
    sel = (roc.thresholds > np.min(roc.thresholds)) & np.isfinite(roc.mean_tpr)
    return float(np.max(roc.mean_tpr[sel])) if sel.any() else math.nan


def _nanmean(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else math.nan


def _nanstd(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.std()) if x.size else math.nan


def bootstrap_std_difference(
    tpr_a: np.ndarray,
    tpr_b: np.ndarray,
    *,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """``std(tpr_a) - std(tpr_b)`` over situations and its paired-bootstrap interval.

    ``tpr_a``, ``tpr_b``: ``(S,)`` per-situation TPRs of two models on the same
    situations (NaN: undefined, dropped where either is). Resamples the situations with
    replacement ``n_boot`` times (same draw for both models, as they share situations).
    Returns (difference, lower, upper) of the central ``level`` interval.
    """
    a, b = np.asarray(tpr_a, dtype=np.float64), np.asarray(tpr_b, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if a.size < 2:
        return (math.nan, math.nan, math.nan)
    idx = np.random.default_rng(seed).integers(0, a.size, size=(n_boot, a.size))
    diff = a[idx].std(axis=1) - b[idx].std(axis=1)
    tail = (1.0 - level) / 2.0
    lo, hi = np.quantile(diff, [tail, 1.0 - tail])
    return (float(a.std() - b.std()), float(lo), float(hi))


# ---------------------------------------------------------------------- FN / FP
def errors_over_threshold(
    scores: np.ndarray, sits: Situations, thresholds: np.ndarray, model: str
) -> pl.DataFrame:
    """Mean false negatives, false positives and kept agents per situation over the
    thresholds ``(K,)`` of one model (the paper's Fig. 5), one row per threshold."""
    counts = confusion_counts(np.asarray(scores, dtype=np.float64), sits.baseline, thresholds)
    return errors_table(model, thresholds, counts.tp, counts.fp, counts.fn, sits.n)


def errors_table(
    model: str,
    thresholds: np.ndarray,
    tp: np.ndarray,
    fp: np.ndarray,
    fn: np.ndarray,
    n_situations: int,
) -> pl.DataFrame:
    """The FN/FP-over-threshold rows from the counts ``(K,)`` at each threshold."""
    n = n_situations
    return pl.DataFrame(
        {
            "model": [model] * len(thresholds),
            "threshold": np.asarray(thresholds, dtype=np.float64),
            "mean_false_negatives": fn / n,
            "mean_false_positives": fp / n,
            "mean_kept": (tp + fp) / n,
            "false_negatives": np.asarray(fn, dtype=np.int64),
            "false_positives": np.asarray(fp, dtype=np.int64),
        }
    )


# ---------------------------------------------------------------------- cascade
def cascade_summary(
    frames: pl.DataFrame, stage_names: Sequence[str], tier_names: Sequence[str]
) -> dict[str, Any]:
    """The funnel, tier sizes, false negatives and compute of the cascade over all
    situations of a frames table (frames without agents included: they cost time too).

    Times come only from replayed frames (tables read from disk have none): ``compute``
    and each stage's ``time_s`` sum over the ``timed_situations`` that have them."""
    n = frames.height
    if n == 0:
        raise StatsError("no frames to summarise")
    baseline = int(frames["n_baseline"].sum())
    timed = frames.filter(pl.col("survival_all_time_s").is_not_null())
    stages = []
    for s in stage_names:
        fn = int(frames[f"fn_{s}"].sum())
        stages.append(
            {
                "model": s,
                "mean_kept": _float(frames[f"kept_{s}"].mean()),
                "false_negatives": fn,
                "fn_share": fn / baseline if baseline else math.nan,
                "situations_with_fn": int((frames[f"fn_{s}"] > 0).sum()),
                "time_s": float(timed[f"time_{s}_s"].sum()) if timed.height else None,
                "median_time_s": _float(timed[f"time_{s}_s"].median()) if timed.height else None,
            }
        )
    tiers = [
        {
            "name": t,
            "mean_agents": _float(frames[f"tier_{t}"].mean()),
            "min_agents": _int(frames[f"tier_{t}"].min()),
            "max_agents": _int(frames[f"tier_{t}"].max()),
        }
        for t in tier_names
    ]
    summary: dict[str, Any] = {
        "situations": n,
        "mean_others": _float(frames["n_others"].mean()),
        "baseline_agent_frames": baseline,
        "stages": stages,
        "tiers": tiers,
        "timing_available": timed.height > 0,
        "timed_situations": timed.height,
    }
    if timed.height:
        summary["compute"] = _compute(timed, stage_names)
    return summary


def _compute(timed: pl.DataFrame, stage_names: Sequence[str]) -> dict[str, float]:
    """Cascade time (stages + survival sort) against survival analysis on all agents."""
    stage_cols = [timed[f"time_{s}_s"] for s in stage_names]
    per_situation = timed["sort_time_s"]
    for col in stage_cols:
        per_situation = per_situation + col
    stage_time = sum(float(col.sum()) for col in stage_cols)
    sort_time = float(timed["sort_time_s"].sum())
    survival_all = float(timed["survival_all_time_s"].sum())
    cascade = stage_time + sort_time
    return {
        "stages_time_s": stage_time,
        "sort_time_s": sort_time,
        "cascade_time_s": cascade,
        "survival_all_time_s": survival_all,
        "cascade_over_survival_all": cascade / survival_all if survival_all > 0 else math.nan,
        "median_cascade_time_s": _float(per_situation.median()),
        "median_sort_time_s": _float(timed["sort_time_s"].median()),
        "median_survival_all_time_s": _float(timed["survival_all_time_s"].median()),
    }


def funnel_table(summary: Mapping[str, Any]) -> pl.DataFrame:
    """The funnel as rows: all agents, each stage, each tier (mean agents per situation),
    with cumulative false negatives and compute time where they apply."""
    rows = [
        {
            "step": "all other agents",
            "kind": "input",
            "mean_agents": summary["mean_others"],
            "false_negatives": 0,
            "time_s": None,
        }
    ]
    for s in summary["stages"]:
        rows.append(
            {
                "step": s["model"],
                "kind": "stage",
                "mean_agents": s["mean_kept"],
                "false_negatives": s["false_negatives"],
                "time_s": s["time_s"],
            }
        )
    last_fn = rows[-1]["false_negatives"]
    for k, t in enumerate(summary["tiers"]):
        time_s = summary.get("compute", {}).get("sort_time_s") if k == 0 else None
        rows.append(
            {
                "step": t["name"],
                "kind": "tier",
                "mean_agents": t["mean_agents"],
                "false_negatives": last_fn,
                "time_s": time_s,
            }
        )
    return pl.DataFrame(
        rows,
        schema={
            "step": pl.String,
            "kind": pl.String,
            "mean_agents": pl.Float64,
            "false_negatives": pl.Int64,
            "time_s": pl.Float64,
        },
    )


# ---------------------------------------------------------------------- everything
@dataclass(frozen=True, eq=False)
class DatasetStats:
    """Everything :func:`write_stats` writes (tables and the summary)."""

    summary: dict[str, Any]
    models: dict[str, ModelStats]
    roc: pl.DataFrame  # all models' mean curves
    errors: pl.DataFrame  # FN/FP over threshold of the errors model
    funnel: pl.DataFrame
    per_frame: pl.DataFrame
    per_scene: pl.DataFrame
    stage_names: tuple[str, ...]
    tier_names: tuple[str, ...]
    # The streamed statistics' per-frame table: per-scene Parquet pieces on disk, in
    # order (``per_frame`` then holds its columns only); write_stats writes them piece
    # by piece.
    per_frame_pieces: tuple[pathlib.Path, ...] | None = None


def compute_stats(
    agents: pl.DataFrame,
    frames: pl.DataFrame,
    *,
    models: Sequence[str] | None = None,
    errors_model: str = DEFAULT_ERRORS_MODEL,
    stage_names: Sequence[str] | None = None,
    tier_names: Sequence[str] | None = None,
    baseline_threshold: float | None = None,
    inputs: Iterable[str] = (),
) -> DatasetStats:
    """All dataset statistics of an agents table and its frames table.

    ``models``: the models to compare (default: every ``risk_<model>`` column, registry
    order); ``errors_model``: the model of the FN/FP export; ``stage_names`` and
    ``tier_names``: the cascade's (default: the agents table's ``kept_<stage>`` and the
    frames table's ``tier_<name>`` columns).
    """
    agents = sort_agents(agents)
    present = model_names_of(agents)
    names = list(present if models is None else models)
    for m in [*names, errors_model]:
        if m not in present:
            raise StatsError(
                f"no risk_{m} column in the table; it has: {', '.join(present) or 'none'}"
            )
    stages = list(stage_names_of(agents) if stage_names is None else stage_names)
    if tier_names is None:  # the frames table's tier_<name> columns, in order
        tier_names = [c.removeprefix("tier_") for c in frames.columns if c.startswith("tier_")]
    sits = situations_of(agents)
    per_model = {m: model_stats(agents[f"risk_{m}"].to_numpy(), sits, m) for m in names}
    if errors_model not in per_model:
        per_model_err = model_stats(agents[f"risk_{errors_model}"].to_numpy(), sits, errors_model)
    else:
        per_model_err = per_model[errors_model]
    errors = errors_over_threshold(
        agents[f"risk_{errors_model}"].to_numpy(), sits, per_model_err.roc.thresholds, errors_model
    )
    cascade = cascade_summary(frames, stages, tier_names)
    per_frame = _per_frame(frames, sits, per_model)
    summary = stats_summary(
        inputs=inputs,
        situations=_situation_counts(frames, sits),
        baseline={
            "model": BASELINE_MODEL,
            "threshold": baseline_threshold,
            "important_agent_frames": int(sits.baseline.sum()),
            "agent_frames": int(sits.situation.size),
            "mean_important_per_situation": float(sits.n_positive.mean()),
        },
        sweep="exact: every distinct score of the model is a threshold",
        models={m: model_summary(s) for m, s in per_model.items()},
        errors_model=errors_model,
        cascade={"stage_names": stages, "tier_names": list(tier_names), **cascade},
    )
    return DatasetStats(
        summary=summary,
        models=per_model,
        roc=pl.concat([s.curve() for s in per_model.values()]),
        errors=errors,
        funnel=funnel_table(cascade),
        per_frame=per_frame,
        per_scene=per_scene_table(per_frame, stages, tier_names),
        stage_names=tuple(stages),
        tier_names=tuple(tier_names),
    )


def stats_summary(
    *,
    inputs: Iterable[str],
    situations: dict[str, int],
    baseline: dict[str, Any],
    sweep: str,
    models: dict[str, Any],
    errors_model: str,
    cascade: dict[str, Any],
) -> dict[str, Any]:
    """``summary.json``'s content, in its order."""
    return {
        "inputs": list(inputs),
        # how "auc" is computed (replay evaluate pools instead; issue 31)
        "auc_method": "mean of the per-situation ROC curves (the paper's)",
        "situations": situations,
        "baseline": baseline,
        "sweep": sweep,
        "operating_points": {
            "tpr_0.9": "highest threshold where the mean TPR reaches 0.9",
            "tpr_0.95": "highest threshold where the mean TPR reaches 0.95",
            "tpr_1": "highest threshold where the mean TPR is 1 (std of TPR 0 by construction)",
            "youden": "threshold with the largest mean TPR - mean FPR",
        },
        "models": models,
        "errors_model": errors_model,
        "cascade": cascade,
    }


def _situation_counts(frames: pl.DataFrame, sits: Situations) -> dict[str, int]:
    no_agents = int((frames["n_others"] == 0).sum())
    return {
        "total": frames.height,
        "with_agents": sits.n,
        "without_agents": no_agents,
        "empty_baseline": int(sits.no_positive.sum()),
        "full_baseline": int(sits.no_negative.sum()),
        "tpr_defined": int((~sits.no_positive).sum()),
        "fpr_defined": int((~sits.no_negative).sum()),
    }


def model_summary(s: ModelStats) -> dict[str, Any]:
    return {
        "auc": s.roc.auc,
        "n_thresholds": int(s.roc.thresholds.size),
        "std_tpr_curve": s.std_tpr_curve,
        "std_tpr_high_tpr": {
            "mean_tpr_range": list(HIGH_TPR_RANGE),
            "min": s.std_tpr_high[0],
            "max": s.std_tpr_high[1],
        },
        "mean_tpr_above_min": s.mean_tpr_above_min,
        "zero_score_important_share": s.zero_score_positive_share,
        "points": {name: _point_dict(p) for name, p in s.points.items()},
    }


def _point_dict(p: OperatingPoint) -> dict[str, Any]:
    d = dict(p.__dict__)
    d.pop("name")
    return d


def _per_frame(
    frames: pl.DataFrame, sits: Situations, per_model: Mapping[str, ModelStats]
) -> pl.DataFrame:
    """The frames table plus, per model, TPR and kept agents at its tpr_0.95 threshold."""
    tpr = {m: s.per_situation_tpr["tpr_0.95"] for m, s in per_model.items()}
    kept = {m: s.per_situation_kept["tpr_0.95"] for m, s in per_model.items()}
    return per_frame_table(frames, sits.keys, tpr, kept)


def per_frame_table(
    frames: pl.DataFrame,
    keys: pl.DataFrame,
    tpr: Mapping[str, np.ndarray],
    kept: Mapping[str, np.ndarray],
) -> pl.DataFrame:
    """``frames`` with each model's TPR and kept agents per situation (``keys``' rows,
    model -> ``(S,)``) and each frame's degenerate status, sorted by situation."""
    cols: dict[str, Any] = {}
    for m in tpr:
        cols[f"tpr95_{m}"] = tpr[m]
        cols[f"kept95_{m}"] = kept[m].astype(np.int64)
    extra = keys.with_columns(pl.Series(k, v) for k, v in cols.items())
    out = frames.join(extra, on=list(SITUATION_KEY), how="left")
    status = (
        pl.when(pl.col("n_others") == 0)
        .then(pl.lit("no agents"))
        .when(pl.col("n_baseline") == 0)
        .then(pl.lit("empty baseline"))
        .when(pl.col("n_baseline") == pl.col("n_others"))
        .then(pl.lit("full baseline"))
        .otherwise(pl.lit(""))
    )
    return out.with_columns(status.alias("degenerate")).sort(SITUATION_KEY)


def per_scene_table(
    per_frame: pl.DataFrame, stage_names: Sequence[str], tier_names: Sequence[str]
) -> pl.DataFrame:
    """One row per scene: frame counts, mean agents, degenerate frames, the cascade."""
    d = pl.col("degenerate")
    timed = time_columns(stage_names)
    return (
        per_frame.group_by("scene", maintain_order=True)
        .agg(
            pl.len().alias("frames"),
            pl.col("n_others").mean().alias("mean_others"),
            pl.col("n_baseline").sum().alias("baseline_agent_frames"),
            (d == "no agents").sum().alias("frames_without_agents"),
            (d == "empty baseline").sum().alias("frames_empty_baseline"),
            (d == "full baseline").sum().alias("frames_full_baseline"),
            *(pl.col(f"kept_{s}").mean().alias(f"mean_kept_{s}") for s in stage_names),
            *(pl.col(f"fn_{s}").sum().alias(f"fn_{s}") for s in stage_names),
            *(pl.col(f"tier_{t}").mean().alias(f"mean_tier_{t}") for t in tier_names),
            *(pl.col(c).sum().alias(c) for c in timed),
            *(
                pl.col(c).mean().alias(f"mean_{c}")
                for c in per_frame.columns
                if c.startswith("tpr95_")
            ),
        )
        .sort("scene")
    )


def _float(value: Any) -> float:
    """A polars aggregate (typed as any Python literal) as a float."""
    return float(value)


def _int(value: Any) -> int:
    """A polars aggregate (typed as any Python literal) as an int."""
    return int(value)
