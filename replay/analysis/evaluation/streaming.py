"""``replay evaluate``'s summary and tables from a run's part files, one scene at a time
(issue 38): the driver holds per-scene sums and merged curves, never the corpus's rows.

:func:`evaluate_parts` passes over the part files (``OUT/parts/agents``), each pass
reading one part at a time (only the columns that pass needs; columns a scene lacks are
nulls, as in a diagonal concatenation). A scene is a (scene name, part) pair; the
bootstrap's clusters are the scenes in name order, so the resampling depends on the scene
list and the seed, not on the engine or the order in which scenes finished.

1. Once: the exact additive pieces of every scene (agents are distinct within a scene,
   situations lie inside one): reference counts (overall and per group), agreement,
   the budgets' kept positives per rule, the cascade's stage misses, track flags, the
   composition's counts, shares and value histograms, short scenes, egos, situations,
   the positives table's rows.
2. Per chunk of :data:`CURVES_PER_PASS` curves (group x model x reference; groups are
   the whole corpus, each ``--group-by`` label and the calibration sites): every
   scene's :class:`risk.roc_counts.BinCounts` merged into one running curve each (and
   the mean-over-situations curve's weighted counts); then a second pass for the
   bootstrap columns (one per scene, on the merged curve's coarse bins) and the
   positives' scores in the bins where the operating thresholds fall.
3. Once, at the exact thresholds: miss rates with their intervals (overall and per
   group), site transfer, and the values in the bins holding the composition medians.

Exact against the full-rows evaluation (tested; the slow obvious oracle is
:func:`replay.analysis.evaluation.corpus.evaluate_table`): reference counts, agreement,
budgets with their intervals, operating thresholds, miss rates with their intervals,
stage misses, site transfer, composition (medians too: refined on the last pass), track
flags, short scenes, the positives table. Within a stated bound: every AUC
(``auc.error_bound``), the situation-mean AUC (``auc_situation_mean_error_bound``) and the
TPR at fixed FPRs (``error_bound``): a grid bin holding several distinct scores is one
threshold (:func:`risk.roc_counts.binned_roc`); the roc table's points are the binned
curve's. Approximate: the AUC and TPR intervals (the bootstrap's 512 coarse bins group
grid bins rather than distinct scores; identical when each grid bin holds one score).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import polars as pl

from replay.analysis.evaluation.corpus import (
    ROC_TABLE_POINTS,
    STATES,
    TRUTH_COLUMNS,
    EvaluationError,
    EvaluationSettings,
    agreement,
    calibration_sites,
    check_groupings,
    no_positive_message,
    reference_arrays,
    site_of,
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
    situation_weights,
    weighted_auc,
    weighted_bin_counts,
)

#: Scenes' counts merged into the running curve at once (fewer sorts of the running one).
MERGE_BATCH = 32
#: Curves (group x model x reference) held at once: their merged grid bins, and coarse
#: bins x scenes for the bootstrap; two passes over the parts per chunk.
CURVES_PER_PASS = 12
#: The columns a reference may come from (besides ``label_*``), and the others the exact
#: per-scene pieces (counts, budgets, agreement, flags, composition, positives) read.
_REFERENCE_COLUMNS = ("baseline", "truth_label", "truth_complete", "planner_label")
_OTHER_COLUMNS = (
    "scene", "frame", "ego_id", "agent_id", "distance_m", "truth_yielded", "track_ok", "kind",
    "t_s", "dataset", "dropped_by", "truth_gap_m", "truth_pet_s", "speed_mps",
)  # fmt: skip
#: A group of rows: () the whole corpus, (grouping, label), or the calibration sites.
Group = tuple[str, ...]
OVERALL: Group = ()
CALIBRATION: Group = ("calibration sites",)


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
    groupings: tuple[str, ...] = ()
    calibration_sites: tuple[str, ...] | None = None  # None: every other site
    targets: tuple[float, ...] = TPR_TARGETS

    @classmethod
    def of(
        cls, settings: EvaluationSettings, hindsight: HindsightSettings | None = None
    ) -> StreamSettings:
        """The settings of the command (``replay evaluate``'s options)."""
        return cls(
            models=settings.models, baseline_threshold=settings.baseline_threshold,
            hindsight_windows=settings.hindsight_windows, n_boot=settings.n_boot,
            level=settings.level, seed=settings.seed,
            horizon_s=(hindsight or HindsightSettings()).horizon_s,
            groupings=check_groupings(settings.groupings),
            calibration_sites=settings.calibration_sites,
        )  # fmt: skip


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


@dataclass(frozen=True)
class SceneRows:
    """One scene's rows in the evaluation's order (frame, ego; stable): the table, model
    scores, references, agent identities and situations (dense within the scene), the
    group label of every row per grouping, and its place among the scenes (``index``:
    the bootstrap's cluster)."""

    name: str
    index: int
    df: pl.DataFrame
    scores: dict[str, np.ndarray]
    refs: dict[str, np.ndarray]
    agent_key: np.ndarray
    situations: np.ndarray
    labels: dict[str, np.ndarray]

    def mask(self, group: Group, calibration: frozenset[str]) -> np.ndarray | None:
        """The rows of ``group`` (None: every row)."""
        if group == OVERALL:
            return None
        if group == CALIBRATION:
            return np.full(self.df.height, site_of(self.name) in calibration)
        return self.labels[group[0]] == group[1]


def scene_units(parts: Sequence[pathlib.Path]) -> list[tuple[str, int]]:
    """Every (scene name, part number) in name order: the scenes of the bootstrap (a
    part given twice is two scenes; a table part may hold several scenes)."""
    units: set[tuple[str, int]] = set()
    for k, path in enumerate(parts):
        if "scene" in pl.read_parquet_schema(path):
            names = pl.read_parquet(path, columns=["scene"])["scene"].cast(pl.String).unique()
            units.update((str(n), k) for n in names.to_list())
        else:
            units.add((str(path), k))
    return sorted(units)


def iter_scenes(
    parts: Sequence[pathlib.Path],
    st: StreamSettings,
    columns: pl.Schema,
    *,
    datasets: Mapping[str, str] | None = None,
    models: Sequence[str] | None = None,
    units: Sequence[tuple[str, int]] | None = None,
) -> Iterator[SceneRows]:
    """Every scene of ``parts``, one part read at a time over ``columns`` (of the risk
    columns only those of ``models``, default all; :func:`corpus_columns`)."""
    index = {u: j for j, u in enumerate(units or scene_units(parts))}
    wanted = {
        c: t
        for c, t in columns.items()
        if not c.startswith("risk_") or c == "risk_survival" or models is None
        or c.removeprefix("risk_") in models
    }  # fmt: skip
    for k, path in enumerate(parts):
        own = pl.read_parquet_schema(path)
        df = pl.read_parquet(path, columns=[c for c in wanted if c in own])
        df = df.with_columns(
            pl.lit(None, dtype=t).alias(c) for c, t in wanted.items() if c not in own
        )
        if "scene" not in own:
            df = df.with_columns(pl.lit(str(path)).alias("scene"))
        for (name,), sub in sorted(df.partition_by("scene", as_dict=True).items()):
            yield _scene_rows(str(name), index[str(name), k], sub, st, datasets)


def _scene_rows(
    name: str,
    index: int,
    df: pl.DataFrame,
    st: StreamSettings,
    datasets: Mapping[str, str] | None,
) -> SceneRows:
    df = df.sort("frame", "ego_id", maintain_order=True)
    present = [c.removeprefix("risk_") for c in df.columns if c.startswith("risk_")]
    models = [m for m in (present if st.models is None else st.models) if m in present]
    refs, _ = reference_arrays(
        df, baseline_threshold=st.baseline_threshold, windows=st.hindsight_windows
    )
    scores = {m: df[f"risk_{m}"].to_numpy().astype(np.float64, copy=False) for m in models}
    labels: dict[str, np.ndarray] = {}
    for g in st.groupings:
        if g == "dataset":
            labels[g] = _dataset_column(df, datasets).to_numpy()
        elif g == "kind":
            labels[g] = df["kind"].cast(pl.String).fill_null("other").to_numpy()
        else:  # site
            labels[g] = np.full(df.height, site_of(name), dtype=object)
    return SceneRows(
        name, index, df, scores, refs, _rank(df, "ego_id", "agent_id"),
        _rank(df, "ego_id", "frame"), labels,
    )  # fmt: skip


@dataclass
class SceneSummary:
    """What one scene adds exactly (pass 1): reference counts per group, budget sums per
    rule, agreement, the side pieces (:func:`side_counts`), its positives, and the
    composition's value histograms (hindsight rule, label, quantity) -> counts."""

    counts: dict[Group, dict[str, dict[str, int]]]
    budgets: dict[str, list[dict[str, Any]]]
    agreement: dict[str, Any]
    situations: int
    side: dict[str, Any]
    positives: pl.DataFrame
    short: bool
    histograms: dict[tuple[str, str, str], BinCounts]
    labels: dict[str, set[str]]


def scene_summary(
    rows: SceneRows, st: StreamSettings, datasets: Mapping[str, str] | None
) -> SceneSummary:
    """One scene's exact pieces."""
    df, scores, refs, agent_key = rows.df, rows.scores, rows.refs, rows.agent_key
    one = np.zeros(df.height, dtype=np.int64)  # the scene, as a cluster code
    n_sit = int(np.unique(rows.situations).size)
    counts: dict[Group, dict[str, dict[str, int]]] = {
        OVERALL: {name: reference_counts(r, agent_key, one) for name, r in refs.items()}
    }
    for g, lab in rows.labels.items():
        for label in np.unique(lab):
            m = lab == label
            counts[g, str(label)] = {
                name: reference_counts(r[m], agent_key[m], one[m]) for name, r in refs.items()
            }
    stages = [c for c in df.columns if c.startswith("kept_")]
    distance = (
        df["distance_m"].to_numpy().astype(np.float64, copy=False)
        if "distance_m" in df.columns
        else None
    )
    budgets = {
        name: [
            _budget_counts(row, n_sit)
            for row in budget_recall(
                scores, r, situations=rows.situations, codes=one, distance_m=distance,
                kept_sets={"cascade": df[stages[-1]].to_numpy()} if stages else None,
            )
        ]
        for name, r in refs.items()
    }  # fmt: skip
    span = df["t_s"].max() - df["t_s"].min() if df.height else None  # type: ignore[operator]
    return SceneSummary(
        counts, budgets, agreement(refs, df, agent_key), n_sit,
        side=side_counts(df, refs, agent_key, datasets),
        positives=positives_table(df, datasets),
        short=bool(span is not None and span < st.horizon_s - 1e-9),  # type: ignore[operator]
        histograms=_histograms(df, refs),
        labels={g: {str(x) for x in np.unique(lab)} for g, lab in rows.labels.items()},
    )  # fmt: skip


def _composition_values(df: pl.DataFrame) -> dict[str, np.ndarray]:
    """The composition's quantities per row: time since the scene's first frame (s) and
    the agent's speed (m/s; NaN left out of the median, as ``np.nanmedian``)."""
    out = {"time_in_scene_s": (df["t_s"] - df["t_s"].min()).to_numpy().astype(np.float64)}
    if "speed_mps" in df.columns:
        out["speed_mps"] = df["speed_mps"].to_numpy().astype(np.float64)
    return out


def _histograms(
    df: pl.DataFrame, refs: Mapping[str, np.ndarray]
) -> dict[tuple[str, str, str], BinCounts]:
    values = _composition_values(df)
    out = {}
    for name, r in refs.items():
        if not name.startswith("hindsight"):
            continue
        st = state_codes(r)
        for label in ("positive", "negative"):
            m = st == STATES[label]
            for q, v in values.items():
                x = v[m]
                x = x[~np.isnan(x)]
                out[name, label, q] = bin_counts(x, np.ones(x.size, dtype=bool))
    return out


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


@dataclass
class StreamedEvaluation:
    """:func:`evaluate_parts`' result: the summary (as the full-rows evaluation's, with
    the bounds of the binned figures), the roc and positives tables, and the bytes of
    merged curves and bootstrap columns held at most."""

    summary: dict[str, Any]
    roc: pl.DataFrame
    positives: pl.DataFrame
    held_bytes: int = 0


@dataclass
class _Merging:
    """Running merged curves of one chunk: batches of scenes' counts wait in ``pending``."""

    max_bins: int | None
    merged: dict[Any, BinCounts] = field(default_factory=dict)
    pending: dict[Any, list[BinCounts]] = field(default_factory=dict)

    def add(self, key: Any, counts: BinCounts) -> None:
        self.pending.setdefault(key, []).append(counts)

    def flush(self) -> None:
        for key, batch in self.pending.items():
            self.merged[key] = merge_counts(
                [self.merged.get(key, BinCounts.empty()), *batch], self.max_bins
            )
        self.pending.clear()


def evaluate_parts(
    parts: Sequence[pathlib.Path],
    settings: StreamSettings | None = None,
    *,
    datasets: Mapping[str, str] | None = None,
    hindsight: HindsightSettings | None = None,
    inputs: Sequence[str] = (),
    evaluation: EvaluationSettings | None = None,
) -> StreamedEvaluation:
    """The evaluation of the scenes in ``parts`` (part files of the agents table, each
    read one at a time; see the module docstring). ``evaluation``: the command's
    settings, recorded in the summary (default: from ``settings``). Raises
    :class:`EvaluationError` as the full evaluation does (missing columns or models, no
    positive under any reference, an unknown calibration site)."""
    st = settings or StreamSettings()
    if not parts:
        raise EvaluationError("no scene to evaluate")
    columns = corpus_columns(parts, st.models)
    _check_columns(parts, columns, st)
    units = scene_units(parts)
    n_scenes = len(units)
    draws = scene_draws(n_scenes, n_boot=st.n_boot, seed=st.seed) if st.n_boot > 0 else None
    present = [c.removeprefix("risk_") for c in columns if c.startswith("risk_")]
    models = [m for m in (present if st.models is None else st.models) if m in present]
    sites = sorted({site_of(name) for name, _ in units})
    calibration = calibration_sites(st.calibration_sites, sites)
    cal = frozenset(calibration)

    def scenes(models: Sequence[str] | None = None) -> Iterator[SceneRows]:
        return iter_scenes(parts, st, columns, datasets=datasets, models=models, units=units)

    # Pass 1: the exact pieces.
    totals: dict[str, Any] = {}
    group_counts: dict[Group, dict[str, dict[str, int]]] = {}
    budget_rules: dict[str, list[dict[str, Any]]] = {}
    budget_cols: dict[str, np.ndarray] = {}  # (rules, positives / kept ones / kept, S)
    histograms = _Merging(st.max_curve_bins)
    labels: dict[str, set[str]] = {g: set() for g in st.groupings}
    positive_rows: list[pl.DataFrame] = []
    short: list[str] = []
    situations = 0
    cal_rows = test_rows = 0
    for i, rows in enumerate(scenes()):
        scene = scene_summary(rows, st, datasets)
        situations += scene.situations
        exact = {"references": scene.counts[OVERALL], "agreement": scene.agreement,
                 "side": scene.side}  # fmt: skip
        totals = add_counts(totals, exact) if totals else exact
        for g, c in scene.counts.items():
            group_counts[g] = add_counts(group_counts[g], c) if g in group_counts else c
        for name, brows in scene.budgets.items():
            if name not in budget_cols:
                budget_rules[name] = [
                    {k: r[k] for k in ("rule", "kind", "k", "radius_m")} for r in brows
                ]
                budget_cols[name] = np.zeros((len(brows), 3, n_scenes), dtype=np.int64)
            budget_cols[name][:, :, rows.index] = [
                [r["positives"], r["kept_positives"], r["kept"]] for r in brows
            ]
        for key, h in scene.histograms.items():
            histograms.add(key, h)
        for grouping, seen in scene.labels.items():
            labels[grouping] |= seen
        if scene.positives.height:
            positive_rows.append(scene.positives)
        if scene.short:
            short.append(rows.name)
        if site_of(rows.name) in cal:
            cal_rows += rows.df.height
        else:
            test_rows += rows.df.height
        if (i + 1) % MERGE_BATCH == 0:
            histograms.flush()
    histograms.flush()
    side = totals["side"]
    counts = totals["references"]
    refs = [n for n, c in counts.items() if c["positive_agent_frames"] > 0]
    if not refs:
        h = counts["hindsight"]
        raise EvaluationError(
            no_positive_message(side["rows"], n_scenes, h["unknown_agent_frames"], hindsight)
        )
    groups: list[Group] = [OVERALL] + [(g, lab) for g in st.groupings for lab in sorted(labels[g])]
    transfer = bool(calibration) and cal_rows > 0 and test_rows > 0
    curve_groups = groups + ([CALIBRATION] if transfer else [])

    # Pass 2 (per chunk of curves): merged curves, then bootstrap columns and the
    # positives' scores in the bins where the thresholds fall.
    pairs = [(g, m) for m in models for g in curve_groups]
    per_chunk = max(1, CURVES_PER_PASS // max(1, len(refs)))
    thresholds: dict[str, dict[str, float]] = {m: {} for m in models}
    cal_thresholds: dict[tuple[str, str], float] = {}
    blocks: dict[tuple[Group, str, str], dict[str, Any]] = {}
    roc_frames: list[pl.DataFrame] = []
    held = 0
    for start in range(0, len(pairs), per_chunk):
        chunk = pairs[start : start + per_chunk]
        chunk_models = sorted({m for _, m in chunk})
        curves, sit_curves = _Merging(st.max_curve_bins), _Merging(st.max_curve_bins)
        for i, rows in enumerate(scenes(chunk_models)):
            for g, m in chunk:
                mask = rows.mask(g, cal)
                s, sit = _masked(rows.scores[m], mask), _masked(rows.situations, mask)
                for name in refs:
                    r = _masked(rows.refs[name], mask)
                    curves.add((g, m, name), bin_counts(s, r))
                    if g != CALIBRATION:
                        include, positive = reference_mask(r)
                        ok = include & ~np.isnan(s)
                        pw, nw = situation_weights(sit[ok], positive[ok])
                        sit_curves.add((g, m, name), weighted_bin_counts(s[ok], pw, nw))
            if (i + 1) % MERGE_BATCH == 0:
                curves.flush()
                sit_curves.flush()
        curves.flush()
        sit_curves.flush()
        merged = curves.merged
        crossings = {
            (g, m, name, t): recall_crossing(merged[g, m, name], t)
            for (g, m, name) in merged
            if g in (OVERALL, CALIBRATION)
            for t in (st.targets if g == OVERALL else st.targets[:1])
        }
        open_bins: dict[tuple[Group, str, str, float], tuple[int, list[np.ndarray]]] = {
            key: (int(merged[key[:3]].bins[c[0]]), [])
            for key, c in crossings.items()
            if c is not None and merged[key[:3]].low[c[0]] < merged[key[:3]].high[c[0]]
        }
        cols = {
            key: np.zeros((2, min(whole.bins.size, BOOT_BINS), n_scenes), dtype=np.int32)
            for key, whole in merged.items()
            if draws is not None and key[0] != CALIBRATION
        }
        if cols or open_bins:
            for rows in scenes(chunk_models):
                masks = {g: rows.mask(g, cal) for g, _ in chunk}
                for (g, m, name, _t), (b, in_bin) in open_bins.items():
                    sc = _masked(rows.scores[m], masks[g])
                    pos = (np.asarray(_masked(rows.refs[name], masks[g])) == 1) & ~np.isnan(sc)
                    pos[pos] = score_bins(sc[pos], merged[g, m, name].level) == b
                    in_bin.append(sc[pos])
                for (g, m, name), col in cols.items():
                    one = bin_counts(
                        _masked(rows.scores[m], masks[g]), _masked(rows.refs[name], masks[g])
                    )
                    p, n = scene_bin_matrix(merged[g, m, name], [one])
                    col[0, :, rows.index], col[1, :, rows.index] = p[:, 0], n[:, 0]
        held = max(
            held,
            sum(c.nbytes for c in merged.values())
            + sum(c.nbytes for c in sit_curves.merged.values())
            + sum(c.nbytes for c in cols.values()),
        )
        for (g, m, name, t), crossing in crossings.items():
            if crossing is None:
                value = -math.inf
            elif (g, m, name, t) in open_bins:
                value = kth_highest(np.concatenate(open_bins[g, m, name, t][1]), crossing[1])
            else:
                value = float(merged[g, m, name].low[crossing[0]])
            if g == OVERALL:
                thresholds[m][f"tpr{t:g}_{name}"] = value
            else:
                cal_thresholds[m, name] = value
        for (g, m, name), whole in merged.items():
            if g == CALIBRATION:
                continue
            block = _roc_block(whole, cols.get((g, m, name)), draws, st)
            auc, bound = weighted_auc(sit_curves.merged[g, m, name])
            block["auc_situation_mean"] = auc
            block["auc_situation_mean_error_bound"] = bound
            blocks[g, m, name] = block
            if g == OVERALL:
                roc_frames.append(_roc_points(whole, m, name))
        del merged, cols, curves, sit_curves
    # The thresholds in the full evaluation's order: reference, then target.
    thresholds = {
        m: {f"tpr{t:g}_{n}": thresholds[m][f"tpr{t:g}_{n}"] for n in refs for t in st.targets}
        for m in models
    }

    # Pass 3: miss rates at the thresholds, site transfer, the composition's medians.
    last = _last_pass(
        scenes(),
        groups, models, refs, thresholds, cal_thresholds if transfer else {}, cal,
        histograms.merged, _median_bins(histograms.merged), n_scenes,
    )  # fmt: skip
    by: dict[str, dict[str, Any]] = {g: {} for g in st.groupings}
    overall: dict[str, Any] = {}
    for g in groups:
        block = {
            "references": {n: group_counts[g][n] for n in refs},
            "models": {
                m: {
                    n: {
                        **blocks[g, m, n],
                        "miss_rate": _miss_rates(last.misses[g, m, n], thresholds[m], draws,
                                                 st.level),
                    }
                    for n in refs
                }
                for m in models
            },
        }  # fmt: skip
        if g == OVERALL:
            overall = block
        else:
            by[g[0]][g[1]] = block
    summary: dict[str, Any] = {
        "inputs": list(inputs),
        # how every "auc" is computed (replay stats averages per situation; issue 31)
        "auc_method": "one ROC curve pooled over every agent-frame",
        "auc_binning": (
            "thresholds on a fixed score grid, counts summed over scenes: each auc states "
            "its error_bound, the largest difference from the every-distinct-score curve"
        ),
        "settings": _settings_block(evaluation, st, models, calibration),
        "hindsight": None if hindsight is None else _asdict(hindsight),
        "baseline": {"model": "survival", "threshold": st.baseline_threshold},
        "scenes": n_scenes,
        "egos": side["egos"],
        "situations": situations,
        "scenes_shorter_than_horizon": sorted(short),
        "operating_thresholds": OPERATING_THRESHOLDS,
        "bootstrap": {
            "n_boot": st.n_boot,
            "level": st.level,
            "seed": st.seed,
            "scenes": n_scenes,
        },
        "thresholds": thresholds,
        "references": {**counts, **overall["references"]},
        "models": overall["models"],
        "by": by,
    }
    if "kept" in side:
        summary["cascade"] = _cascade(side, refs)
    if transfer:
        summary["site_transfer"] = _site_transfer(last.transfer, cal_thresholds, calibration,
                                                  sites, st.targets[0])  # fmt: skip
    summary.update(
        {
            "reference_names": refs,
            "references_missing": _references_missing(columns, st),
            "references_without_positives": {
                n: (
                    f"no positive among {c['agent_frames']} agent-frames "
                    f"({c['negative_agent_frames']} negative, {c['unknown_agent_frames']} "
                    "unknown): every rate against it is undefined"
                )
                for n, c in counts.items()
                if n not in refs
            },
            "budgets": {
                n: _budget_rows(budget_rules[n], budget_cols[n], situations, draws, st.level)
                for n in refs
            },
            "agreement": totals["agreement"],
            "composition": _composition(side, histograms.merged, last.medians),
            "track_flags": _track_flags(side),
        }
    )
    positives = (
        pl.concat(positive_rows, how="diagonal_relaxed").sort("scene", "ego_id", "agent_id")
        if positive_rows
        else pl.DataFrame()
    )
    roc = pl.concat(roc_frames) if roc_frames else pl.DataFrame()
    return StreamedEvaluation(summary, roc, positives, int(held))


def evaluate_frame(
    agents: pl.DataFrame,
    *,
    settings: EvaluationSettings | None = None,
    datasets: Mapping[str, str] | None = None,
    hindsight: HindsightSettings | None = None,
    inputs: Sequence[str] = (),
) -> dict[str, Any]:
    """The summary of an agents table already in memory (the library's
    :func:`replay.analysis.evaluation.collect.evaluate_inputs` and the sensitivity
    sweep's), by the same passes as ``replay evaluate``: each scene is written to a
    temporary part file and :func:`evaluate_parts` reads them back."""
    settings = settings or EvaluationSettings()
    with tempfile.TemporaryDirectory(prefix="replay-evaluate-") as tmp:
        scenes = (
            sorted(agents.partition_by("scene", as_dict=True).items(), key=lambda kv: str(kv[0]))
            if "scene" in agents.columns and agents.height
            else [(("",), agents)]
        )
        paths = []
        for k, (_, part) in enumerate(scenes):
            paths.append(pathlib.Path(tmp) / f"{k}.parquet")
            part.write_parquet(paths[-1])
        return evaluate_parts(
            paths, StreamSettings.of(settings, hindsight), datasets=datasets,
            hindsight=hindsight, inputs=inputs, evaluation=settings,
        ).summary  # fmt: skip


OPERATING_THRESHOLDS = {
    "tpr0.95_survival": "highest threshold keeping 95 % of survival-baseline agent-frames (pooled)",
    "tpr1_survival": "highest threshold keeping every survival-baseline agent-frame",
    "tpr0.95_hindsight": "highest threshold keeping 95 % of hindsight positives",
    "tpr1_hindsight": "highest threshold keeping every hindsight positive",
}


def _asdict(value: Any) -> dict[str, Any]:

    return asdict(value)


def _settings_block(
    evaluation: EvaluationSettings | None,
    st: StreamSettings,
    models: Sequence[str],
    calibration: Sequence[str],
) -> dict[str, Any]:
    ev = evaluation or EvaluationSettings(
        models=st.models, baseline_threshold=st.baseline_threshold, groupings=st.groupings,
        calibration_sites=st.calibration_sites, n_boot=st.n_boot, level=st.level,
        seed=st.seed, hindsight_windows=st.hindsight_windows,
    )  # fmt: skip
    return {
        **{k: (list(v) if isinstance(v, tuple) else v) for k, v in _asdict(ev).items()},
        "models": list(models),
        "calibration_sites": list(calibration),
    }


def _masked(values: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    return values if mask is None else values[mask]


def _check_columns(parts: Sequence[pathlib.Path], columns: pl.Schema, st: StreamSettings) -> None:
    """The full evaluation's checks, on the union of the parts' columns."""
    union: set[str] = set()
    for path in parts:
        union.update(pl.read_parquet_schema(path))
    missing = [c for c in ("scene", "agent_id", "ego_id", "kind", *TRUTH_COLUMNS) if c not in union]
    if missing:
        raise EvaluationError(
            f"the table has no {', '.join(missing)} column(s): it was written before the "
            "hindsight truth existed; replay the scenes again (replay run --table, or give "
            "the .mcap scenes to replay evaluate)"
        )
    present = [m for m in MODELS if f"risk_{m}" in union]
    for m in st.models or ():
        if m not in present:
            raise EvaluationError(
                f"no risk_{m} column in the table; it has: {', '.join(present) or 'none'}"
            )
    if "risk_survival" not in union and "baseline" not in union:
        raise EvaluationError("the table has neither risk_survival nor baseline")


def _references_missing(columns: pl.Schema, st: StreamSettings) -> dict[str, str]:
    """The notes on absent references: they depend on the columns only."""
    empty = pl.DataFrame(schema=columns)
    _, missing = reference_arrays(
        empty, baseline_threshold=st.baseline_threshold, windows=st.hindsight_windows
    )
    return missing


def _roc_points(whole: BinCounts, model: str, reference: str) -> pl.DataFrame:
    """The roc table's rows of one binned curve (thresholds ascending, at most
    :data:`ROC_TABLE_POINTS`, evenly spread, the ends kept)."""
    roc = binned_roc(whole)
    k = roc.thresholds.size
    idx = (
        np.unique(np.linspace(0, k - 1, min(k, ROC_TABLE_POINTS)).round().astype(int))
        if k
        else np.empty(0, int)
    )
    return pl.DataFrame(
        {
            "model": [model] * idx.size,
            "reference": [reference] * idx.size,
            "threshold": roc.thresholds[idx],
            "tpr": roc.tpr[idx],
            "fpr": roc.fpr[idx],
        }
    )


def _median_bins(
    histograms: Mapping[tuple[str, str, str], BinCounts],
) -> dict[tuple[str, str, str], list[tuple[int, int]]]:
    """Per histogram, the bins (index) and ranks in them (0 = the lowest) of its middle
    value(s): one for an odd count, two for an even one (the median is their mean)."""
    out = {}
    for key, h in histograms.items():
        n = int(h.positives.sum())
        if n == 0:
            continue
        cum = np.cumsum(h.positives)
        ranks = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
        out[key] = [
            (i, int(k - (cum[i - 1] if i else 0)))
            for k in ranks
            for i in [int(np.searchsorted(cum, k + 1))]
        ]
    return out


@dataclass
class _LastPass:
    misses: dict[tuple[Group, str, str], dict[str, np.ndarray]]
    transfer: dict[tuple[str, str], dict[str, dict[str, int]]]
    medians: dict[tuple[str, str, str], float]


def _last_pass(
    scenes: Iterator[SceneRows],
    groups: Sequence[Group],
    models: Sequence[str],
    refs: Sequence[str],
    thresholds: Mapping[str, Mapping[str, float]],
    cal_thresholds: Mapping[tuple[str, str], float],
    cal: frozenset[str],
    histograms: Mapping[tuple[str, str, str], BinCounts],
    median_bins: Mapping[tuple[str, str, str], list[tuple[int, int]]],
    n_scenes: int,
) -> _LastPass:
    """Pass 3: per (group, model, reference) the miss columns at the model's thresholds
    (per scene: positives and kept positives, for the intervals; totals of the rest);
    per (model, reference) the site transfer's counts; the composition's middle values."""
    misses: dict[tuple[Group, str, str], dict[str, np.ndarray]] = {}
    transfer: dict[tuple[str, str], dict[str, dict[str, int]]] = {}
    found: dict[tuple[str, str, str], list[np.ndarray]] = {k: [] for k in median_bins}
    for rows in scenes:
        j = rows.index
        for g in groups:
            mask = rows.mask(g, cal)
            key_ = _masked(rows.agent_key, mask)
            for m in models:
                s = _masked(rows.scores[m], mask)
                named = list(thresholds[m].values())
                for name in refs:
                    r = np.asarray(_masked(rows.refs[name], mask))
                    scored = (r >= 0) & ~np.isnan(s)
                    pos = scored & (r == 1)
                    cols = misses.setdefault((g, m, name), {
                        "kept_positives": np.zeros((len(named), n_scenes), dtype=np.int64),
                        "positives": np.zeros(n_scenes, dtype=np.int64),
                        **{k: np.zeros(len(named), dtype=np.int64)
                           for k in ("missed", "missed_agents", "kept")},
                        "scored": np.zeros(1, dtype=np.int64),
                    })  # fmt: skip
                    cols["scored"][0] += scored.sum()
                    cols["positives"][j] = pos.sum()
                    for i, thr in enumerate(named):
                        keep = s >= thr
                        missed = pos & ~keep
                        cols["kept_positives"][i, j] = (pos & keep).sum()
                        cols["missed"][i] += missed.sum()
                        cols["missed_agents"][i] += np.unique(key_[missed]).size
                        cols["kept"][i] += (scored & keep).sum()
        part = "calibration" if site_of(rows.name) in cal else "test"
        for (m, name), thr in cal_thresholds.items():
            s, r = rows.scores[m], rows.refs[name]
            include, positive = reference_mask(r)
            agent = include & ~np.isnan(s)
            pos = agent & positive
            keep = s >= thr
            t = transfer.setdefault((m, name), {})
            t[part] = add_counts(t.get(part, _NO_COUNTS), {
                "positives": int(pos.sum()), "kept_positives": int((keep & pos).sum()),
                "agents": int(agent.sum()), "kept_agents": int((keep & agent).sum()),
            })  # fmt: skip
        if median_bins:
            values = _composition_values(rows.df)
            for key, where in median_bins.items():
                name, label, q = key
                h = histograms[key]
                x = values[q][state_codes(rows.refs[name]) == STATES[label]]
                x = x[~np.isnan(x)]
                middle = np.isin(score_bins(x, h.level), h.bins[[i for i, _ in where]])
                found[key].append(x[middle])  # only the middle bins' values
    return _LastPass(misses, transfer, _medians(found, histograms, median_bins))


_NO_COUNTS = {"positives": 0, "kept_positives": 0, "agents": 0, "kept_agents": 0}


def _medians(
    found: Mapping[tuple[str, str, str], list[np.ndarray]],
    histograms: Mapping[tuple[str, str, str], BinCounts],
    median_bins: Mapping[tuple[str, str, str], list[tuple[int, int]]],
) -> dict[tuple[str, str, str], float]:
    """The exact medians: the middle value(s) picked from the values of their bins (the
    mean of two, as ``np.median``)."""
    out = {}
    for key, where in median_bins.items():
        h = histograms[key]
        x = np.concatenate(found[key]) if found[key] else np.empty(0)
        bins = score_bins(x, h.level)
        picks = [float(np.sort(x[bins == h.bins[i]])[k]) for i, k in where]
        out[key] = picks[0] if len(picks) == 1 else (picks[0] + picks[1]) / 2
    return out


def _site_transfer(
    counts: Mapping[tuple[str, str], Mapping[str, Mapping[str, int]]],
    thresholds: Mapping[tuple[str, str], float],
    calibration: Sequence[str],
    sites: Sequence[str],
    target: float,
) -> dict[str, dict[str, Any]]:
    """:func:`risk.evaluation.site_transfer` per model and reference from the counts."""
    out: dict[str, dict[str, Any]] = {}
    for (m, name), thr in thresholds.items():
        block: dict[str, Any] = {
            "calibration_sites": sorted(set(calibration) & set(sites)),
            "test_sites": sorted(set(sites) - set(calibration)),
            "target_tpr": target,
            "threshold": thr,
        }
        for part in ("calibration", "test"):
            c = counts[m, name][part]
            block[part] = {
                "positives": c["positives"],
                "tpr": c["kept_positives"] / c["positives"] if c["positives"] else math.nan,
                "kept_share": c["kept_agents"] / c["agents"] if c["agents"] else math.nan,
            }
        out.setdefault(m, {})[name] = block
    return out


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


def _composition(
    side: Mapping[str, Any],
    histograms: Mapping[tuple[str, str, str], BinCounts],
    medians: Mapping[tuple[str, str, str], float],
) -> dict[str, Any]:
    """The composition block (as the full evaluation's) from the sums and the medians."""
    out: dict[str, Any] = {}
    for name, labels in side.get("composition", {}).items():
        out[name] = {}
        for label, c in labels.items():
            block: dict[str, Any] = {"agent_frames": c["agent_frames"]}
            if c["agent_frames"]:
                block["median_time_in_scene_s"] = medians.get(
                    (name, label, "time_in_scene_s"), math.nan
                )
                block["share_first_2s"] = c["first_2s"] / c["agent_frames"]
                if side["speed"]:
                    block["median_speed_mps"] = medians.get((name, label, "speed_mps"), math.nan)
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
