"""``replay stats``' statistics from a run's part files, one part at a time (issue 38):
the driver holds per-scene sums, merged grid-binned curves and a few bins' rows, never the
corpus's rows.

Three passes over the parts (``OUT/parts/agents`` with their ``frames``), each reading one
part at a time, in a fixed order (the parts' scene names, then their paths), so the result
does not depend on the order the parts are given in:

1. every model's mean-sweep weights per grid bin (:mod:`risk.sweep_counts`), merged as
   they come; the situation and baseline counts; the frames' sums, minima and maxima and
   histograms of the compute times;
2. the rows of the bins where the operating thresholds fall (the TPR targets' crossing
   bins, the bins that could hold a better Youden point, the lowest bin) and the times
   in the bins of the medians;
3. at the exact thresholds: every situation's TPR, FPR and kept agents (summed; the
   ``tpr_0.95`` ones go to the per-frame table, written part by part to a scratch folder
   and streamed into ``per_frame`` by :func:`replay.analysis.stats.files.write_stats`:
   ``DatasetStats.per_frame_pieces``).

Exact against :func:`replay.analysis.stats.compute.compute_stats` (the full-rows
computation, kept as the tests' oracle), to the rounding of sums taken in another order:
the operating points (thresholds, mean and std of TPR, FPR, kept agents, false
negatives), the situation and baseline counts, ``zero_score_important_share``, the
cascade funnel (medians too), the per-frame and per-scene tables, and every point of the
roc and errors tables. Binned: the roc and errors tables have one point per occupied
grid bin (:data:`risk.roc_counts.GRID_BITS`; at most :data:`MAX_CURVE_BINS` bins per
model), not one per distinct score, so ``auc`` is within its stated ``auc_error_bound``,
``n_thresholds`` counts the binned points, and ``std_tpr_curve`` and
``std_tpr_high_tpr`` are taken over the binned points (a subset of the exact curve's).
"""

from __future__ import annotations

import math
import pathlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import polars as pl

from replay.analysis.evaluation.streaming import _median_bins, _medians, _Merging
from replay.analysis.stats.compute import (
    HIGH_TPR_RANGE,
    TPR_TARGETS,
    TPR_TOLERANCE,
    DatasetStats,
    ModelStats,
    OperatingPoint,
    _curve_mean_std,
    _std_range,
    errors_table,
    funnel_table,
    model_summary,
    per_frame_table,
    per_scene_table,
    per_situation_rates,
    situations_of,
    sort_agents,
    stats_summary,
)
from replay.core.stats_sink import SITUATION_KEY, time_columns, with_ego_column
from replay.errors import StatsError
from risk.registry import BASELINE_MODEL, MODELS
from risk.roc_counts import MAX_CURVE_BINS, bin_counts, score_bins
from risk.sweep_counts import (
    BinPoints,
    SweepCounts,
    SweepRows,
    binned_sweep,
    collapse,
    crossing_bin,
    merge_sweeps,
    points_in_bin,
    rows_in_bins,
    situation_counts,
    sweep_counts,
    sweep_rows,
    threshold_for_mean_tpr,
    tpr_above_lowest,
    youden_candidates,
    youden_threshold,
)

#: Parts' counts merged into the running curves at once.
MERGE_BATCH = 32
#: How the roc table's points are taken (summary.json's ``sweep``).
BINNED_SWEEP = (
    "binned: one threshold per occupied bin of a fixed score grid (the bin's lowest score;"
    " each point is a point of the exact every-distinct-score curve); auc within"
    " auc_error_bound of the exact one; operating points exact"
)


@dataclass(frozen=True)
class StatsPart:
    """One complete scene's (or table's) part files."""

    agents: pathlib.Path
    frames: pathlib.Path


def ordered_parts(parts: Sequence[StatsPart]) -> list[StatsPart]:
    """``parts`` in the order every pass reads them: by their scene names, then path."""

    def key(p: StatsPart) -> tuple[list[str], str]:
        schema = pl.read_parquet_schema(p.agents)
        names = (
            pl.read_parquet(p.agents, columns=["scene"])["scene"].cast(pl.String).unique().sort()
            if "scene" in schema
            else pl.Series([], dtype=pl.String)
        )
        return [str(n) for n in names.to_list()], str(p.agents)

    return sorted(parts, key=key)


def _schema_union(paths: Sequence[pathlib.Path]) -> dict[str, pl.DataType]:
    union: dict[str, pl.DataType] = {}
    for path in paths:
        for name, dtype in pl.read_parquet_schema(path).items():
            union.setdefault(name, dtype)
    return union


def _read(path: pathlib.Path, columns: Mapping[str, pl.DataType]) -> pl.DataFrame:
    """``columns`` of a part file; those it lacks as nulls (as a diagonal concatenation)."""
    own = pl.read_parquet_schema(path)
    df = pl.read_parquet(path, columns=[c for c in columns if c in own])
    return df.with_columns(
        pl.lit(None, dtype=t).alias(c) for c, t in columns.items() if c not in own
    )


@dataclass
class _Part:
    """One part read: its sorted agents (None: no agent-frame), situations and frames."""

    agents: pl.DataFrame | None
    frames: pl.DataFrame

    def scores(self, model: str) -> np.ndarray:
        assert self.agents is not None
        return self.agents[f"risk_{model}"].to_numpy().astype(np.float64)


@dataclass
class _Running:
    """Each model's running merged sweep: parts' counts wait in batches."""

    max_bins: int | None
    merged: dict[str, SweepCounts] = field(default_factory=dict)
    pending: dict[str, list[SweepCounts]] = field(default_factory=dict)

    def add(self, model: str, counts: SweepCounts) -> None:
        self.pending.setdefault(model, []).append(counts)
        if len(self.pending[model]) >= MERGE_BATCH:
            self.flush()

    def flush(self) -> None:
        for m, batch in self.pending.items():
            if batch:
                old = [self.merged[m]] if m in self.merged else []
                self.merged[m] = merge_sweeps([*old, *batch], self.max_bins)
        self.pending = {}


def _frame_sums(
    frames: pl.DataFrame, stages: Sequence[str], tiers: Sequence[str]
) -> dict[str, Any]:
    """One part's additive pieces of the cascade summary."""
    timed = frames.filter(pl.col("survival_all_time_s").is_not_null())
    out: dict[str, Any] = {
        "situations": frames.height,
        "without_agents": int((frames["n_others"] == 0).sum()),
        "n_others": int(frames["n_others"].sum()),
        "n_baseline": int(frames["n_baseline"].sum()),
        "timed": timed.height,
    }
    for s in stages:
        out[f"kept_{s}"] = int(frames[f"kept_{s}"].sum())
        out[f"fn_{s}"] = int(frames[f"fn_{s}"].sum())
        out[f"fn_any_{s}"] = int((frames[f"fn_{s}"] > 0).sum())
    for t in tiers:
        col = frames[f"tier_{t}"]
        out[f"tier_{t}"] = int(col.sum())
        out[f"tier_min_{t}"] = None if col.is_empty() else int(col.min())  # type: ignore[arg-type]
        out[f"tier_max_{t}"] = None if col.is_empty() else int(col.max())  # type: ignore[arg-type]
    for c in time_columns(stages):
        out[c] = float(timed[c].sum()) if timed.height else 0.0
    return out


def _add_sums(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    if not a:
        return b
    out = {}
    for k, v in a.items():
        w = b[k]
        if k.startswith("tier_min_") or k.startswith("tier_max_"):
            pick = min if k.startswith("tier_min_") else max
            out[k] = v if w is None else w if v is None else pick(v, w)
        else:
            out[k] = v + w
    return out


def _time_values(frames: pl.DataFrame, stages: Sequence[str]) -> dict[str, np.ndarray]:
    """The values of the compute medians over the timed frames of a part."""
    timed = frames.filter(pl.col("survival_all_time_s").is_not_null())
    cascade = timed["sort_time_s"]
    for s in stages:
        cascade = cascade + timed[f"time_{s}_s"]
    out = {f"time_{s}_s": timed[f"time_{s}_s"].to_numpy() for s in stages}
    out["sort_time_s"] = timed["sort_time_s"].to_numpy()
    out["survival_all_time_s"] = timed["survival_all_time_s"].to_numpy()
    out["cascade_time_s"] = cascade.to_numpy()
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


def _key(column: str) -> tuple[str, str, str]:
    """A histogram's key for :func:`replay.analysis.evaluation.streaming._median_bins`."""
    return ("time", column, "")


@dataclass
class _PointSums:
    """A model's situations at one threshold, summed over parts: count, mean and M2 of
    the defined TPRs (Chan's pairwise update), FPR sum and count, kept, false negatives
    and situations missing any."""

    n_tpr: int = 0
    mean_tpr: float = 0.0
    m2_tpr: float = 0.0
    fpr: float = 0.0
    n_fpr: int = 0
    kept: float = 0.0
    fn: float = 0.0
    missing: int = 0

    def add(self, rates: Mapping[str, np.ndarray], n_positive: np.ndarray) -> None:
        tpr = rates["tpr"][np.isfinite(rates["tpr"])]
        if tpr.size:
            mean_b = float(tpr.mean())
            m2_b = float(((tpr - mean_b) ** 2).sum())
            n = self.n_tpr + tpr.size
            delta = mean_b - self.mean_tpr
            self.mean_tpr += delta * tpr.size / n
            self.m2_tpr += m2_b + delta**2 * self.n_tpr * tpr.size / n
            self.n_tpr = n
        fpr = rates["fpr"][np.isfinite(rates["fpr"])]
        self.fpr += float(fpr.sum())
        self.n_fpr += fpr.size
        self.kept += float(rates["kept"].sum())
        fn = np.nan_to_num(n_positive * (1.0 - rates["tpr"]), nan=0.0)
        self.fn += float(fn.sum())
        self.missing += int((fn > 0.5).sum())

    def point(self, name: str, threshold: float, n_situations: int) -> OperatingPoint:
        return OperatingPoint(
            name=name,
            threshold=threshold,
            mean_tpr=self.mean_tpr if self.n_tpr else math.nan,
            std_tpr=math.sqrt(max(self.m2_tpr / self.n_tpr, 0.0)) if self.n_tpr else math.nan,
            mean_fpr=self.fpr / self.n_fpr if self.n_fpr else math.nan,
            mean_kept=self.kept / n_situations,
            mean_false_negatives=self.fn / n_situations,
            situations_missing_any=self.missing,
        )


def stream_stats(
    parts: Sequence[StatsPart],
    scratch: pathlib.Path,
    *,
    models: Sequence[str] | None = None,
    errors_model: str,
    stage_names: Sequence[str],
    tier_names: Sequence[str],
    baseline_threshold: float | None = None,
    inputs: Sequence[str] = (),
    max_curve_bins: int | None = MAX_CURVE_BINS,
) -> DatasetStats:
    """The statistics of the scenes in ``parts`` (as
    :func:`replay.analysis.stats.compute.compute_stats`; see the module docstring).
    ``scratch``: an empty folder for the per-frame pieces, which the returned
    ``per_frame_pieces`` lists (keep it until the tables are written; ``per_frame``
    holds only the table's columns)."""
    if not parts:
        raise StatsError("no scene to summarise")
    ordered = ordered_parts(parts)
    a_union = _schema_union([p.agents for p in ordered])
    present = [m for m in MODELS if f"risk_{m}" in a_union]
    names = list(present if models is None else models)
    for m in [*names, errors_model]:
        if m not in present:
            raise StatsError(
                f"no risk_{m} column in the table; it has: {', '.join(present) or 'none'}"
            )
    swept = list(dict.fromkeys([*names, errors_model]))
    for col in ("frame", "baseline"):
        if col not in a_union:
            raise StatsError(f"the agents table has no {col!r} column")
    a_cols: dict[str, pl.DataType] = {
        c: a_union[c] for c in ("scene", "ego_id", "frame", "baseline") if c in a_union
    }
    a_cols.update({f"risk_{m}": a_union[f"risk_{m}"] for m in swept})
    f_union = _schema_union([p.frames for p in ordered])
    stages, tiers = list(stage_names), list(tier_names)

    def read_parts() -> Iterator[_Part]:
        for p in ordered:
            agents = _read(p.agents, a_cols)
            frames = _read(p.frames, f_union)
            sorted_agents = sort_agents(agents) if agents.height else None
            yield _Part(sorted_agents, with_ego_column(frames))

    # Pass 1: sums, merged curves, histograms.
    running = _Running(max_curve_bins)
    histograms = _Merging(max_curve_bins)
    sums: dict[str, Any] = {}
    n_sit = agent_frames = important = no_pos = no_neg = 0
    zero = {m: [0, 0] for m in names}  # positives scored <= 0, positives
    for part in read_parts():
        sums = _add_sums(sums, _frame_sums(part.frames, stages, tiers))
        for col, values in _time_values(part.frames, stages).items():
            histograms.add(_key(col), bin_counts(values, np.ones(values.size, dtype=bool)))
        if part.agents is None:
            continue
        sits = situations_of(part.agents)
        n_sit += sits.n
        agent_frames += int(sits.situation.size)
        important += int(sits.baseline.sum())
        no_pos += int(sits.no_positive.sum())
        no_neg += int(sits.no_negative.sum())
        for m in swept:
            scores = part.scores(m)
            rows = sweep_rows(scores, sits.situation, sits.baseline)
            p_sits, n_sits = situation_counts(sits.situation, sits.baseline, scores)
            running.add(m, sweep_counts(rows, p_sits, n_sits))
            if m in zero:
                pos = scores[sits.baseline]
                zero[m][0] += int((pos <= 0).sum())
                zero[m][1] += pos.size
        if _batch_full(histograms):
            histograms.flush()
    running.flush()
    histograms.flush()
    if not sums or sums["situations"] == 0:
        raise StatsError("no frames to summarise")
    if n_sit == 0:
        raise StatsError("no agent-frames: every frame is empty (no agent besides the ego)")
    for m in swept:
        if m not in running.merged or not running.merged[m].rates.bins.size:
            raise StatsError(f"no agent has a risk_{m} value (every score is NaN)")
    binned = {m: binned_sweep(running.merged[m], n_sit) for m in swept}

    # Pass 2: the rows of the bins the operating thresholds fall in; the median bins.
    targets = {f"tpr_{t:g}": t for t in TPR_TARGETS}
    crossing = {
        m: {n: crossing_bin(binned[m], t, TPR_TOLERANCE) for n, t in targets.items()} for m in names
    }
    refine: dict[str, set[int]] = {}
    for m in names:
        merged = running.merged[m]
        mixed = merged.rates.low < merged.rates.high
        wanted = {b for b in crossing[m].values() if b is not None and mixed[b]}
        wanted.update(youden_candidates(binned[m], merged, TPR_TOLERANCE))
        if mixed.size and mixed[0]:
            wanted.add(0)
        refine[m] = wanted
    median_bins = _median_bins(histograms.merged)
    found_rows: dict[str, list[SweepRows]] = {m: [] for m in names if refine[m]}
    found_times: dict[tuple[str, str, str], list[np.ndarray]] = {k: [] for k in median_bins}
    if found_rows or median_bins:
        for part in read_parts():
            if median_bins:
                times = _time_values(part.frames, stages)
                for key, where in median_bins.items():
                    h = histograms.merged[key]
                    x = times[key[1]]
                    middle = np.isin(score_bins(x, h.level), h.bins[[i for i, _ in where]])
                    found_times[key].append(x[middle])
            if part.agents is None or not found_rows:
                continue
            sits = situations_of(part.agents)
            for m in found_rows:
                rows = sweep_rows(part.scores(m), sits.situation, sits.baseline)
                found_rows[m].append(
                    collapse(rows_in_bins(rows, running.merged[m], sorted(refine[m])))
                )
                if len(found_rows[m]) >= MERGE_BATCH:  # one entry per distinct score
                    found_rows[m] = [collapse(SweepRows.concat(found_rows[m]))]
    medians = _medians(found_times, histograms.merged, median_bins)
    thresholds: dict[str, dict[str, float]] = {}
    above_min: dict[str, float] = {}
    for m in names:
        rows = SweepRows.concat(found_rows.get(m, []))
        points: dict[int, BinPoints] = {
            b: points_in_bin(binned[m], running.merged[m], b, rows) for b in sorted(refine[m])
        }
        thresholds[m] = {}
        for n, t in targets.items():
            b = crossing[m][n]
            at = None if b is None else points.get(b)
            thresholds[m][n] = threshold_for_mean_tpr(binned[m], b, at, t, TPR_TOLERANCE)
        thresholds[m]["youden"] = youden_threshold(binned[m], points, TPR_TOLERANCE)
        above_min[m] = tpr_above_lowest(binned[m], points.get(0))

    # Pass 3: every situation at the exact thresholds; the per-frame pieces.
    point_sums = {m: {n: _PointSums() for n in thresholds[m]} for m in names}
    pieces: list[tuple[str, int, pathlib.Path]] = []
    scene_rows: list[pl.DataFrame] = []
    for k, part in enumerate(read_parts()):
        if part.agents is None:
            keys = part.frames.select(SITUATION_KEY).head(0)
            tpr95: dict[str, np.ndarray] = {m: np.empty(0) for m in names}
            kept95: dict[str, np.ndarray] = {m: np.empty(0) for m in names}
        else:
            sits = situations_of(part.agents)
            keys, tpr95, kept95 = sits.keys, {}, {}
            for m in names:
                scores = part.scores(m)
                for n, thr in thresholds[m].items():
                    rates = per_situation_rates(scores, sits, thr)
                    point_sums[m][n].add(rates, sits.n_positive)
                    if n == "tpr_0.95":
                        tpr95[m], kept95[m] = rates["tpr"], rates["kept"]
        per_frame = per_frame_table(part.frames, keys, tpr95, kept95)
        for (scene,), piece in per_frame.partition_by("scene", as_dict=True).items():
            path = scratch / f"{k}-{len(pieces)}.parquet"
            piece.write_parquet(path)
            pieces.append((str(scene), k, path))
            scene_rows.append(per_scene_table(piece, stages, tiers))
        if len(scene_rows) >= MERGE_BATCH:  # one frame, not one per scene
            scene_rows = [pl.concat(scene_rows, how="diagonal_relaxed")]
    pieces.sort(key=lambda x: (x[0], x[1]))
    piece_files = tuple(p for _, _, p in pieces)
    per_scene = pl.concat(scene_rows, how="diagonal_relaxed").sort("scene", maintain_order=True)

    per_model: dict[str, ModelStats] = {}
    summaries: dict[str, Any] = {}
    for m in names:
        sw = binned[m].sweep
        points_ = {n: point_sums[m][n].point(n, thr, n_sit) for n, thr in thresholds[m].items()}
        s = ModelStats(
            model=m, roc=sw, points=points_, std_tpr_curve=_curve_mean_std(sw),
            std_tpr_high=_std_range(sw, HIGH_TPR_RANGE), mean_tpr_above_min=above_min[m],
            per_situation_tpr={}, per_situation_kept={},
            zero_score_positive_share=zero[m][0] / zero[m][1] if zero[m][1] else math.nan,
        )  # fmt: skip
        per_model[m] = s
        summaries[m] = {
            **model_summary(s),
            "auc_error_bound": binned[m].auc_error_bound,
            "mixed_bins": binned[m].mixed_bins,
        }
    err = running.merged[errors_model].counts
    tp = np.rint(np.cumsum(err.positives[::-1])[::-1]).astype(np.int64)
    fp = np.rint(np.cumsum(err.negatives[::-1])[::-1]).astype(np.int64)
    errors = errors_table(errors_model, err.low, tp, fp, (tp[0] if tp.size else 0) - tp, n_sit)
    cascade = _cascade(sums, medians, stages, tiers)
    summary = stats_summary(
        inputs=inputs,
        situations={
            "total": sums["situations"],
            "with_agents": n_sit,
            "without_agents": sums["without_agents"],
            "empty_baseline": no_pos,
            "full_baseline": no_neg,
            "tpr_defined": n_sit - no_pos,
            "fpr_defined": n_sit - no_neg,
        },
        baseline={
            "model": BASELINE_MODEL,
            "threshold": baseline_threshold,
            "important_agent_frames": important,
            "agent_frames": agent_frames,
            "mean_important_per_situation": important / n_sit,
        },
        sweep=BINNED_SWEEP,
        models=summaries,
        errors_model=errors_model,
        cascade={"stage_names": stages, "tier_names": tiers, **cascade},
    )
    return DatasetStats(
        summary=summary,
        models=per_model,
        roc=pl.concat([s.curve() for s in per_model.values()]),
        errors=errors,
        funnel=funnel_table(cascade),
        per_frame=pl.read_parquet(piece_files[0]).head(0),  # the columns; rows stay on disk
        per_frame_pieces=piece_files,
        per_scene=per_scene,
        stage_names=tuple(stages),
        tier_names=tuple(tiers),
    )


def _batch_full(merging: _Merging) -> bool:
    return any(len(v) >= MERGE_BATCH for v in merging.pending.values())


def _cascade(
    sums: Mapping[str, Any],
    medians: Mapping[tuple[str, str, str], float],
    stages: Sequence[str],
    tiers: Sequence[str],
) -> dict[str, Any]:
    """:func:`replay.analysis.stats.compute.cascade_summary` from the parts' sums and
    the exact medians."""
    n, timed = sums["situations"], sums["timed"]
    baseline = sums["n_baseline"]

    def median(col: str) -> float:
        return medians.get(_key(col), math.nan)

    summary: dict[str, Any] = {
        "situations": n,
        "mean_others": sums["n_others"] / n,
        "baseline_agent_frames": baseline,
        "stages": [
            {
                "model": s,
                "mean_kept": sums[f"kept_{s}"] / n,
                "false_negatives": sums[f"fn_{s}"],
                "fn_share": sums[f"fn_{s}"] / baseline if baseline else math.nan,
                "situations_with_fn": sums[f"fn_any_{s}"],
                "time_s": sums[f"time_{s}_s"] if timed else None,
                "median_time_s": median(f"time_{s}_s") if timed else None,
            }
            for s in stages
        ],
        "tiers": [
            {
                "name": t,
                "mean_agents": sums[f"tier_{t}"] / n,
                "min_agents": sums[f"tier_min_{t}"],
                "max_agents": sums[f"tier_max_{t}"],
            }
            for t in tiers
        ],
        "timing_available": timed > 0,
        "timed_situations": timed,
    }
    if timed:
        stage_time = sum(sums[f"time_{s}_s"] for s in stages)
        sort_time, survival_all = sums["sort_time_s"], sums["survival_all_time_s"]
        cascade = stage_time + sort_time
        summary["compute"] = {
            "stages_time_s": stage_time,
            "sort_time_s": sort_time,
            "cascade_time_s": cascade,
            "survival_all_time_s": survival_all,
            "cascade_over_survival_all": cascade / survival_all if survival_all > 0 else math.nan,
            "median_cascade_time_s": median("cascade_time_s"),
            "median_sort_time_s": median("sort_time_s"),
            "median_survival_all_time_s": median("survival_all_time_s"),
        }
    return summary


__all__ = ["BINNED_SWEEP", "StatsPart", "ordered_parts", "stream_stats"]
