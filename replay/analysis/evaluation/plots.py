"""Plots of the outcome evaluation (matplotlib, Agg backend): the pooled ROC of every
model against the hindsight truth, and the miss rate against hindsight per group."""

from __future__ import annotations

import pathlib
from collections.abc import Mapping
from typing import Any

import matplotlib

matplotlib.use("Agg")  # before pyplot: files only, never a window

import matplotlib.pyplot as plt
import numpy as np
import polars as pl

from outputs.atomic import atomic_output
from replay.analysis.stats.plots import DPI, MODEL_COLORS


def plot_evaluation(
    summary: Mapping[str, Any], roc: pl.DataFrame, out_dir: pathlib.Path, *, threshold: str
) -> dict[str, pathlib.Path]:
    """``roc_hindsight.png`` and one ``miss_rate_by_<grouping>.png`` per grouping (miss
    rates at the operating threshold named ``threshold``); nothing when hindsight has no
    positive."""
    if "hindsight" not in summary.get("reference_names", ["hindsight"]):
        return {}
    written = {"roc_hindsight.png": _roc(summary, roc, out_dir / "roc_hindsight.png")}
    for grouping, blocks in summary.get("by", {}).items():
        name = f"miss_rate_by_{grouping}.png"
        written[name] = _miss(summary, grouping, blocks, threshold, out_dir / name)
    return written


def _save(fig: Any, path: pathlib.Path) -> pathlib.Path:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def _roc(summary: Mapping[str, Any], roc: pl.DataFrame, path: pathlib.Path) -> pathlib.Path:
    fig, ax = plt.subplots(figsize=(7.0, 6.2), dpi=DPI)
    h = summary["references"]["hindsight"]
    for model, per_ref in summary["models"].items():
        curve = roc.filter((pl.col("model") == model) & (pl.col("reference") == "hindsight"))
        if curve.height == 0:
            continue
        auc = per_ref["hindsight"]["auc"]
        ci = auc.get("ci")
        label = f"{model} AUC {auc['value']:.3f}" + (
            f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci and ci[0] is not None else ""
        )
        ax.plot(
            np.r_[0.0, curve["fpr"].to_numpy()[::-1], 1.0],
            np.r_[0.0, curve["tpr"].to_numpy()[::-1], 1.0],
            color=MODEL_COLORS.get(model), label=label, lw=1.4,
        )  # fmt: skip
    ax.plot([0, 1], [0, 1], color="0.8", lw=0.8, ls="--")
    ax.set_xlabel("FPR (pooled agent-frames)")
    ax.set_ylabel("TPR: share of hindsight positives kept")
    ax.set_title("ROC against what really happened")
    ax.legend(fontsize=7, loc="lower right")
    fig.text(
        0.01, 0.005,
        f"{h['positive_agent_frames']} positive agent-frames ({h['positive_agents']} agents), "
        f"{h['negative_agent_frames']} negative, {h['unknown_agent_frames']} censored left out; "
        f"intervals: scene bootstrap",
        fontsize=7,
    )  # fmt: skip
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    return _save(fig, path)


def _miss(
    summary: Mapping[str, Any],
    grouping: str,
    blocks: Mapping[str, Any],
    threshold: str,
    path: pathlib.Path,
) -> pathlib.Path:
    groups = list(blocks)
    models = list(summary["models"])
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(groups) + 3), 4.8), dpi=DPI)
    width = 0.8 / max(len(models), 1)
    x = np.arange(len(groups))
    for k, model in enumerate(models):
        vals, lo, hi = [], [], []
        for g in groups:
            mr = blocks[g]["models"][model]["hindsight"]["miss_rate"].get(threshold, {})
            v = mr.get("value")
            ci = mr.get("ci") or [None, None]
            v = np.nan if v is None else v
            vals.append(v)
            lo.append(0.0 if ci[0] is None or np.isnan(v) else max(v - ci[0], 0.0))
            hi.append(0.0 if ci[1] is None or np.isnan(v) else max(ci[1] - v, 0.0))
        ax.bar(
            x + (k - (len(models) - 1) / 2) * width, vals, width, yerr=[lo, hi],
            color=MODEL_COLORS.get(model), label=model, error_kw={"lw": 0.7},
        )  # fmt: skip
    counts = [blocks[g]["references"]["hindsight"]["positive_agents"] for g in groups]
    ax.set_xticks(x, [f"{g}\n({c} agents)" for g, c in zip(groups, counts, strict=True)])
    ax.set_ylabel("miss rate against hindsight")
    ax.set_title(f"Hindsight positives dropped, by {grouping} (threshold {threshold})")
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    return _save(fig, path)


def plot_budgets(budgets: pl.DataFrame, out_dir: pathlib.Path) -> dict[str, pathlib.Path]:
    """``budget_<reference>.png`` per reference: the share of its positives kept against
    the agents kept per situation, one line per top-K rule (each model, nearest-K), the
    radius rules as a dashed line at their mean kept counts, the cascade as a star."""
    written: dict[str, pathlib.Path] = {}
    if budgets.height == 0:
        return written
    for ref in dict.fromkeys(budgets["reference"].to_list()):
        sub = budgets.filter(pl.col("reference") == ref)
        fig, ax = plt.subplots(figsize=(7.5, 5.6), dpi=DPI)
        for i, rule in enumerate(dict.fromkeys(sub["rule"].to_list())):
            r = sub.filter(pl.col("rule") == rule).sort("mean_kept")
            x = r["mean_kept"].to_numpy()
            y = r["recall"].fill_null(np.nan).to_numpy()
            lo = np.nan_to_num(y - r["ci_lo"].fill_null(np.nan).to_numpy())
            hi = np.nan_to_num(r["ci_hi"].fill_null(np.nan).to_numpy() - y)
            kind = r["kind"][0]
            if kind == "fixed":
                ax.errorbar(x, y, yerr=[lo, hi], fmt="*", ms=12, color="black",
                            label=f"{rule} (mean kept {x[0]:.1f})")  # fmt: skip
                continue
            style = {"radius": ("--", "0.3"), "top_k": ("-", None)}[kind]
            color = style[1] or MODEL_COLORS.get(rule, "0.5" if rule == "nearest" else f"C{i}")
            ls = ":" if rule == "nearest" else style[0]
            ax.errorbar(x, y, yerr=[lo, hi], ls=ls, marker="o", ms=3, lw=1.2, capsize=2,
                        color=color, label=f"{rule} (R)" if kind == "radius" else rule)  # fmt: skip
        ax.set_xscale("log", base=2)
        ax.set_xlabel("agents kept per situation (K; mean for radius and cascade)")
        ax.set_ylabel(f"share of {ref} positives kept")
        n_pos = int(sub["positives"][0])
        ax.set_title(f"Budgets against {ref} ({n_pos} positive agent-frames)")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2, loc="lower right")
        fig.tight_layout()
        name = f"budget_{ref}.png"
        written[name] = _save(fig, out_dir / name)
    return written


def plot_sensitivity(rows: pl.DataFrame, path: pathlib.Path) -> pathlib.Path:
    """``sensitivity.png``: each model's AUC (with its interval) per sweep variant, one
    panel per reference; the defaults' value as a dotted line."""
    variants = rows.select("group", "variant").unique(maintain_order=True).rows()
    refs = list(dict.fromkeys(rows["reference"].to_list()))
    fig, axes = plt.subplots(len(refs), 1, figsize=(12, 4.2 * len(refs)), dpi=DPI, squeeze=False)
    x = np.arange(len(variants))
    models = list(dict.fromkeys(rows["model"].to_list()))
    for ax, ref in zip(axes[:, 0], refs, strict=True):
        sub = rows.filter(pl.col("reference") == ref)
        for i, m in enumerate(models):
            if ref == "survival" and m == "survival":
                continue
            by = {
                (r["group"], r["variant"]): r
                for r in sub.filter(pl.col("model") == m).iter_rows(named=True)
            }
            y = np.array([by[v]["auc"] if v in by else np.nan for v in variants], dtype=float)
            lo = np.array([by[v]["ci_lo"] if v in by else np.nan for v in variants], dtype=float)
            hi = np.array([by[v]["ci_hi"] if v in by else np.nan for v in variants], dtype=float)
            color = MODEL_COLORS.get(m, f"C{i}")
            off = (i - len(models) / 2) * 0.04
            # A bootstrap interval need not contain its point estimate (few scenes, a
            # skewed statistic): matplotlib refuses negative error bars, so clip at 0.
            below = np.clip(np.nan_to_num(y - lo), 0.0, None)
            above = np.clip(np.nan_to_num(hi - y), 0.0, None)
            ax.errorbar(x + off, y, yerr=[below, above], fmt="o", ms=3, lw=0.8, color=color,
                        label=m)  # fmt: skip
            ax.axhline(y[0], color=color, lw=0.5, ls=":")
        ax.set_xticks(x, [f"{g}\n{v}" for g, v in variants], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(f"AUC against {ref}")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, ncol=3, loc="lower left")
    fig.tight_layout()
    return _save(fig, path)
