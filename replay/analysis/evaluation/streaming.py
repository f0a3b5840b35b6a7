"""The overall block of ``replay evaluate``'s summary from a run's part files, one scene
at a time (issue 38): the driver holds per-scene summaries and merged curves, never the
corpus's rows. Not yet what ``replay evaluate`` runs: see ``benchmarks/results/memory.md``.

Passes over ``OUT/parts/agents`` in scene-key order, each reading one part at a time
(only the score, reference, situation and cascade columns; columns a scene lacks are
nulls, as in the full evaluation's diagonal concatenation). Per chunk of
:data:`MODELS_PER_PASS` models (so that only that chunk's curves are held):

1. every scene's :class:`risk.roc_counts.BinCounts` per model and reference, merged into
   one running curve each; on the first chunk also the exact additive pieces: reference
   counts, agreement (agents are distinct within a scene, so counts add up), the
   budgets' kept positives per rule (situations lie inside a scene);
2. every scene on each curve's coarse bootstrap bins (one column per scene), weighed by
   :func:`risk.evaluation.scene_draws` over the key-ordered scenes: the resampling
   depends on the scene list and the seed, not on the engine or the order in which
   scenes finished; and the positives' scores in the bins where the operating
   thresholds fall, so that the thresholds are exact.

Then one pass for every model at the exact thresholds: missed agent-frames and agents,
kept shares and the miss rates' intervals.

Exact against :func:`replay.analysis.evaluation.corpus.evaluate_table` (tested): the
reference counts, agreement, budgets with their intervals, operating thresholds and miss
rates with their intervals. Within a stated bound: the AUC (``error_bound``, from the
bins that hold distinct scores, :func:`risk.roc_counts.binned_roc`) and the TPR at fixed
FPRs. Approximate: the AUC and TPR intervals (the bootstrap's 512 coarse bins group grid
bins, not distinct scores; identical when each bin holds one score). Not covered: the
per-group blocks (dataset, kind), the situation-mean AUC, site transfer, the cascade's
stage misses, composition medians, track flags, and the roc and positives tables.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import polars as pl

from replay.analysis.evaluation.corpus import (
    STATES,
    EvaluationError,
    agreement,
    reference_arrays,
    state_codes,
)
from replay.analysis.evaluation.files import positives_table
from risk.budgets import budget_recall
from risk.evaluation import (
    BOOT_BINS,
    FPR_POINTS,
    TPR_TARGETS,
    distinct,
    percentile_interval,
    reference_counts,
    reference_mask,
    scene_draws,
)
from risk.hindsight import HindsightSettings
from risk.registry import BASELINE_THRESHOLD, MODELS
from risk.roc_counts import (
    MAX_CURVE_BINS,
    BinCounts,
    bin_counts,
    binned_replicates,
    binned_roc,
    kth_highest,
    merge_counts,
    recall_crossing,
    scene_bin_matrix,
    score_bins,
)

#: Scenes' counts merged into the running curve at once (fewer sorts of the running one).
MERGE_BATCH = 32
#: Models whose curves (merged grid bins, and coarse bins x scenes for the bootstrap) are
#: held at once: two passes over the parts per chunk.
MODELS_PER_PASS = 3
#: The columns a reference may come from (besides ``label_*``), and the others the exact
#: per-scene pieces (counts, budgets, agreement) read.
_REFERENCE_COLUMNS = ("baseline", "truth_label", "truth_complete", "planner_label")
_OTHER_COLUMNS = (
    "scene", "frame", "ego_id", "agent_id", "distance_m", "truth_yielded", "track_ok", "kind",
    "t_s", "dataset", "dropped_by", "truth_gap_m", "truth_pet_s", "speed_mps",
)  # fmt: skip


@dataclass(frozen=True)
class StreamSettings:
    models: tuple[str, ...] | None = None  # default: every risk_<model> column
    baseline_threshold: float = BASELINE_THRESHOLD
    hindsight_windows: str = "complete"
    n_boot: int = 1000
    level: float = 0.95
    seed: int = 0
    fpr_points: tuple[float, ...] = FPR_POINTS
    max_curve_bins: int = MAX_CURVE_BINS  # merged curves are coarsened beyond this
    horizon_s: float = HindsightSettings().horizon_s  # scenes shorter are listed


def run_parts(out_dir: str | os.PathLike[str], table: str = "agents") -> list[pathlib.Path]:
    """The part files of ``table`` of a run's output folder, in scene-key order (from
    the markers of ``OUT/parts/.done``)."""
    done = pathlib.Path(out_dir) / "parts" / ".done"
    entries = []
    for marker in done.rglob("*.json"):
        data = json.loads(marker.read_text(encoding="utf-8"))
        path = data.get("tables", {}).get(table, {}).get("path")
        if path:
            entries.append((str(data["key"]), pathlib.Path(path)))
    if not entries:
        raise EvaluationError(f"{out_dir}: no complete scene with a {table} table")
    return [p for _, p in sorted(entries)]


def corpus_columns(parts: Sequence[pathlib.Path], models: Sequence[str] | None) -> pl.Schema:
    """The columns the pass reads, over every part (from the files' schemas only): a
    scene without one of them reads it as nulls, as the full evaluation's diagonal
    concatenation does (e.g. a scene without planner truth is unknown under it)."""
    union: dict[str, pl.DataType] = {}
    for path in parts:
        for name, dtype in pl.read_parquet_schema(path).items():
            union.setdefault(name, dtype)
    present = [m for m in MODELS if f"risk_{m}" in union]
    wanted = {f"risk_{m}" for m in (present if models is None else models) if m in present}
    return pl.Schema(
        {
            c: t
            for c, t in union.items()
            if c in wanted
            or c == "risk_survival"
            or c in _REFERENCE_COLUMNS
            or c in _OTHER_COLUMNS
            or c.startswith(("label_", "kept_"))
        }
    )


@dataclass
class SceneSummary:
    """What one scene adds: its ROC counts per (model, reference) and the exact additive
    pieces: reference counts, budget counts per rule, agreement counts."""

    curves: dict[tuple[str, str], BinCounts]
    counts: dict[str, dict[str, int]]
    budgets: dict[str, list[dict[str, Any]]]
    agreement: dict[str, Any]
    situations: int
    side: dict[str, Any] = field(default_factory=dict)  # :func:`side_counts`
    positives: pl.DataFrame | None = None  # its rows of the positives table
    short: bool = False  # its recorded span is shorter than the horizon
    name: str = ""  # its ``scene`` column


@dataclass(frozen=True)
class SceneArrays:
    """One part's rows in the evaluation's order: the table, model scores, references
    and agent identities (dense within the scene)."""

    df: pl.DataFrame
    scores: dict[str, np.ndarray]
    refs: dict[str, np.ndarray]
    agent_key: np.ndarray


def scene_arrays(path: pathlib.Path, settings: StreamSettings, columns: pl.Schema) -> SceneArrays:
    """One part over ``columns`` (:func:`corpus_columns`), its rows in the evaluation's
    order (frame, ego; stable), as
    :func:`replay.analysis.evaluation.collect.evaluation_agents` reads them."""
    own = pl.read_parquet_schema(path)
    df = pl.read_parquet(path, columns=[c for c in columns if c in own])
    df = df.with_columns(
        pl.lit(None, dtype=t).alias(c) for c, t in columns.items() if c not in own
    ).sort("frame", "ego_id", maintain_order=True)
    models = [c.removeprefix("risk_") for c in columns if c.startswith("risk_")]
    if settings.models is not None:
        models = [m for m in settings.models if m in models]
    refs, _ = reference_arrays(
        df, baseline_threshold=settings.baseline_threshold, windows=settings.hindsight_windows
    )
    scores = {m: df[f"risk_{m}"].to_numpy().astype(np.float64, copy=False) for m in models}
    return SceneArrays(df, scores, refs, _rank(df, "ego_id", "agent_id"))


def scene_summary(
    path: pathlib.Path,
    settings: StreamSettings,
    columns: pl.Schema,
    *,
    curve_models: Sequence[str] | None = None,
    exact: bool = True,
    datasets: Mapping[str, str] | None = None,
) -> SceneSummary:
    """One part's :class:`SceneSummary` (pass 1): the curves of ``curve_models`` (default:
    all); the exact pieces only with ``exact``."""
    arrays = scene_arrays(path, settings, columns)
    df, scores, refs, agent_key = arrays.df, arrays.scores, arrays.refs, arrays.agent_key
    curves = {
        (m, name): bin_counts(s, r)
        for m, s in scores.items()
        if curve_models is None or m in curve_models
        for name, r in refs.items()
    }
    if not exact:
        return SceneSummary(curves, {}, {}, {}, 0)
    situations = _rank(df, "ego_id", "frame")
    one = np.zeros(df.height, dtype=np.int64)  # the scene, as a cluster code
    counts = {name: reference_counts(r, agent_key, one) for name, r in refs.items()}
    stages = [c for c in df.columns if c.startswith("kept_")]
    distance = (
        df["distance_m"].to_numpy().astype(np.float64, copy=False)
        if "distance_m" in df.columns
        else None
    )
    budgets = {
        name: [
            _budget_counts(row, int(np.unique(situations).size))
            for row in budget_recall(
                scores, r, situations=situations, codes=one, distance_m=distance,
                kept_sets={"cascade": df[stages[-1]].to_numpy()} if stages else None,
            )
        ]
        for name, r in refs.items()
    }  # fmt: skip
    span = df["t_s"].max() - df["t_s"].min() if "t_s" in df.columns and df.height else None
    return SceneSummary(
        curves, counts, budgets, agreement(refs, df, agent_key), int(np.unique(situations).size),
        side=side_counts(df, refs, agent_key, datasets),
        positives=positives_table(df, datasets),
        short=span is not None and span < settings.horizon_s - 1e-9,  # type: ignore[operator]
        name=str(df["scene"][0]) if "scene" in df.columns and df.height else str(path),
    )  # fmt: skip


def _dataset_column(df: pl.DataFrame, datasets: Mapping[str, str] | None) -> pl.Series:
    """Each row's dataset, as the full evaluation names it: the mapping (scene ->
    dataset), else the ``dataset`` column, else ``unknown``."""
    if datasets:
        return df["scene"].cast(pl.String).replace_strict(dict(datasets), default="unknown")
    if "dataset" in df.columns:
        return df["dataset"].cast(pl.String).fill_null("unknown")
    return pl.Series(["unknown"] * df.height, dtype=pl.String)


def side_counts(
    df: pl.DataFrame,
    refs: Mapping[str, np.ndarray],
    agent_key: np.ndarray,
    datasets: Mapping[str, str] | None,
) -> dict[str, Any]:
    """One scene's additive pieces of the cascade's stage misses, the track flags and the
    composition's counts and shares (agents are distinct within a scene, so the distinct
    counts add up over scenes; :func:`merge_side` turns the sums into the blocks)."""
    n = df.height
    out: dict[str, Any] = {
        "rows": n,
        "egos": int(df["ego_id"].n_unique()) if n else 0,
        "speed": "speed_mps" in df.columns,
    }
    stages = [c for c in df.columns if c.startswith("kept_")]
    if stages:
        kept = np.column_stack([df[c].fill_null(False).to_numpy() for c in stages]).astype(bool)
        out["kept"] = {c.removeprefix("kept_"): int(kept[:, j].sum()) for j, c in enumerate(stages)}
        out["cascade"] = {}
        for name, r in refs.items():
            include, positive = reference_mask(r)
            pos = include & positive
            out["cascade"][name] = {
                "positives": int(pos.sum()),
                **{
                    c.removeprefix("kept_"): {
                        "missed_agent_frames": int((pos & ~kept[:, j]).sum()),
                        "missed_agents": distinct(agent_key, pos & ~kept[:, j]),
                    }
                    for j, c in enumerate(stages)
                },
            }
    if "track_ok" in df.columns:
        bad = ~df["track_ok"].fill_null(True).to_numpy().astype(bool)
        dataset = _dataset_column(df, datasets).to_numpy()
        kinds = df["kind"].cast(pl.String).fill_null("None").to_numpy()  # as str(None)
        out["track"] = {
            "agent_frames": int(bad.sum()),
            "agents": int(df.filter(pl.Series(bad))["agent_id"].n_unique()),
            "scenes": int(bad.any()),
            "by_kind": {str(k): int((kinds[bad] == k).sum()) for k in np.unique(kinds[bad])},
            "by_dataset": {
                str(d): [int((bad & (dataset == d)).sum()), int((dataset == d).sum())]
                for d in np.unique(dataset)
            },
        }
    t0 = (df["t_s"] - df["t_s"].min()).to_numpy() if n else np.zeros(0)
    speed = df["speed_mps"].to_numpy().astype(np.float64) if "speed_mps" in df.columns else None
    out["composition"] = {}
    for name, r in refs.items():
        if not name.startswith("hindsight"):
            continue
        st = state_codes(r)
        block = {}
        for label in ("positive", "negative"):
            m = st == STATES[label]
            block[label] = {
                "agent_frames": int(m.sum()),
                "first_2s": int((t0[m] <= 2.0 + 1e-9).sum()),
                "standing": int((speed[m] < 0.5).sum()) if speed is not None else 0,
            }
        out["composition"][name] = block
    return out


def _rank(df: pl.DataFrame, *columns: str) -> np.ndarray:
    return df.select(pl.struct(*columns).rank("dense").cast(pl.Int64)).to_series().to_numpy()


def _budget_counts(row: dict[str, Any], n_situations: int) -> dict[str, Any]:
    """A budget row of one scene as sums: its mean kept count times its situations."""
    return {
        "rule": row["rule"], "kind": row["kind"], "k": row["k"], "radius_m": row["radius_m"],
        "positives": row["positives"], "kept_positives": row["kept_positives"],
        "kept": round(row["mean_kept"] * n_situations),
    }  # fmt: skip


def add_counts(a: Any, b: Any) -> Any:
    """The sum of two nested count structures of the same shape (dicts by key, lists by
    position, numbers added, booleans or-ed, other leaves equal)."""
    if isinstance(a, dict):
        return {k: add_counts(a[k], b[k]) if k in a and k in b else a.get(k, b.get(k))
                for k in {**a, **b}}  # fmt: skip
    if isinstance(a, list):
        return [add_counts(x, y) for x, y in zip(a, b, strict=True)]
    if isinstance(a, bool):
        return a or b
    if isinstance(a, int | float) and not isinstance(a, bool):
        return a + b
    return a


def streamed_roc(
    parts: Sequence[pathlib.Path],
    settings: StreamSettings | None = None,
    *,
    datasets: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """``models -> reference -> {auc: {value, ci, error_bound}, tpr_at_fpr, agent_frames,
    positives, mixed_bins}`` over the scenes of ``parts`` (one part file per scene, in
    key order), and the bytes of the per-scene summaries held."""
    st = settings or StreamSettings()
    columns = corpus_columns(parts, st.models)
    n_scenes = len(parts)
    draws = scene_draws(n_scenes, n_boot=st.n_boot, seed=st.seed) if st.n_boot > 0 else None
    present = [c.removeprefix("risk_") for c in columns if c.startswith("risk_")]
    model_names = [m for m in (present if st.models is None else st.models) if m in present]
    chunks = [
        model_names[i : i + MODELS_PER_PASS] for i in range(0, len(model_names), MODELS_PER_PASS)
    ]
    totals: dict[str, Any] = {}
    budget_rules: dict[str, list[dict[str, Any]]] = {}
    budget_cols: dict[str, np.ndarray] = {}  # (rules, positives / kept ones / kept, S)
    situations = 0
    positive_rows: list[pl.DataFrame] = []
    short: list[str] = []
    with_positives: list[str] = []
    thresholds: dict[str, dict[str, float]] = {}
    models: dict[str, dict[str, Any]] = {}
    held = 0
    for number, chunk in enumerate(chunks or [[]]):
        # pass 1 (per chunk of models): the chunk's merged curves; on the first, the
        # exact sums too
        merged: dict[tuple[str, str], BinCounts] = {}
        pending: dict[tuple[str, str], list[BinCounts]] = {}
        for i, path in enumerate(parts):
            scene = scene_summary(
                path, st, columns, curve_models=chunk, exact=number == 0, datasets=datasets
            )
            if number == 0:
                situations += scene.situations
                exact = {"references": scene.counts, "agreement": scene.agreement,
                         "side": scene.side}  # fmt: skip
                if scene.positives is not None and scene.positives.height:
                    positive_rows.append(scene.positives)
                if scene.short:
                    short.append(scene.name)
                totals = add_counts(totals, exact) if totals else exact
                for name, rows in scene.budgets.items():
                    if name not in budget_cols:
                        budget_rules[name] = [
                            {k: r[k] for k in ("rule", "kind", "k", "radius_m")} for r in rows
                        ]
                        budget_cols[name] = np.zeros((len(rows), 3, n_scenes), dtype=np.int64)
                    budget_cols[name][:, :, i] = [
                        [r["positives"], r["kept_positives"], r["kept"]] for r in rows
                    ]
            for curve, counts in scene.curves.items():
                pending.setdefault(curve, []).append(counts)
            if (i + 1) % MERGE_BATCH == 0 or i + 1 == len(parts):
                for curve, batch in pending.items():
                    merged[curve] = merge_counts(
                        [merged.get(curve, BinCounts.empty()), *batch], st.max_curve_bins
                    )
                pending.clear()
        if number == 0:
            with_positives = [
                n for n, c in totals["references"].items() if c["positive_agent_frames"]
            ]
        crossings = {
            (m, name, t): recall_crossing(merged[m, name], t)
            for (m, name) in merged
            if name in with_positives
            for t in TPR_TARGETS
        }
        # Crossing bins holding several values: the positives' scores there decide.
        open_bins: dict[tuple[str, str, float], tuple[int, list[np.ndarray]]] = {
            key: (int(merged[key[:2]].bins[c[0]]), [])
            for key, c in crossings.items()
            if c is not None and merged[key[:2]].low[c[0]] < merged[key[:2]].high[c[0]]
        }
        cols = {
            curve: np.zeros((2, min(whole.bins.size, BOOT_BINS), n_scenes), dtype=np.int32)
            for curve, whole in merged.items()
            if draws is not None
        }
        if cols or open_bins:  # pass 2 (per chunk): bootstrap columns, crossing bins
            for j, path in enumerate(parts):
                arrays = scene_arrays(path, st, columns)
                for (m, name, _t), (b, found) in open_bins.items():
                    sc, r = arrays.scores[m], arrays.refs[name]
                    pos = (np.asarray(r) == 1) & ~np.isnan(sc)
                    pos[pos] = score_bins(sc[pos], merged[m, name].level) == b
                    found.append(sc[pos])
                for (m, name), col in cols.items():
                    counts = bin_counts(arrays.scores[m], arrays.refs[name])
                    p, n = scene_bin_matrix(merged[m, name], [counts])
                    col[0, :, j], col[1, :, j] = p[:, 0], n[:, 0]
        held = max(
            held,
            sum(c.nbytes for c in merged.values()) + sum(c.nbytes for c in cols.values()),
        )
        for (m, name, t), c in crossings.items():
            if c is None:
                value = -math.inf
            elif (m, name, t) in open_bins:
                value = kth_highest(np.concatenate(open_bins[m, name, t][1]), c[1])
            else:
                value = float(merged[m, name].low[c[0]])
            thresholds.setdefault(m, {})[f"tpr{t:g}_{name}"] = value
        for (m, name), whole in merged.items():
            models.setdefault(m, {})[name] = _roc_block(whole, cols.get((m, name)), draws, st)
        del merged, cols
    misses = _miss_columns(parts, st, columns, thresholds, with_positives)  # pass 3
    for m, refs in models.items():
        for name, block in refs.items():
            if name in with_positives:
                block["miss_rate"] = _miss_rates(misses[m, name], thresholds[m], draws, st.level)
    budgets = {
        name: _budget_rows(budget_rules[name], budget_cols[name], situations, draws, st.level)
        for name in with_positives
    }
    side = totals["side"]
    positives = (
        pl.concat(positive_rows, how="diagonal_relaxed").sort("scene", "ego_id", "agent_id")
        if positive_rows
        else pl.DataFrame()
    )
    return {"scenes": n_scenes, "models": models, "summary_bytes": int(held),
            "references": totals["references"], "agreement": totals["agreement"],
            "budgets": budgets, "thresholds": thresholds,
            "egos": side["egos"], "situations": situations,
            "scenes_shorter_than_horizon": sorted(short),
            "cascade": _cascade(side, with_positives),
            "track_flags": _track_flags(side),
            "composition": _composition(side),
            "positives": positives,
            "auc_method": "pooled ROC on a fixed score grid, summed over scenes"}  # fmt: skip


def _cascade(side: Mapping[str, Any], references: Sequence[str]) -> dict[str, Any]:
    """:func:`risk.evaluation.stage_misses` per reference from the scenes' sums."""
    if "kept" not in side:
        return {}
    rows = side["rows"]
    out: dict[str, Any] = {}
    for name in references:
        sums = side["cascade"][name]
        n_pos = sums["positives"]
        out[name] = [
            {
                "stage": stage,
                "missed_agent_frames": sums[stage]["missed_agent_frames"],
                "miss_rate": sums[stage]["missed_agent_frames"] / n_pos if n_pos else math.nan,
                "missed_agents": sums[stage]["missed_agents"],
                "kept_share": kept / rows if rows else math.nan,
            }
            for stage, kept in side["kept"].items()
        ]
    return out


def _track_flags(side: Mapping[str, Any]) -> dict[str, Any]:
    """The track-flag block of the summary (as the full evaluation's) from the sums."""
    if "track" not in side:
        return {"available": False}
    t = side["track"]
    return {
        "available": True,
        "agent_frames": t["agent_frames"],
        "share": t["agent_frames"] / max(1, side["rows"]),
        "agents": t["agents"],
        "scenes": t["scenes"],
        "by_kind": {k: v for k, v in t["by_kind"].items() if v},
        "share_by_dataset": {d: bad / rows for d, (bad, rows) in t["by_dataset"].items()},
    }


def _composition(side: Mapping[str, Any]) -> dict[str, Any]:
    """Counts and shares of the composition block (its medians are not streamed yet)."""
    out: dict[str, Any] = {}
    for name, labels in side.get("composition", {}).items():
        out[name] = {}
        for label, c in labels.items():
            block: dict[str, Any] = {"agent_frames": c["agent_frames"]}
            if c["agent_frames"]:
                block["share_first_2s"] = c["first_2s"] / c["agent_frames"]
                if side["speed"]:
                    block["share_standing"] = c["standing"] / c["agent_frames"]
            out[name][label] = block
    return out


def _roc_block(
    whole: BinCounts, col: np.ndarray | None, draws: np.ndarray | None, st: StreamSettings
) -> dict[str, Any]:
    """One curve's AUC, TPR at the FPR points (with their bounds) and, with the scenes'
    bootstrap columns ``col (2, bins, S)``, their intervals."""
    roc = binned_roc(whole)
    block: dict[str, Any] = {
        "agent_frames": roc.n_positive + roc.n_negative,
        "positives": roc.n_positive,
        "mixed_bins": roc.mixed_bins,
        "grid_level": whole.level,
        "auc": {"value": roc.auc, "error_bound": roc.auc_error_bound},
        "tpr_at_fpr": {
            f"{f:g}": {"value": roc.tpr_at(f), "error_bound": roc.tpr_error_bound}
            for f in st.fpr_points
        },
    }
    if draws is not None and col is not None and roc.n_positive and roc.n_negative:
        auc_r, tpr_r = binned_replicates(col[0], col[1], draws, st.fpr_points)
        block["auc"]["ci"] = list(percentile_interval(auc_r, level=st.level))
        for k, f in enumerate(st.fpr_points):
            block["tpr_at_fpr"][f"{f:g}"]["ci"] = list(
                percentile_interval(tpr_r[:, k], level=st.level)
            )
    return block


def _miss_columns(
    parts: Sequence[pathlib.Path],
    st: StreamSettings,
    columns: pl.Schema,
    thresholds: dict[str, dict[str, float]],
    references: Sequence[str],
) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """Per (model, reference): per threshold and scene ``(T, S)`` the positives kept, the
    positive and missed agent-frames, the distinct agents missed and the agent-frames
    kept, and per scene the included agent-frames."""
    n = len(parts)
    out: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for j, path in enumerate(parts):
        arrays = scene_arrays(path, st, columns)
        for m, s in arrays.scores.items():
            named = thresholds.get(m, {})
            for name in references:
                r = np.asarray(arrays.refs[name])
                scored = (r >= 0) & ~np.isnan(s)
                pos = scored & (r == 1)
                cols = out.setdefault((m, name), {
                    k: np.zeros((len(named), n), dtype=np.int64)
                    for k in ("kept_positives", "missed", "missed_agents", "kept")
                } | {"scored": np.zeros(n, dtype=np.int64),
                     "positives": np.zeros(n, dtype=np.int64)})  # fmt: skip
                cols["scored"][j] = scored.sum()
                cols["positives"][j] = pos.sum()
                for i, thr in enumerate(named.values()):
                    keep = s >= thr
                    missed = pos & ~keep
                    cols["kept_positives"][i, j] = (pos & keep).sum()
                    cols["missed"][i, j] = missed.sum()
                    cols["missed_agents"][i, j] = np.unique(arrays.agent_key[missed]).size
                    cols["kept"][i, j] = (scored & keep).sum()
    return out


def _miss_rates(
    cols: dict[str, np.ndarray], named: dict[str, float], draws: np.ndarray | None, level: float
) -> dict[str, Any]:
    """:func:`risk.evaluation.evaluate_scores`' miss rates from the scenes' columns."""
    n_pos, n_scored = int(cols["positives"].sum()), int(cols["scored"].sum())
    out: dict[str, Any] = {}
    for i, (name, thr) in enumerate(named.items()):
        missed = int(cols["missed"][i].sum())
        out[name] = {
            "threshold": float(thr),
            "value": missed / n_pos if n_pos else math.nan,
            "missed_agent_frames": missed,
            "missed_agents": int(cols["missed_agents"][i].sum()),
            "kept_share": int(cols["kept"][i].sum()) / n_scored if n_scored else math.nan,
        }
        if draws is not None and n_scored:
            d = draws.astype(np.float64)
            with np.errstate(invalid="ignore", divide="ignore"):
                tot = d @ cols["positives"].astype(np.float64)
                reps = np.where(
                    tot > 0, 1.0 - (d @ cols["kept_positives"][i].astype(np.float64)) / tot, np.nan
                )
            out[name]["ci"] = list(percentile_interval(reps, level=level))
    return out


def _budget_rows(
    rules: list[dict[str, Any]],
    cols: np.ndarray,
    situations: int,
    draws: np.ndarray | None,
    level: float,
) -> list[dict[str, Any]]:
    """The budget rows of the corpus from every scene's sums ``cols (rules, 3, S)``
    (positives, kept positives, kept agents): recall and mean kept count from the sums,
    the interval from the scenes' columns weighed by the draws (exact, as
    :func:`risk.budgets.budget_recall`)."""
    out = []
    for j, rule in enumerate(rules):
        pos, kept = cols[j, 0].astype(np.float64), cols[j, 1].astype(np.float64)
        n_pos, n_kept = int(cols[j, 0].sum()), int(cols[j, 1].sum())
        row: dict[str, Any] = {
            **rule,
            "mean_kept": int(cols[j, 2].sum()) / max(1, situations),
            "positives": n_pos,
            "kept_positives": n_kept,
            "value": n_kept / n_pos if n_pos else math.nan,
        }
        if draws is not None:
            d = draws.astype(np.float64)
            with np.errstate(invalid="ignore", divide="ignore"):
                reps = (d @ kept) / (d @ pos)
            row["ci"] = list(percentile_interval(reps, level=level))
        out.append(row)
    return out


def max_difference(streamed: dict[str, Any], summary: dict[str, Any]) -> dict[str, float]:
    """The largest AUC difference against an evaluation summary's (``summary["models"]``),
    the largest of the stated bounds, the largest difference of an interval's ends, and
    how many curves differ by more than their own bound, over the curves both have."""
    diff = bound = ci = 0.0
    beyond = 0
    for m, refs in streamed["models"].items():
        for name, block in refs.items():
            full = summary.get("models", {}).get(m, {}).get(name)
            if full is None or math.isnan(block["auc"]["value"]):
                continue
            gap = abs(block["auc"]["value"] - full["auc"]["value"])
            beyond += gap > block["auc"]["error_bound"] + 1e-12
            diff = max(diff, gap)
            bound = max(bound, block["auc"]["error_bound"])
            if "ci" in block["auc"] and "ci" in full["auc"]:
                ci = max(
                    ci,
                    *(
                        abs(a - b)
                        for a, b in zip(block["auc"]["ci"], full["auc"]["ci"], strict=True)
                    ),
                )
    return {"auc": diff, "auc_bound": bound, "auc_ci": ci, "beyond_bound": float(beyond)}
