"""Plots of the dataset statistics (matplotlib, Agg backend: no display needed).

- :func:`plot_roc`: the mean ROC curve of every model in one figure (the paper's Fig. 4),
  in the paper's colours (they are matplotlib's default cycle in the paper's model order),
  the ``tpr_0.95`` operating point marked, the degenerate situations in the caption;
- :func:`plot_errors`: mean false negatives and false positives per situation over the
  threshold of one model (the paper's Fig. 5);
- :func:`plot_robustness`: the std of TPR across situations over the mean TPR, every
  model (the paper's robustness figure depends on where on the curve it is taken);
- :func:`plot_funnel`: the cascade funnel with tier sizes (the paper's Fig. 6) beside the
  compute time of each stage and of survival analysis on all agents.

Each function takes the :class:`replay.analysis.stats.compute.DatasetStats` (or its parts) and a path,
writes one PNG atomically and returns the path.
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")  # before pyplot: files only, never a window

import matplotlib.pyplot as plt
import numpy as np
import polars as pl

from outputs.atomic import atomic_write
from replay.analysis.stats.compute import DatasetStats
from risk.registry import MODELS

#: Each model's colour, from the registry (``ModelSpec.color``: the paper's, Sec. V).
MODEL_COLORS: dict[str, str] = {name: spec.color for name, spec in MODELS.items()}
DPI = 110


def plot_roc(
    curves: pl.DataFrame,
    summary: Mapping[str, Any],
    path: str | os.PathLike[str],
    *,
    point: str = "tpr_0.95",
) -> pathlib.Path:
    """All models' mean ROC curves (``curves``: the ``roc`` table) in one figure."""
    fig, ax = plt.subplots(figsize=(7.0, 6.2), dpi=DPI)
    models = summary["models"]
    for name in curves["model"].unique(maintain_order=True).to_list():
        c = curves.filter(pl.col("model") == name)
        fpr, tpr = _closed_curve(c["mean_fpr"].to_numpy(), c["mean_tpr"].to_numpy())
        info = models[name]
        op = info["points"][point]
        sig = ", ".join(
            f"{_sigma(info, p)} @ {p.removeprefix('tpr_')}" for p in ("tpr_0.9", "tpr_0.95")
        )
        label = f"{_title(name)}: AUC {info['auc']:.3f}, σ(TPR) {sig}"
        color = MODEL_COLORS.get(name)
        ax.plot(fpr, tpr, color=color, lw=1.8, label=label, drawstyle="default")
        if op["mean_fpr"] is not None and math.isfinite(op["mean_fpr"]):
            ax.plot(
                [op["mean_fpr"]], [op["mean_tpr"]], "o", color=color, ms=5, mec="black", mew=0.5
            )
    ax.plot([0, 1], [0, 1], ls=":", color="0.6", lw=1, label="chance")
    ax.set(
        xlim=(-0.01, 1.01),
        ylim=(-0.01, 1.02),
        xlabel="mean false positive rate FPR (-)",
        ylabel="mean true positive rate TPR (-)",
    )
    ax.set_title("Importance filtering against the survival-analysis baseline (ROC)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=7.2, framealpha=0.9)
    fig.text(0.01, 0.005, _caption(summary, point), fontsize=7.5, va="bottom", wrap=True)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return _save(fig, path)


def _sigma(info: Mapping[str, Any], point: str) -> str:
    """σ at a point, or n/a when reaching that TPR keeps every agent (FPR 1)."""
    p = info["points"].get(point)
    if p is None:
        return "n/a"
    if p["mean_fpr"] is not None and p["mean_fpr"] >= 1 - 1e-9 and info["auc"] < 1:
        return "n/a"
    return _num(p["std_tpr"], ".3f")


def _closed_curve(fpr: np.ndarray, tpr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The curve sorted by FPR, from (0, 0) to (1, 1) as the AUC closes it."""
    order = np.lexsort((tpr, fpr))
    return np.r_[0.0, fpr[order], 1.0], np.r_[0.0, tpr[order], 1.0]


def _caption(summary: Mapping[str, Any], point: str) -> str:
    s = summary["situations"]
    base = summary["baseline"]
    return (
        f"{s['with_agents']} situations with agents ({s['total']} frames; "
        f"{s['without_agents']} without agents left out). Baseline: survival R_S >= "
        f"{_num(base['threshold'], 'g')}, {base['mean_important_per_situation']:.1f} important "
        f"agents per situation. TPR undefined (empty baseline) in {s['empty_baseline']}, FPR "
        f"undefined (every agent important) in {s['full_baseline']} situations: left out of "
        f"the respective means. Dots: {point} operating point. Curves closed to (0,0), (1,1)."
    )


def plot_errors(
    errors: pl.DataFrame,
    summary: Mapping[str, Any],
    path: str | os.PathLike[str],
) -> pathlib.Path:
    """Mean FN and FP per situation over the risk threshold of one model (log x axis)."""
    model = errors["model"][0]
    thr = errors["threshold"].to_numpy()
    ok = thr > 0  # a log axis cannot show threshold 0 (keep everything)
    fig, ax = plt.subplots(figsize=(7.0, 4.6), dpi=DPI)
    ax.step(
        thr[ok],
        errors["mean_false_negatives"].to_numpy()[ok],
        where="post",
        color="tab:red",
        lw=1.8,
        label="false negatives (important agents dropped)",
    )
    ax.step(
        thr[ok],
        errors["mean_false_positives"].to_numpy()[ok],
        where="post",
        color="tab:blue",
        lw=1.8,
        label="false positives (unimportant agents kept)",
    )
    ax.step(
        thr[ok],
        errors["mean_kept"].to_numpy()[ok],
        where="post",
        color="0.4",
        lw=1,
        ls="--",
        label="agents kept",
    )
    info = summary["models"][model]
    for name, style in (("tpr_0.95", ":"), ("tpr_1", "-.")):
        t = info["points"][name]["threshold"]
        if t is not None and t > 0:
            ax.axvline(
                t,
                color="black",
                ls=style,
                lw=1,
                label=f"threshold at mean TPR {name.removeprefix('tpr_')}: {t:.3g}",
            )
    ax.set_xscale("log")
    unit = MODELS[model].unit or "-"
    ax.set(
        xlabel=f"risk threshold of {_title(model)} ({unit}); agents with risk >= it are kept",
        ylabel="agents per situation (mean)",
    )
    ax.set_title(f"Filtering errors over the threshold: {_title(model)}")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    n = summary["situations"]["with_agents"]
    off_axis = ""
    if (~ok).any():
        zero = errors.filter(pl.col("threshold") <= 0).row(0, named=True)
        off_axis = (
            f" Threshold 0 (off the log axis) keeps {zero['mean_kept']:.1f} agents: FN "
            f"{zero['mean_false_negatives']:.2f}, FP {zero['mean_false_positives']:.1f}."
        )
    fig.text(
        0.01,
        0.005,
        f"Means over {n} situations with agents, against the survival baseline. Lower "
        "threshold: fewer false negatives, more false positives." + off_axis,
        fontsize=7.5,
        va="bottom",
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path)


def plot_robustness(
    curves: pl.DataFrame,
    summary: Mapping[str, Any],
    path: str | os.PathLike[str],
    *,
    paper_sigma: Mapping[str, float] | None = None,
) -> pathlib.Path:
    """Std of TPR across situations over the mean TPR (one line per model), with the
    paper's robustness values as dotted horizontal lines when given."""
    fig, ax = plt.subplots(figsize=(7.0, 4.8), dpi=DPI)
    for name in curves["model"].unique(maintain_order=True).to_list():
        c = curves.filter(pl.col("model") == name).sort("mean_tpr")
        ax.plot(
            c["mean_tpr"].to_numpy(),
            c["std_tpr"].to_numpy(),
            color=MODEL_COLORS.get(name),
            lw=1.4,
            label=_title(name),
        )
    for name, value in (paper_sigma or {}).items():
        ax.axhline(
            value,
            color=MODEL_COLORS.get(name),
            ls=":",
            lw=1.5,
            label=f"paper: σ {value:g}, {_title(name)}",
        )
    std = curves["std_tpr"].to_numpy() if curves.height else np.zeros(0)
    # No defined std at all (every situation degenerate, or one situation): a fixed axis.
    top = float(np.nanmax(std)) if np.isfinite(std).any() and np.nanmax(std) > 0 else 0.1
    ax.set(
        xlim=(0, 1.01),
        ylim=(0, 1.6 * top),  # headroom for the legend above the curves
        xlabel="mean true positive rate TPR (-)",
        ylabel="std of TPR across situations σ (-)",
    )
    ax.set_title("Robustness: spread of the TPR across situations along each ROC curve")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="upper left")
    n = summary["situations"]["tpr_defined"]
    fig.text(
        0.01,
        0.005,
        f"Over the {n} situations with a defined TPR. σ is 0 at TPR 1 and "
        "largest mid-curve, so models compare only at equal mean TPR.",
        fontsize=7.5,
        va="bottom",
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return _save(fig, path)


def plot_funnel(
    cascade: Mapping[str, Any], path: str | os.PathLike[str], *, title: str = ""
) -> pathlib.Path:
    """The cascade funnel (mean agents per situation after each stage, then the tiers)
    and, when times were measured, compute per stage vs survival on all agents."""
    timed = bool(cascade.get("timing_available"))
    fig, axes = plt.subplots(
        1,
        2 if timed else 1,
        figsize=(11.0 if timed else 7.0, 4.8),
        dpi=DPI,
        gridspec_kw={"width_ratios": [3, 2]} if timed else None,
    )
    ax = axes[0] if timed else axes
    _funnel_axes(ax, cascade)
    if timed:
        _compute_axes(axes[1], cascade)
    fig.suptitle(title or "Filter cascade: agents after each stage and planner tiers")
    n = cascade["situations"]
    fig.text(
        0.01,
        0.005,
        f"Means over {n} situations. FN: important agents (survival baseline on all agents, "
        f"{cascade['baseline_agent_frames']} agent-frames) dropped up to that stage, summed "
        "over situations; tiers: (min-max) per situation. Compute: medians per situation, "
        "stages stacked; the ratio compares the median totals.",
        fontsize=7.5,
        va="bottom",
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.96))
    return _save(fig, path)


def _funnel_axes(ax: Any, cascade: Mapping[str, Any]) -> None:
    labels = ["all other agents"]
    values = [cascade["mean_others"]]
    colors = ["0.55"]
    notes = [""]
    for s in cascade["stages"]:
        labels.append(_title(s["model"]))
        values.append(s["mean_kept"])
        colors.append(MODEL_COLORS.get(s["model"], "tab:cyan"))
        notes.append(f"FN {s['false_negatives']}")
    tier_colors = ["#4c72b0", "#55a868", "#c44e52", "#8172b2"]
    for k, t in enumerate(cascade["tiers"]):
        labels.append(f"tier: {t['name']}")
        values.append(t["mean_agents"])
        colors.append(tier_colors[k % len(tier_colors)])
        notes.append(f"{t['min_agents']}-{t['max_agents']}")
    y = np.arange(len(labels))[::-1]
    ax.barh(y, values, color=colors, edgecolor="black", lw=0.5)
    top = max(values) if values else 1.0
    for yi, v, note in zip(y, values, notes, strict=True):
        ax.text(
            v + 0.01 * top,
            yi,
            f"{v:.1f}" + (f"  ({note})" if note else ""),
            va="center",
            fontsize=8,
        )
    ax.set_yticks(y, labels, fontsize=8.5)
    ax.set_xlim(0, top * 1.3)
    ax.set_xlabel("agents per situation (mean)")
    ax.set_title("Agents after each stage, then the planner tiers", fontsize=9)
    ax.grid(axis="x", alpha=0.3)


def _compute_axes(ax: Any, cascade: Mapping[str, Any]) -> None:
    # Medians per situation: the machine is shared, and preempted frames make means jumpy.
    comp = cascade["compute"]
    labels = [*(_title(s["model"]) for s in cascade["stages"]), "survival sort (survivors)"]
    values = [
        *(1e3 * s["median_time_s"] for s in cascade["stages"]),
        1e3 * comp["median_sort_time_s"],
    ]
    left = np.cumsum([0.0, *values[:-1]])
    colors = [*(MODEL_COLORS.get(s["model"], "tab:cyan") for s in cascade["stages"]), "tab:olive"]
    for lab, v, lft, col in zip(labels, values, left, colors, strict=True):
        ax.barh(1, v, left=lft, color=col, edgecolor="black", lw=0.5, label=f"{lab}: {v:.2f} ms")
    ref = 1e3 * comp["median_survival_all_time_s"]
    ax.barh(
        0,
        ref,
        color="tab:olive",
        hatch="//",
        edgecolor="black",
        lw=0.5,
        label=f"survival on all agents: {ref:.2f} ms",
    )
    ratio = comp["median_cascade_time_s"] / comp["median_survival_all_time_s"]
    ax.set_yticks([1, 0], [f"cascade\n({ratio:.2f}x)", "survival\non all"], fontsize=8.5)
    ax.set_ylim(-0.6, 2.9)  # room above the bars for the legend
    ax.set_xlim(0, max(left[-1] + values[-1], ref) * 1.05)
    ax.set_xlabel("ms per situation (median wall time)")
    ax.set_title("Compute: cascade vs survival analysis on all agents", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", ncol=1, framealpha=0.9)
    ax.grid(axis="x", alpha=0.3)


def _title(model: str) -> str:
    spec = MODELS.get(model)
    return spec.title if spec else model


def _num(value: Any, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return format(value, fmt)


def _save(fig: Any, path: str | os.PathLike[str]) -> pathlib.Path:
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    finally:
        plt.close(fig)


def plot_all(
    stats: DatasetStats,
    out_dir: str | os.PathLike[str],
    *,
    paper_sigma: Mapping[str, float] | None = None,
) -> dict[str, pathlib.Path]:
    """The standard plots of a :class:`replay.analysis.stats.compute.DatasetStats` into ``out_dir``."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = stats.summary
    return {
        "roc.png": plot_roc(stats.roc, summary, out / "roc.png"),
        "robustness.png": plot_robustness(
            stats.roc, summary, out / "robustness.png", paper_sigma=paper_sigma
        ),
        "errors.png": plot_errors(stats.errors, summary, out / "errors.png"),
        "cascade_funnel.png": plot_funnel(summary["cascade"], out / "cascade_funnel.png"),
    }


__all__: Sequence[str] = (
    "MODEL_COLORS",
    "plot_all",
    "plot_errors",
    "plot_funnel",
    "plot_robustness",
    "plot_roc",
)
