"""The files and the text of ``replay evaluate``: ``summary.json``, the tables (ROC
points, miss rates, budgets, the positives), the plots, and the end-of-run summary."""

from __future__ import annotations

import json
import math
import os
import pathlib
from collections.abc import Mapping
from typing import Any

import numpy as np
import polars as pl

from outputs.atomic import atomic_output
from replay.analysis.evaluation.corpus import (
    HEADLINE_THRESHOLD,
    REFERENCES,
)
from replay.analysis.evaluation.plots import plot_budgets, plot_evaluation
from risk.hindsight import HindsightSettings


def positives_table(
    agents: pl.DataFrame, datasets: Mapping[str, str] | None = None
) -> pl.DataFrame:
    """One row per distinct agent that really came close (scene, ego, agent): its kind,
    dataset, first and last frame labelled positive, least gap and PET, and the cascade
    stage that dropped it at a positive frame (null: kept at every positive frame)."""
    pos = agents.filter(pl.col("truth_label").fill_null(False))
    if pos.height == 0:
        return pl.DataFrame()
    dropped = (
        pl.col("dropped_by").cast(pl.String).drop_nulls().first()
        if "dropped_by" in pos.columns
        else pl.lit(None, dtype=pl.String)
    )
    out = (
        pos.group_by("scene", "ego_id", "agent_id", maintain_order=True)
        .agg(
            pl.col("kind").cast(pl.String).first(),
            pl.col("frame").min().alias("first_frame"),
            pl.col("frame").max().alias("last_frame"),
            pl.len().alias("positive_frames"),
            pl.col("truth_gap_m").min().alias("min_gap_m"),
            pl.col("truth_pet_s").min().alias("min_pet_s"),
            dropped.alias("dropped_by"),
        )
        .sort("scene", "ego_id", "agent_id")
    )
    ds = dict(datasets or {})
    return out.with_columns(
        pl.col("scene")
        .replace_strict(ds, default="unknown", return_dtype=pl.String)
        .alias("dataset")
    )


def budget_table(summary: Mapping[str, Any]) -> pl.DataFrame:
    """The budgets as rows: reference x rule x budget (K, radius or the cascade's fixed
    set), with the mean kept agents per situation, the recall and its interval."""
    rows = []
    for ref, block in summary.get("budgets", {}).items():
        for r in block:
            ci = r.get("ci", [None, None])
            rows.append(
                {
                    "reference": ref, "rule": r["rule"], "kind": r["kind"], "k": r["k"],
                    "radius_m": r["radius_m"], "mean_kept": r["mean_kept"],
                    "positives": r["positives"], "kept_positives": r["kept_positives"],
                    "recall": r["value"], "ci_lo": ci[0], "ci_hi": ci[1],
                }
            )  # fmt: skip
    schema = {
        "reference": pl.String, "rule": pl.String, "kind": pl.String, "k": pl.Int64,
        "radius_m": pl.Float64, "mean_kept": pl.Float64, "positives": pl.Int64,
        "kept_positives": pl.Int64, "recall": pl.Float64, "ci_lo": pl.Float64,
        "ci_hi": pl.Float64,
    }  # fmt: skip
    return pl.DataFrame(rows, schema=schema)


def miss_table(summary: Mapping[str, Any]) -> pl.DataFrame:
    """Miss rates as rows: group (``all`` or grouping=value) x model x reference x
    threshold, with the interval, missed agent-frames and agents, kept share."""
    rows = []

    def add(group: str, block: Mapping[str, Any]) -> None:
        for model, per_ref in block["models"].items():
            for ref, ev in per_ref.items():
                for thr, mr in ev["miss_rate"].items():
                    ci = mr.get("ci", [None, None])
                    rows.append(
                        {
                            "group": group, "model": model, "reference": ref,
                            "operating_threshold": thr, "threshold": mr["threshold"],
                            "positives": ev["positives"], "miss_rate": mr["value"],
                            "ci_lo": ci[0], "ci_hi": ci[1],
                            "missed_agent_frames": mr["missed_agent_frames"],
                            "missed_agents": mr["missed_agents"], "kept_share": mr["kept_share"],
                            "auc": ev["auc"]["value"],
                        }
                    )  # fmt: skip

    add("all", summary)
    for grouping, blocks in summary.get("by", {}).items():
        for value, block in blocks.items():
            add(f"{grouping}={value}", block)
    return pl.DataFrame(rows, infer_schema_length=None)


def write_evaluation(
    summary: Mapping[str, Any],
    out_dir: str | os.PathLike[str],
    *,
    roc: pl.DataFrame,
    positives: pl.DataFrame,
    plots: bool = True,
) -> dict[str, pathlib.Path]:
    """``summary.json``, the tables (``roc`` and ``positives`` as
    :func:`replay.analysis.evaluation.streaming.evaluate_parts` made them, ``miss_rates``
    and ``budgets`` from the summary; Parquet and CSV) and the plots into ``out_dir``,
    each file atomically. Returns name -> path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    tables = {
        "roc": roc,
        "miss_rates": miss_table(summary),
        "positives": positives,
        "budgets": budget_table(summary),
    }
    for name, df in tables.items():
        for suffix in (".parquet", ".csv"):
            path = out / f"{name}{suffix}"
            with atomic_output(path) as tmp:
                if suffix == ".csv":
                    df.write_csv(tmp)
                else:
                    df.write_parquet(tmp, compression="zstd")
            written[path.name] = path
    if plots:
        written.update(plot_evaluation(summary, tables["roc"], out, threshold=HEADLINE_THRESHOLD))
        written.update(plot_budgets(tables["budgets"], out))
    path = out / "summary.json"
    text = json.dumps(
        _jsonable({**summary, "files": sorted([*written, "summary.json"])}),
        indent=2,
        allow_nan=False,
    )
    with atomic_output(path) as tmp:
        pathlib.Path(tmp).write_text(text + "\n", encoding="utf-8")
    written[path.name] = path
    return written


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


# ---------------------------------------------------------------------- text
#: How these AUCs are computed, and why ``replay stats``' differ (issue 31).
EVALUATION_AUC_NOTE = (
    "AUC: one ROC curve pooled over every agent-frame of every scene; 'replay stats'"
    " averages per-situation curves (the paper's measure), so its AUCs differ"
)


def auc_bound_note(summary: Mapping[str, Any]) -> str:
    """The largest error bound of the summary's AUCs (binned on a fixed score grid,
    :mod:`replay.analysis.evaluation.streaming`), as a sentence; empty without one."""
    bounds = [
        float(block["auc"]["error_bound"])
        for per_ref in summary.get("models", {}).values()
        for block in per_ref.values()
        if isinstance(block.get("auc", {}).get("error_bound"), float)
        and math.isfinite(block["auc"]["error_bound"])
    ]
    if not bounds:
        return ""
    return (
        f"AUC ± {max(bounds):.1e} bound: thresholds on a fixed score grid summed over scenes; "
        "each AUC lies within its stated error_bound (summary.json) of the "
        "every-distinct-score value, the largest shown here"
    )


def format_evaluation(summary: Mapping[str, Any]) -> str:
    """The end-of-run text: counts per reference, each model's AUC against every
    reference with intervals, its miss rate against hindsight at the headline threshold,
    the references missing or without positives, and the planner/hindsight agreement."""
    ref = summary["references"]
    names = list(summary.get("reference_names", [n for n in REFERENCES if n in ref]))
    level = summary["bootstrap"]["level"]
    h, s = ref["hindsight"], ref["survival"]
    windows = summary["settings"].get("hindsight_windows", "any")
    lines = [
        f"{summary['scenes']} scenes, {summary['egos']} egos, {summary['situations']} "
        f"situations, {h['agent_frames']} agent-frames",
        f"Hindsight ({windows} windows): {h['positive_agent_frames']} positive agent-frames "
        f"({h['positive_agents']} distinct agents, in {h['scenes_with_positive']} scenes), "
        f"{h['negative_agent_frames']} negative, {h['unknown_agent_frames']} unknown (left out)",
        f"Survival baseline: {s['positive_agent_frames']} important agent-frames "
        f"({s['positive_agents']} distinct agents)",
    ]
    for name in names:
        if name in ("hindsight", "survival"):
            continue
        c = ref[name]
        lines.append(
            f"{name}: {c['positive_agent_frames']} positive, {c['negative_agent_frames']} "
            f"negative, {c['unknown_agent_frames']} unknown agent-frames"
        )
    for name, why in {
        **summary.get("references_missing", {}),
        **summary.get("references_without_positives", {}),
    }.items():
        lines.append(f"Reference {name}: {why}")
    short = summary.get("scenes_shorter_than_horizon") or []
    if short:
        hz = (summary.get("hindsight") or {}).get("horizon_s", HindsightSettings().horizon_s)
        shown = ", ".join(short[:5]) + (", ..." if len(short) > 5 else "")
        lines.append(
            f"Note: {len(short)} scene(s) shorter than the {hz:g} s horizon have no complete "
            f"window: {shown}"
        )
    pct = f"{100 * level:g} %"
    lines.append(EVALUATION_AUC_NOTE)
    if note := auc_bound_note(summary):
        lines.append(note)
    lines.append(f"AUC per reference [{pct} scene-bootstrap interval]:")
    lines.append(f"  {'model':<22}" + "".join(f"{n:>30}" for n in names))
    for model, per_ref in summary["models"].items():
        cells = [
            f"{_f(per_ref[n]['auc']['value'])} {_ci(per_ref[n]['auc'])}" if n in per_ref else "n/a"
            for n in names
        ]
        lines.append(f"  {model:<22}" + "".join(f"{c:>30}" for c in cells))
    planner = summary.get("agreement", {}).get("planner")
    if planner and "hindsight" in planner:
        b = planner["hindsight"]
        lines.append(
            f"Planner-important: {planner['important']['agent_frames']} agent-frames; against "
            f"hindsight {b['positive']['agent_frames']} positive, {b['negative']['agent_frames']} "
            f"negative ({b['negative_yielded']['agent_frames']} with the ego yielding), "
            f"{b['unknown']['agent_frames']} unknown ({b['unknown_yielded']['agent_frames']} "
            "with the ego yielding)"
        )
    cascade = summary.get("cascade", {}).get("hindsight")
    if cascade:
        parts = ", ".join(
            f"{st['stage']} {st['missed_agent_frames']} ({st['missed_agents']} agents)"
            for st in cascade
        )
        lines.append(f"Cascade misses against hindsight (cumulative agent-frames): {parts}")
    return "\n".join(lines)


def _f(value: Any) -> str:
    return (
        "n/a"
        if value is None or (isinstance(value, float) and not math.isfinite(value))
        else f"{value:.3f}"
    )


def _ci(block: Mapping[str, Any]) -> str:
    ci = block.get("ci")
    if not ci or ci[0] is None or not math.isfinite(ci[0]):
        return ""
    return f"[{ci[0]:.3f}, {ci[1]:.3f}]"
