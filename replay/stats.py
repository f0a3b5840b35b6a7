"""Dataset statistics: how well each risk model filters against the survival baseline.

Everything here works on two polars tables (see ``docs/statistics.md``):

- the **agents** table, one row per situation and agent: the columns that
  ``replay run --table`` writes (:mod:`replay.tables`) plus ``scene`` (a name of the
  scene the row comes from); a **situation** is one frame of one scene, identified by
  ``(scene, frame)``;
- the **frames** table, one row per situation: agent and baseline counts, the cascade's
  agents after each stage, its cumulative false negatives, its tier sizes and (when the
  frames were replayed, not read from tables) its compute times. :class:`StatsSink`
  builds both while the engine runs; :func:`frames_from_agents` derives the frames table
  from an agents table read from disk (without times: tables do not store them).

:func:`compute_stats` turns them into the ROC curves of every model (the paper's Fig. 4),
the false negatives and false positives over the threshold of one model (Fig. 5), the
cascade funnel (Fig. 6) and per-scene and per-frame tables; :func:`write_stats` writes
them (Parquet + CSV, ``summary.json``). Plots are in :mod:`replay.plots`.

Choices the spec leaves open (documented here and in ``docs/statistics.md``):

- **Sweep**: exact. The thresholds of a model's curve are every distinct score it gives
  in the data, so each situation's TPR and FPR are evaluated at every point where they
  change. :func:`exact_sweep` gets the mean curves and the std of TPR from cumulative
  sums over the agents sorted once by score (O(A log A), no situations x thresholds
  matrix); the tests check it against :func:`risk.metrics.roc_curve` with the same
  thresholds (whose own default switches to a 2048-point grid above 2048 scores).
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

import json
import math
import os
import pathlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import polars as pl

from replay.atomic import atomic_output
from replay.engine import FrameResult, SceneInfo
from replay.errors import ReplayError
from replay.tablecheck import check_agents_table
from replay.tables import TableSink
from risk.cascade import CascadeResult
from risk.metrics import confusion_counts
from risk.registry import BASELINE_MODEL, MODELS

#: The model of the FN/FP-over-threshold export by default (the paper's Fig. 5).
DEFAULT_ERRORS_MODEL = "headway_2d"
#: Target mean TPRs of the named operating points.
TPR_TARGETS = (0.9, 0.95, 1.0)
#: Mean TPRs within this of a target count as reaching it (sums of 1/P_s round).
TPR_TOLERANCE = 1e-9
#: Mean TPRs over which the std of TPR is reported as a range (the filtering region).
HIGH_TPR_RANGE = (0.8, 1.0)
SITUATION_KEY = ("scene", "frame")
#: Variances of TPR below this are rounding (see :func:`exact_sweep`); std < 3e-7.
VAR_ROUNDING = 1e-13


class StatsError(ReplayError):
    """Statistics that cannot be computed from the given input (the message says why)."""


# ---------------------------------------------------------------------- collecting
class StatsSink:
    """A :class:`replay.engine.Sink` that collects the agents and frames tables of one
    scene, named ``scene`` in the ``scene`` column of both."""

    def __init__(self, scene: str):
        self.scene = scene
        self._table = TableSink(None)
        self._frames: list[dict[str, Any]] = []
        self._info: SceneInfo | None = None

    def begin(self, info: SceneInfo) -> None:
        self._info = info
        self._table.begin(info)
        self._frames = []

    def add(self, result: FrameResult) -> None:
        info = self._require_info()
        self._table.add(result)
        row = cascade_frame_row(result.cascade, [t.name for t in info.cascade.tiers])
        self._frames.append(
            {"scene": self.scene, "frame": result.index, "t_s": result.frame.t, **row}
        )

    def close(self) -> None:
        pass  # everything stays in memory until agents() / frames() are asked for

    def abort(self) -> None:
        self._frames = []
        self._table.abort()

    def agents(self) -> pl.DataFrame:
        """The agents table (TableSink columns with ``scene`` first)."""
        df = self._table.dataframe()
        return df.select(pl.lit(self.scene).alias("scene"), pl.all())

    def frames(self) -> pl.DataFrame:
        """The frames table (one row per processed frame, times included)."""
        info = self._require_info()
        return frames_table(
            self._frames, info.cascade.stage_names, [t.name for t in info.cascade.tiers], timed=True
        )

    def _require_info(self) -> SceneInfo:
        if self._info is None:
            raise StatsError("StatsSink: begin() must be called before add()")
        return self._info


def cascade_frame_row(res: CascadeResult, tier_names: Sequence[str]) -> dict[str, Any]:
    """One frames-table row (without scene, frame and time) from a cascade result."""
    row: dict[str, Any] = {
        "n_others": int(res.others.sum()),
        "n_baseline": int(res.baseline.sum()),
    }
    for name, kept in zip(res.stage_names, res.n_kept, strict=True):
        row[f"kept_{name}"] = int(kept)
    for name, fn in zip(res.stage_names, res.false_negatives, strict=True):
        row[f"fn_{name}"] = int(fn)
    for name, count in zip(tier_names, res.tier_counts(len(tier_names)), strict=True):
        row[f"tier_{name}"] = int(count)
    for name, t in zip(res.stage_names, res.stage_time_s, strict=True):
        row[f"time_{name}_s"] = float(t)
    row["sort_time_s"] = float(res.sort_time_s)
    row["survival_all_time_s"] = float(res.survival_all_time_s)
    return row


def frames_table(
    rows: Sequence[Mapping[str, Any]],
    stage_names: Sequence[str],
    tier_names: Sequence[str],
    *,
    timed: bool,
) -> pl.DataFrame:
    """The frames table from rows of :func:`cascade_frame_row` plus scene, frame, t_s.

    ``timed=False`` (tables read from disk) gives null time columns.
    """
    columns = frame_columns(stage_names, tier_names)
    schema = {
        c: _FRAME_DTYPES.get(c, pl.Int64 if not c.endswith("_s") else pl.Float64) for c in columns
    }
    df = pl.DataFrame([{c: r.get(c) for c in columns} for r in rows], schema=schema, orient="row")
    if not timed:
        df = df.with_columns(
            pl.lit(None, dtype=pl.Float64).alias(c) for c in _time_columns(stage_names)
        )
    return df


_FRAME_DTYPES = {"scene": pl.String, "frame": pl.Int64, "t_s": pl.Float64}


def frame_columns(stage_names: Sequence[str], tier_names: Sequence[str]) -> list[str]:
    """The frames-table columns, in order."""
    return [
        "scene",
        "frame",
        "t_s",
        "n_others",
        "n_baseline",
        *(f"kept_{s}" for s in stage_names),
        *(f"fn_{s}" for s in stage_names),
        *(f"tier_{t}" for t in tier_names),
        *_time_columns(stage_names),
    ]


def _time_columns(stage_names: Sequence[str]) -> list[str]:
    return [*(f"time_{s}_s" for s in stage_names), "sort_time_s", "survival_all_time_s"]


# ---------------------------------------------------------------------- tables from disk
def stage_names_of(agents: pl.DataFrame) -> list[str]:
    """The cascade stages recorded in an agents table (``kept_<stage>`` columns, in order)."""
    return [c.removeprefix("kept_") for c in agents.columns if c.startswith("kept_")]


def model_names_of(agents: pl.DataFrame) -> list[str]:
    """The models whose risks an agents table holds, in registry order."""
    present = {c.removeprefix("risk_") for c in agents.columns if c.startswith("risk_")}
    return [m for m in MODELS if m in present]


def tier_names_of(agents: pl.DataFrame, fallback: Sequence[str] = ()) -> list[str]:
    """Tier names in cascade order: the Enum order of a Parquet table's ``tier`` column,
    else ``fallback`` (the cascade config's tiers), which must name every tier seen."""
    dtype = agents.schema.get("tier")
    if isinstance(dtype, pl.Enum):
        return list(dtype.categories)
    seen = (
        set(agents["tier"].drop_nulls().unique().to_list()) if "tier" in agents.columns else set()
    )
    missing = sorted(seen - set(fallback))
    if missing:
        raise StatsError(
            f"the table names tiers {missing} that the cascade configuration does not have "
            f"({', '.join(fallback) or 'none'}); a CSV table does not store the tier order: "
            "pass the cascade TOML it was made with (--cascade)"
        )
    return list(fallback)


def frames_from_agents(
    agents: pl.DataFrame, stage_names: Sequence[str], tier_names: Sequence[str]
) -> pl.DataFrame:
    """The frames table of an agents table (no times; frames without agents are absent,
    because a table has no row for them)."""
    tier_index = {name: k for k, name in enumerate(tier_names)}
    tier_code = (
        agents["tier"].cast(pl.String).replace_strict(tier_index, default=-1, return_dtype=pl.Int64)
        if "tier" in agents.columns
        else pl.Series([-1] * agents.height, dtype=pl.Int64)
    )
    base = pl.col("baseline")
    aggs = [
        pl.col("t_s").first().alias("t_s"),
        pl.len().cast(pl.Int64).alias("n_others"),
        base.sum().cast(pl.Int64).alias("n_baseline"),
        *(pl.col(f"kept_{s}").sum().cast(pl.Int64).alias(f"kept_{s}") for s in stage_names),
        *((base & ~pl.col(f"kept_{s}")).sum().cast(pl.Int64).alias(f"fn_{s}") for s in stage_names),
        *(
            (pl.col("_tier") >= k).sum().cast(pl.Int64).alias(f"tier_{t}")
            for k, t in enumerate(tier_names)
        ),
    ]
    df = (
        agents.with_columns(tier_code.alias("_tier"))
        .group_by(SITUATION_KEY, maintain_order=True)
        .agg(aggs)
        .sort(SITUATION_KEY)
    )
    df = df.with_columns(
        pl.lit(None, dtype=pl.Float64).alias(c) for c in _time_columns(stage_names)
    )
    return df.select(frame_columns(stage_names, tier_names))


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
    return agents.sort(SITUATION_KEY, maintain_order=True)


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


# ---------------------------------------------------------------------- exact sweep
@dataclass(frozen=True, eq=False)
class Sweep:
    """A model's mean ROC curve over situations, exact at every distinct score.

    ``thresholds (K,)`` ascending (every distinct finite score); ``mean_tpr``,
    ``mean_fpr``, ``std_tpr``, ``mean_kept`` ``(K,)``; the fields mean what they mean in
    :class:`risk.metrics.Sweep` (which the tests use as the oracle).
    """

    thresholds: np.ndarray
    mean_tpr: np.ndarray  # over situations with a baseline agent
    mean_fpr: np.ndarray  # over situations with an agent outside the baseline
    std_tpr: np.ndarray  # population std (ddof = 0) over the same situations as mean_tpr
    mean_kept: np.ndarray  # agents with score >= threshold, mean over all situations
    auc: float  # trapezoids under the mean curve closed with (0, 0) and (1, 1)
    n_situations: int
    n_no_positive: int
    n_no_negative: int


def exact_sweep(scores: np.ndarray, sits: Situations) -> Sweep:
    """The mean ROC curve of ``scores (A,)`` at every distinct score, in O(A log A).

    Why it is exact without an ``(S, K)`` matrix: lowering the threshold past an agent's
    score adds ``1 / P_s`` to its situation's TPR, so the mean TPR is a cumulative sum
    of per-agent weights ``1 / (P_s S_P)`` over the agents sorted by score (``S_P``
    situations with a positive). For the std, TPR_s^2 rises from ``(k/P_s)^2`` to
    ``((k+1)/P_s)^2`` when the ``(k+1)``-th positive of situation ``s`` (by descending
    score) enters; tied agents enter together, so any order among them gives the same
    sum. NaN scores (not an agent) are ignored, as in :mod:`risk.metrics`.
    """
    s = np.asarray(scores, dtype=np.float64)
    ok = ~np.isnan(s)
    s, base, sit = s[ok], sits.baseline[ok], sits.situation[ok]
    if s.size == 0:
        raise StatsError("no agent has a risk value (every score is NaN)")
    n_sit = sits.n
    pos = np.bincount(sit[base], minlength=n_sit)
    neg = np.bincount(sit[~base], minlength=n_sit)
    n_pos_sits, n_neg_sits = int((pos > 0).sum()), int((neg > 0).sum())
    order = np.argsort(-s, kind="stable")  # riskiest first
    s_desc, b_desc, sit_desc = s[order], base[order], sit[order]
    with np.errstate(divide="ignore", invalid="ignore"):
        w_tpr = np.where(b_desc, 1.0 / pos[sit_desc], 0.0)
        w_fpr = np.where(~b_desc, 1.0 / neg[sit_desc], 0.0)
        w_sq = np.where(b_desc, (2.0 * _rank_in_situation(sit_desc, b_desc) + 1.0)
                        / pos[sit_desc] ** 2, 0.0)  # fmt: skip
    # The last agent of each run of equal scores closes that threshold.
    last = np.flatnonzero(np.r_[s_desc[1:] != s_desc[:-1], True])
    cum_tpr, cum_fpr, cum_sq = (np.cumsum(w)[last] for w in (w_tpr, w_fpr, w_sq))
    mean_tpr = _normalised(cum_tpr, n_pos_sits)
    mean_fpr = _normalised(cum_fpr, n_neg_sits)
    # E[TPR^2] is 1 when everyone is kept, like the mean: normalise it the same way.
    mean_sq = _normalised(cum_sq, n_pos_sits)
    var = mean_sq - mean_tpr**2
    # E[x^2] - E[x]^2 leaves rounding of a few eps where the spread is 0; sqrt would
    # blow that up to ~1e-8, so variances below VAR_ROUNDING count as 0.
    std = np.sqrt(np.where(var < VAR_ROUNDING, 0.0, var))
    kept = (last + 1) / n_sit
    rev = slice(None, None, -1)  # descending -> ascending thresholds
    return Sweep(
        thresholds=s_desc[last][rev],
        mean_tpr=mean_tpr[rev],
        mean_fpr=mean_fpr[rev],
        std_tpr=std[rev],
        mean_kept=kept[rev],
        auc=_auc(mean_fpr, mean_tpr),
        n_situations=n_sit,
        n_no_positive=n_sit - n_pos_sits,
        n_no_negative=n_sit - n_neg_sits,
    )


def _rank_in_situation(sit: np.ndarray, positive: np.ndarray) -> np.ndarray:
    """For agents sorted by descending score: how many positives of the same situation
    come before each agent (``(A,)``; only meaningful for positives)."""
    order = np.argsort(sit, kind="stable")  # by situation, keeping the score order
    pos_sorted = positive[order].astype(np.int64)
    before = np.cumsum(pos_sorted) - pos_sorted  # positives before, over all situations
    s_sorted = sit[order]
    first = np.r_[0, np.flatnonzero(s_sorted[1:] != s_sorted[:-1]) + 1]
    group_start = np.repeat(before[first], np.diff(np.r_[first, s_sorted.size]))
    rank = np.empty(sit.size, dtype=np.int64)
    rank[order] = before - group_start
    return rank


def _normalised(cum: np.ndarray, n_sits: int) -> np.ndarray:
    """Mean rates from cumulative weights; the last entry (everyone kept) is exactly 1,
    so that rounding never hides the TPR = 1 operating point."""
    if n_sits == 0 or cum.size == 0 or cum[-1] <= 0:
        return np.full(cum.size, np.nan)
    return np.minimum(cum / cum[-1], 1.0)


def _auc(fpr_desc: np.ndarray, tpr_desc: np.ndarray) -> float:
    """Trapezoids under the curve, from the strictest threshold; closed with (0, 0) and
    (1, 1) as :mod:`risk.metrics` does."""
    if np.isnan(fpr_desc).any() or np.isnan(tpr_desc).any():
        return math.nan
    x = np.r_[0.0, fpr_desc, 1.0]
    y = np.r_[0.0, tpr_desc, 1.0]
    return float(np.sum(np.diff(x) * (y[1:] + y[:-1]) / 2.0))


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
    roc = exact_sweep(scores, sits)
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
    sel = roc.thresholds > np.min(roc.thresholds)
    return float(np.nanmax(roc.mean_tpr[sel])) if sel.any() else math.nan


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
    n = sits.n
    return pl.DataFrame(
        {
            "model": [model] * len(thresholds),
            "threshold": np.asarray(thresholds, dtype=np.float64),
            "mean_false_negatives": counts.fn / n,
            "mean_false_positives": counts.fp / n,
            "mean_kept": (counts.tp + counts.fp) / n,
            "false_negatives": counts.fn,
            "false_positives": counts.fp,
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
                "mean_kept": float(frames[f"kept_{s}"].mean()),
                "false_negatives": fn,
                "fn_share": fn / baseline if baseline else math.nan,
                "situations_with_fn": int((frames[f"fn_{s}"] > 0).sum()),
                "time_s": float(timed[f"time_{s}_s"].sum()) if timed.height else None,
                "median_time_s": float(timed[f"time_{s}_s"].median()) if timed.height else None,
            }
        )
    tiers = [
        {
            "name": t,
            "mean_agents": float(frames[f"tier_{t}"].mean()),
            "min_agents": int(frames[f"tier_{t}"].min()),
            "max_agents": int(frames[f"tier_{t}"].max()),
        }
        for t in tier_names
    ]
    summary: dict[str, Any] = {
        "situations": n,
        "mean_others": float(frames["n_others"].mean()),
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
        "median_cascade_time_s": float(per_situation.median()),
        "median_sort_time_s": float(timed["sort_time_s"].median()),
        "median_survival_all_time_s": float(timed["survival_all_time_s"].median()),
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
    summary = {
        "inputs": list(inputs),
        "situations": _situation_counts(frames, sits),
        "baseline": {
            "model": BASELINE_MODEL,
            "threshold": baseline_threshold,
            "important_agent_frames": int(sits.baseline.sum()),
            "agent_frames": int(sits.situation.size),
            "mean_important_per_situation": float(sits.n_positive.mean()),
        },
        "sweep": "exact: every distinct score of the model is a threshold",
        "operating_points": {
            "tpr_0.9": "highest threshold where the mean TPR reaches 0.9",
            "tpr_0.95": "highest threshold where the mean TPR reaches 0.95",
            "tpr_1": "highest threshold where the mean TPR is 1 (std of TPR 0 by construction)",
            "youden": "threshold with the largest mean TPR - mean FPR",
        },
        "models": {m: _model_summary(s) for m, s in per_model.items()},
        "errors_model": errors_model,
        "cascade": {"stage_names": stages, "tier_names": list(tier_names), **cascade},
    }
    return DatasetStats(
        summary=summary,
        models=per_model,
        roc=pl.concat([s.curve() for s in per_model.values()]),
        errors=errors,
        funnel=funnel_table(cascade),
        per_frame=per_frame,
        per_scene=_per_scene(per_frame, stages, tier_names),
        stage_names=tuple(stages),
        tier_names=tuple(tier_names),
    )


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


def _model_summary(s: ModelStats) -> dict[str, Any]:
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
    cols: dict[str, Any] = {}
    for m, s in per_model.items():
        cols[f"tpr95_{m}"] = s.per_situation_tpr["tpr_0.95"]
        cols[f"kept95_{m}"] = s.per_situation_kept["tpr_0.95"].astype(np.int64)
    extra = sits.keys.with_columns(pl.Series(k, v) for k, v in cols.items())
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


def _per_scene(
    per_frame: pl.DataFrame, stage_names: Sequence[str], tier_names: Sequence[str]
) -> pl.DataFrame:
    """One row per scene: frame counts, mean agents, degenerate frames, the cascade."""
    d = pl.col("degenerate")
    timed = [c for c in _time_columns(stage_names)]
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


# ---------------------------------------------------------------------- reading, writing
def read_agents_table(path: str | os.PathLike[str], scene: str | None = None) -> pl.DataFrame:
    """An agents table written by ``replay run --table`` (.parquet or .csv), with a
    ``scene`` column (kept when the table has one, else ``scene`` or the file name)."""
    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".parquet":
            df = pl.read_parquet(path)
        elif suffix == ".csv":
            df = pl.read_csv(path, infer_schema_length=None)
        else:
            raise StatsError(f"{path}: a table must end in .parquet or .csv")
    except (pl.exceptions.PolarsError, OSError) as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        raise StatsError(f"{path}: not a readable table ({type(exc).__name__}: {exc})") from None
    required = {"frame", "t_s", "agent_id", "baseline"}
    missing = sorted(required - set(df.columns))
    if missing or not model_names_of(df):
        what = ", ".join(missing) or "risk_<model>"
        raise StatsError(f"{path}: not a 'replay run --table' table (no {what} column)")
    check_agents_table(df, path)  # empty, non-numeric or out-of-range risks
    if df.schema["baseline"] != pl.Boolean:
        df = df.with_columns(pl.col("baseline").cast(pl.String).str.to_lowercase() == "true")
    if "scene" not in df.columns:
        df = df.select(pl.lit(scene or path.stem).alias("scene"), pl.all())
    return df.with_columns(pl.col("scene").cast(pl.String), pl.col("frame").cast(pl.Int64))


def concat_agents(tables: Sequence[pl.DataFrame]) -> pl.DataFrame:
    """Agents tables of several scenes as one (tier columns as strings when they differ)."""
    if not tables:
        raise StatsError("no tables to combine")
    dtypes = {str(t.schema.get("tier")) for t in tables}
    if len(dtypes) > 1:
        tables = [t.with_columns(pl.col("tier").cast(pl.String)) for t in tables]
    try:
        return pl.concat(tables, how="diagonal_relaxed")
    except pl.exceptions.PolarsError as exc:
        raise StatsError(f"the tables do not fit together: {exc}") from None


def write_stats(stats: DatasetStats, out_dir: str | os.PathLike[str]) -> dict[str, pathlib.Path]:
    """Write every table as Parquet and CSV and the summary as JSON into ``out_dir``
    (created if needed); each file atomically. Returns name -> path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    tables = {
        "roc": stats.roc,
        "errors": stats.errors,
        "funnel": stats.funnel,
        "per_frame": stats.per_frame,
        "per_scene": stats.per_scene,
    }
    for name, df in tables.items():
        for suffix in (".parquet", ".csv"):
            path = out / f"{name}{suffix}"
            atomic_write(path, lambda tmp, df=df, suffix=suffix: _write_table(df, tmp, suffix))
            written[f"{name}{suffix}"] = path
    summary = {**stats.summary, "files": sorted(p.name for p in written.values())}
    path = out / "summary.json"
    text = json.dumps(_jsonable(summary), indent=2, allow_nan=False)
    atomic_write(path, lambda tmp: pathlib.Path(tmp).write_text(text + "\n", encoding="utf-8"))
    written["summary.json"] = path
    return written


def _write_table(df: pl.DataFrame, tmp: str, suffix: str) -> None:
    if suffix == ".csv":
        df.write_csv(tmp)
    else:
        df.write_parquet(tmp, compression="zstd")


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], Any]) -> pathlib.Path:
    """``write(tmp)`` to a temporary file beside ``path``, which then replaces ``path``
    atomically (see :mod:`replay.atomic`)."""
    try:
        with atomic_output(path) as tmp:
            write(str(tmp))
    except pl.exceptions.PolarsError as exc:  # e.g. a full disk ("os error 28")
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise StatsError(f"could not write {path}: {first}") from None
    return pathlib.Path(path)


def _jsonable(value: Any) -> Any:
    """JSON-safe: NaN and infinities become null (JSON has neither), numpy scalars plain."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value
