"""``replay stats``' streamed statistics (replay.analysis.stats.streaming, risk.sweep_counts)
against the full-rows computation (compute_stats, the oracle) on hand-made part files:
exact figures equal, binned ones within their stated bound, the order of the parts
irrelevant."""

from __future__ import annotations

import json
import math
import pathlib
import random

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from polars.testing import assert_frame_equal

from replay.analysis.stats import StatsError, compute_stats, frames_from_agents
from replay.analysis.stats.files import write_stats
from replay.analysis.stats.streaming import StatsPart, stream_stats
from replay.core.stats_sink import time_columns
from risk.metrics import exact_sweep
from risk.sweep_counts import sweep_rows

MODELS = ("current_distance", "gaussian", "headway_2d")
STAGES = ("current_distance",)
TIERS = ("near", "far")


def scene_tables(
    rng: np.random.Generator, name: str, n_frames: int, values: np.ndarray | None, timed: bool
) -> tuple[pl.DataFrame, pl.DataFrame]:
    """One scene's agents table (two egos, 0-5 agents per situation; scores drawn from
    ``values`` when given, so that ties and shared bins occur) and its frames table."""
    rows: dict[str, list] = {k: [] for k in ("scene", "ego_id", "frame", "t_s", "agent_id",
                                             "baseline", "tier")}  # fmt: skip
    scores: dict[str, list[float]] = {m: [] for m in MODELS}
    for ego in (0, 1):
        for frame in range(n_frames):
            for agent in range(int(rng.integers(0, 6))):
                rows["scene"].append(name)
                rows["ego_id"].append(ego)
                rows["frame"].append(frame)
                rows["t_s"].append(0.1 * frame)
                rows["agent_id"].append(agent + 10)
                rows["baseline"].append(bool(rng.random() < 0.4))
                rows["tier"].append("near" if rng.random() < 0.5 else "far")
                for m in MODELS:
                    x = float(rng.choice(values)) if values is not None else float(rng.random())
                    scores[m].append(x)
    agents = pl.DataFrame(
        {**rows, **{f"risk_{m}": scores[m] for m in MODELS}},
        schema_overrides={"ego_id": pl.Int64, "frame": pl.Int64, "agent_id": pl.Int64,
                          "baseline": pl.Boolean, "t_s": pl.Float64, "scene": pl.String,
                          "tier": pl.String},
    )  # fmt: skip
    agents = agents.with_columns(
        (pl.col("risk_current_distance") > 0.3).alias("kept_current_distance")
    )
    frames = frames_from_agents(agents, STAGES, TIERS)
    if timed:  # compute times, as replayed frames have
        n = frames.height
        frames = frames.with_columns(
            pl.Series(c, rng.random(n) * 1e-3) for c in time_columns(STAGES)
        )
    return agents, frames


def write_parts(
    tmp: pathlib.Path, tables: list[tuple[pl.DataFrame, pl.DataFrame]]
) -> list[StatsPart]:
    tmp.mkdir(parents=True, exist_ok=True)
    parts = []
    for k, (agents, frames) in enumerate(tables):
        a, f = tmp / f"agents-{k}.parquet", tmp / f"frames-{k}.parquet"
        agents.write_parquet(a)
        frames.write_parquet(f)
        parts.append(StatsPart(a, f))
    return parts


def oracle(tables: list[tuple[pl.DataFrame, pl.DataFrame]]):
    agents = pl.concat([a for a, _ in tables], how="diagonal_relaxed")
    frames = pl.concat([f for _, f in tables], how="diagonal_relaxed")
    return compute_stats(agents, frames, stage_names=STAGES, tier_names=TIERS)


def streamed(parts: list[StatsPart], scratch: pathlib.Path, **kw):
    scratch.mkdir(parents=True, exist_ok=True)
    return stream_stats(parts, scratch, errors_model="headway_2d", stage_names=STAGES,
                        tier_names=TIERS, **kw)  # fmt: skip


def pieces(s) -> pl.DataFrame:
    """The streamed per-frame table, read back from its pieces."""
    return pl.concat([pl.read_parquet(p) for p in s.per_frame_pieces], how="diagonal_relaxed")


#: Figures of the summary that are binned (see the module docstring of streaming).
BINNED = {"auc", "n_thresholds", "std_tpr_curve", "std_tpr_high_tpr", "auc_error_bound",
          "mixed_bins"}  # fmt: skip


def close(a, b, path=""):
    """Equal up to the rounding of sums taken in another order."""
    if isinstance(a, dict):
        assert set(a) <= set(b), path
        for k in a:
            close(a[k], b[k], f"{path}/{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            close(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=1e-9, abs=1e-12), path
    else:
        assert a == b, path


def youden_tie(curve, exact: dict, got: dict) -> None:
    """The streamed Youden threshold is the highest whose mean TPR - mean FPR (on the
    exact curve) is within 1e-9 of the largest; the full-rows one is the highest of the
    exactly largest, which rounding can put lower (J = -5.6e-17 against 0 at a tie). When
    the two differ, the streamed one must be the higher, and tied: then its point's
    figures are those of another threshold and are not compared."""
    a, b = exact["points"]["youden"], got["points"]["youden"]
    if a["threshold"] == b["threshold"]:
        return
    j = curve.mean_tpr - curve.mean_fpr
    at = int(np.searchsorted(curve.thresholds, b["threshold"]))
    assert curve.thresholds[at] == b["threshold"]
    assert b["threshold"] > a["threshold"]
    assert j[at] >= np.nanmax(j) - 1e-9
    b.update({k: a[k] for k in a})  # the rest compared as equal


def check_against_oracle(o, s) -> None:
    """Exact figures equal; binned ones within their bound; the binned curve's points
    are points of the exact curve."""
    for key in ("situations", "baseline", "cascade", "errors_model"):
        close(o.summary[key], s.summary[key], key)
    for m, exact in o.summary["models"].items():
        got = s.summary["models"][m]
        youden_tie(o.models[m].roc, exact, got)
        close({k: v for k, v in exact.items() if k not in BINNED},
              {k: v for k, v in got.items() if k not in BINNED}, m)  # fmt: skip
        assert abs(got["auc"] - exact["auc"]) <= got["auc_error_bound"] + 1e-12, m
        e, b = o.models[m].roc, s.models[m].roc
        at = np.searchsorted(e.thresholds, b.thresholds)
        np.testing.assert_array_equal(e.thresholds[at], b.thresholds)
        for f in ("mean_tpr", "mean_fpr", "std_tpr", "mean_kept"):
            np.testing.assert_allclose(getattr(b, f), getattr(e, f)[at], rtol=1e-9, atol=1e-12)
    assert s.per_frame.height == 0 and s.per_frame.columns == o.per_frame.columns
    per_frame = pieces(s)
    assert_frame_equal(o.per_frame, per_frame, check_dtypes=False, rel_tol=1e-9)
    assert_frame_equal(o.per_scene, s.per_scene, check_dtypes=False, rel_tol=1e-9)
    assert_frame_equal(o.funnel, s.funnel, check_dtypes=False, rel_tol=1e-9)
    at = np.searchsorted(o.errors["threshold"].to_numpy(), s.errors["threshold"].to_numpy())
    assert_frame_equal(o.errors[at], s.errors, check_dtypes=False, rel_tol=1e-9)


def test_sweep_weights_by_hand():
    # one situation: scores 0.9 (+), 0.5 (-), 0.1 (+); another: 0.8 (-), 0.3 (+)
    rows = sweep_rows(np.array([0.9, 0.5, 0.1, 0.8, 0.3]), np.array([0, 0, 0, 1, 1]),
                      np.array([True, False, True, False, True]))  # fmt: skip
    np.testing.assert_allclose(rows.tpr, [0.5, 0, 0.5, 0, 1])
    np.testing.assert_allclose(rows.fpr, [0, 1, 0, 1, 0])
    # TPR^2 of situation 0 goes 0 -> 1/4 -> 1: increments 1/4 and 3/4
    np.testing.assert_allclose(rows.square, [0.25, 0, 0.75, 0, 1])


def test_streamed_equals_the_full_rows_on_continuous_scores(tmp_path):
    rng = np.random.default_rng(1)
    tables = [scene_tables(rng, f"s{k}", 12, None, timed=k % 2 == 0) for k in range(5)]
    s = streamed(write_parts(tmp_path / "p", tables), tmp_path / "scratch")
    check_against_oracle(oracle(tables), s)


def test_coarse_grid_still_gives_exact_operating_points(tmp_path):
    # 4 bins at most: nearly every bin holds many scores, so every operating threshold
    # comes from the second pass over the rows of its bin
    rng = np.random.default_rng(2)
    tables = [scene_tables(rng, f"s{k}", 10, None, timed=True) for k in range(4)]
    s = streamed(write_parts(tmp_path / "p", tables), tmp_path / "scratch", max_curve_bins=4)
    assert all(m["mixed_bins"] > 0 for m in s.summary["models"].values())
    check_against_oracle(oracle(tables), s)


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_scenes=st.integers(1, 4),
    n_values=st.integers(2, 12),
    max_bins=st.sampled_from([2, 3, 8, None]),
)
def test_streamed_equals_the_full_rows_with_ties(tmp_path, seed, n_scenes, n_values, max_bins):
    rng = np.random.default_rng(seed)
    values = np.round(rng.random(n_values) * 2 - 0.5, 3)  # a few values, some <= 0: ties
    tables = [scene_tables(rng, f"s{k}", 4, values, timed=bool(k % 2)) for k in range(n_scenes)]
    if sum(a.height for a, _ in tables) == 0:
        return
    work = tmp_path / f"{seed}-{n_scenes}-{n_values}-{max_bins}"
    s = streamed(write_parts(work / "p", tables), work / "scratch", max_curve_bins=max_bins)
    check_against_oracle(oracle(tables), s)


def test_order_of_parts_does_not_change_the_result(tmp_path):
    rng = np.random.default_rng(3)
    tables = [scene_tables(rng, f"s{k}", 8, None, timed=True) for k in range(6)]
    parts = write_parts(tmp_path / "p", tables)
    shuffled = parts[:]
    random.Random(0).shuffle(shuffled)
    a = streamed(parts, tmp_path / "a")
    b = streamed(shuffled[::-1], tmp_path / "b")
    assert json.dumps(a.summary, sort_keys=True) == json.dumps(b.summary, sort_keys=True)
    assert_frame_equal(a.roc, b.roc)
    assert_frame_equal(pieces(a), pieces(b))


def test_streamed_tables_are_written_and_read_back(tmp_path):
    rng = np.random.default_rng(4)
    tables = [scene_tables(rng, f"s{k}", 6, None, timed=False) for k in range(3)]
    s = streamed(write_parts(tmp_path / "p", tables), tmp_path / "scratch")
    files = write_stats(s, tmp_path / "out")
    written = pl.read_parquet(files["per_frame.parquet"])
    assert_frame_equal(written, pieces(s))
    csv = pl.read_csv(files["per_frame.csv"])
    assert csv.height == written.height and csv.columns == written.columns
    assert not list((tmp_path / "out").glob("*.tmp*"))  # nothing half-written left


def test_a_scene_without_agents_counts_its_frames(tmp_path):
    rng = np.random.default_rng(5)
    tables = [scene_tables(rng, f"s{k}", 6, None, timed=True) for k in range(2)]
    agents, frames = tables[0]
    empty = agents.head(0).with_columns(pl.lit("s9").alias("scene"))
    frames_empty = frames.head(3).with_columns(
        pl.lit("s9").alias("scene"), *(pl.lit(0, dtype=pl.Int64).alias(c) for c in
                                       ("n_others", "n_baseline", "kept_current_distance",
                                        "fn_current_distance", "tier_near", "tier_far"))
    )  # fmt: skip
    tables.append((empty, frames_empty))
    s = streamed(write_parts(tmp_path / "p", tables), tmp_path / "scratch")
    check_against_oracle(oracle(tables), s)
    assert s.summary["situations"]["without_agents"] == 3


def test_exact_sweep_is_what_the_weights_add_up_to():
    # the per-row weights, summed in score order, give risk.metrics.exact_sweep's curve
    rng = np.random.default_rng(6)
    scores = np.round(rng.random(200), 2)
    sit = rng.integers(0, 20, 200)
    pos = rng.random(200) < 0.4
    rows = sweep_rows(scores, sit, pos)
    exact = exact_sweep(scores, np.unique(sit, return_inverse=True)[1], pos)
    for k, t in enumerate(exact.thresholds):
        keep = rows.scores >= t
        tpr = rows.tpr[keep].sum() / rows.tpr.sum()
        assert tpr == pytest.approx(exact.mean_tpr[k], abs=1e-12)


def test_a_model_without_any_score_is_one_error(tmp_path):
    rng = np.random.default_rng(7)
    agents, frames = scene_tables(rng, "s0", 4, None, timed=False)
    agents = agents.with_columns(pl.lit(float("nan")).alias("risk_gaussian"))
    with pytest.raises(StatsError, match="risk_gaussian"):
        streamed(write_parts(tmp_path / "p", [(agents, frames)]), tmp_path / "scratch")


def test_replay_stats_command_streams_and_matches_the_oracle(tmp_path):
    from click.testing import CliRunner

    from replay.cli.app import main

    rng = np.random.default_rng(8)
    tiers = ["behavior", "interactive", "cooperative"]  # the default cascade's
    tables = []
    (tmp_path / "in").mkdir()
    for k in range(3):
        agents, _ = scene_tables(rng, f"s{k}", 6, None, timed=False)
        agents = agents.with_columns(
            pl.col("tier").replace({"near": "behavior", "far": "interactive"}).cast(pl.Enum(tiers))
        )
        agents.write_parquet(tmp_path / "in" / f"t{k}.parquet")
        tables.append(agents)
    out = tmp_path / "out"
    result = CliRunner().invoke(
        main, ["stats", str(tmp_path / "in"), "-o", str(out), "--no-plots", "--no-progress",
               "--workers", "1"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sweep"].startswith("binned")
    whole = pl.concat(tables)
    o = compute_stats(whole, frames_from_agents(whole, STAGES, tiers), stage_names=STAGES,
                      tier_names=tiers)  # fmt: skip
    written = pl.read_parquet(out / "per_frame.parquet")
    assert_frame_equal(o.per_frame, written, check_dtypes=False, rel_tol=1e-9)
    for m, block in o.summary["models"].items():
        got = summary["models"][m]
        assert abs(got["auc"] - block["auc"]) <= got["auc_error_bound"] + 1e-12
        assert got["points"]["tpr_0.95"]["threshold"] == block["points"]["tpr_0.95"]["threshold"]
