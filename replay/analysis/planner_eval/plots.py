"""The plots of ``replay plan``: planning time against agent count, and the share of
changed plans per filter (matplotlib, imported only here: about 1 s).

The planning-time scatter draws a deterministic subsample of the rows where the plan
exists: at most :data:`~replay.analysis.planner_eval.streaming.PLOT_POINTS` per planner
and filter, every k-th row in key order (all of them below the cap), collected while
the summary passes over the part files (:class:`~replay.analysis.planner_eval.streaming.PlotPoints`)."""

from __future__ import annotations

import pathlib
from collections.abc import Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from outputs.atomic import atomic_write
from replay.analysis.planner_eval.open_loop import ALL_AGENTS
from replay.analysis.planner_eval.streaming import PlotPoints


def write_plots(
    points: Sequence[PlotPoints], summary: dict[str, Any], out_dir: pathlib.Path
) -> dict[str, pathlib.Path]:
    """``plan_time[_<planner>].png`` and ``plan_changed.png`` into ``out_dir`` (one
    time plot per planner when there are several)."""
    files = {}
    for scatter in points:
        name = scatter.planner
        file = "plan_time.png" if len(points) == 1 else f"plan_time_{name}.png"
        files[file] = _plan_time(scatter, out_dir / file)
    files["plan_changed.png"] = _changed(summary, out_dir / "plan_changed.png")
    return files


def _plan_time(points: PlotPoints, path: pathlib.Path) -> pathlib.Path:
    fig, ax = plt.subplots(figsize=(7.5, 4.5), dpi=110)
    for k, (name, others, total) in enumerate(points.filters):
        label = "all agents (plan)" if name == ALL_AGENTS else f"{name} (filter + plan)"
        ax.scatter(others + 0.15 * k, total, s=5, alpha=0.35, label=label)
    ax.set_xlabel("other agents in the frame")
    ax.set_ylabel("time per frame (ms)")
    ax.set_yscale("log")
    ax.set_title(f"Planning time, {points.planner}: all agents vs each filter")
    ax.legend(markerscale=3, fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    finally:
        plt.close(fig)


def _changed(summary: dict[str, Any], path: pathlib.Path) -> pathlib.Path:
    entries = {
        (planner, name): f
        for planner, entry in summary["planners"].items()
        for name, f in entry["filters"].items()
    }
    several = len(summary["planners"]) > 1
    names = [f"{p}: {n}" if several else n for p, n in entries]
    shares = [f["changed"]["share"] or 0.0 for f in entries.values()]
    cis = [f["changed"]["ci95"] or [np.nan, np.nan] for f in entries.values()]
    lo = [max(0.0, s - (c[0] if c[0] is not None else s)) for s, c in zip(shares, cis, strict=True)]
    hi = [max(0.0, (c[1] if c[1] is not None else s) - s) for s, c in zip(shares, cis, strict=True)]
    kept = [f["mean_kept"] for f in entries.values()]
    fig, ax = plt.subplots(figsize=(7.5, 0.6 * len(names) + 1.6), dpi=110)
    y = np.arange(len(names))
    ax.barh(y, [100 * s for s in shares], xerr=[[100 * v for v in lo], [100 * v for v in hi]],
            color="#c0504d", capsize=3)  # fmt: skip
    ax.set_yticks(y, [f"{n}\n({k:.1f} agents kept)" for n, k in zip(names, kept, strict=True)])
    ax.invert_yaxis()
    ax.set_xlabel("plans changed by the filter (% of comparable ego-frames, 95 % scene bootstrap)")
    ax.set_title("What each filter changes, " + ", ".join(summary["planners"]))
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    finally:
        plt.close(fig)
