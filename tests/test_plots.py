"""Plots (replay.analysis.stats.plots): the files exist and the figures say what they show."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

import replay.analysis.stats.plots as plots
from replay.analysis.stats import compute_stats, frames_from_agents

MODELS = ("current_distance", "path_distance", "survival")


@pytest.fixture(scope="module")
def stats():
    rng = np.random.default_rng(1)
    n_sit, n_agents = 12, 15
    survival = 10.0 ** rng.uniform(-40, -5, size=n_sit * n_agents)
    base = survival >= 1e-25
    df = pl.DataFrame(
        {
            "scene": ["s"] * survival.size,
            "frame": np.repeat(np.arange(n_sit), n_agents),
            "t_s": np.repeat(np.arange(n_sit) * 0.1, n_agents),
            "agent_id": np.tile(np.arange(n_agents), n_sit),
            "risk_current_distance": rng.uniform(0.01, 1, survival.size),
            "risk_path_distance": np.clip(base * 0.5 + rng.uniform(0, 0.5, survival.size), 0, 1),
            "risk_survival": survival,
            "kept_path_distance": base | (rng.random(survival.size) < 0.5),
            "tier": pl.Series([None] * survival.size, dtype=pl.Enum(["behavior"])),
            "baseline": base,
        }
    )
    frames = frames_from_agents(df, ["path_distance"], ["behavior"])
    frames = frames.with_columns(
        pl.lit(0.002).alias("time_path_distance_s"),
        pl.lit(0.001).alias("sort_time_s"),
        pl.lit(0.004).alias("survival_all_time_s"),
    )
    return compute_stats(df, frames, errors_model="path_distance", tier_names=["behavior"])


@pytest.fixture
def captured(monkeypatch):
    """The figures the plot functions save (they are still written)."""
    figures = []
    save = plots._save

    def keep(fig, path):
        figures.append(fig)
        return save(fig, path)

    monkeypatch.setattr(plots, "_save", keep)
    return figures


def is_png(path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000


def test_plot_all_writes_every_png(stats, tmp_path):
    files = plots.plot_all(stats, tmp_path, paper_sigma={"path_distance": 0.04})
    assert set(files) == {"roc.png", "robustness.png", "errors.png", "cascade_funnel.png"}
    assert all(is_png(p) for p in files.values())
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp files


def test_roc_has_one_labelled_curve_per_model(stats, tmp_path, captured):
    plots.plot_roc(stats.roc, stats.summary, tmp_path / "roc.png")
    ax = captured[0].axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    for m in MODELS:
        auc = stats.summary["models"][m]["auc"]
        assert any(f"AUC {auc:.3f}" in lab for lab in labels)
    assert "FPR" in ax.get_xlabel() and "TPR" in ax.get_ylabel()
    colors = {line.get_color() for line in ax.get_lines()}
    assert {plots.MODEL_COLORS[m] for m in MODELS} <= colors
    caption = " ".join(t.get_text() for t in captured[0].texts)
    assert "TPR undefined" in caption and "FPR" in caption


def test_errors_plot_shows_fn_and_fp_over_a_log_threshold(stats, tmp_path, captured):
    plots.plot_errors(stats.errors, stats.summary, tmp_path / "e.png")
    ax = captured[0].axes[0]
    assert ax.get_xscale() == "log"
    labels = " ".join(t.get_text() for t in ax.get_legend().get_texts())
    assert "false negatives" in labels and "false positives" in labels
    assert "threshold" in ax.get_xlabel()


def test_funnel_without_times_has_one_panel(stats, tmp_path, captured):
    cascade = {**stats.summary["cascade"], "timing_available": False}
    cascade.pop("compute")
    plots.plot_funnel(cascade, tmp_path / "f.png")
    assert len(captured[0].axes) == 1
    plots.plot_funnel(stats.summary["cascade"], tmp_path / "g.png")
    assert len(captured[1].axes) == 2
    ticks = [t.get_text() for t in captured[1].axes[0].get_yticklabels()]
    assert ticks[0] == "all other agents" and "tier: behavior" in ticks
