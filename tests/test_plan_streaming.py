"""``replay plan``'s streamed summaries, merged tables and plot points (issue 38): equal to
the full-table computation they replace (kept below as the oracle, main's code before
the change), whatever the parts; a rerun gives the same summary; the merged table is the
concatenation of the parts; the order statistics are numpy's."""

from __future__ import annotations

import itertools
import json
import math
import pathlib
import random
import tempfile
from types import SimpleNamespace
from typing import Any

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from jobs_fixtures import road_corpus, untimed

from replay.analysis.planner_eval import metrics, streaming
from replay.analysis.planner_eval.open_loop import ALL_AGENTS
from replay.analysis.planner_eval.streaming import (
    COUNT_BINS,
    SHIFT_TOLERANCES_M,
    SPEED_SCALED_S,
    SceneSums,
    TableParts,
    frames_of,
    summarize_closed_loop,
    summarize_plans,
)
from replay.analysis.planner_eval.study import _kth_smallest
from replay.cli.app import main
from risk.evaluation import bootstrap_weights, percentile_interval
from risk.order_statistics import OrderStatistics, median_ranks, quantile_ranks

N_BOOT = 200
FILTERS = ("cascade", "nearest:3")
WHYS = ("shift 1.2 m at 3.0 s", "stop/go: stops", "lane: 2 -> 3", "success: no plan")
#: The closed loop's means of non-integer values: equal up to float rounding only (the
#: full table adds them pairwise, the streamed summary scene by scene).
ROUNDED = {"mean_agents", "time_headway_below_1s_s"}
ROUNDED_MEANS = {"score", "score_difference", "progress_ratio_difference"}


# ---------------------------------------------------------------------- hand-made parts
def plan_rows(rng: np.random.Generator, scene: str, dataset: str) -> pl.DataFrame:
    """One scene's plans table: a few egos and frames, all agents and two filters, with
    nulls where the planner leaves them, ties in the times and every kind of change."""
    rows: list[dict[str, Any]] = []
    for ego in range(int(rng.integers(1, 4))):
        for frame in range(0, 5 * int(rng.integers(1, 8)), 5):
            others = int(rng.choice([0, 3, 12, 30, 60, 140]))
            all_ok = bool(rng.random() < 0.85)
            speed = float(rng.uniform(0, 30)) if rng.random() < 0.9 else math.nan
            common = {"scene": scene, "dataset": dataset, "planner": "idm", "ego_id": ego,
                      "frame": frame, "n_others": others, "ego_speed_mps": speed}  # fmt: skip
            rows.append({
                **common, "filter": ALL_AGENTS, "n_agents": others, "filter_ms": 0.0,
                "plan_ms": round(float(rng.lognormal(1, 0.5)), int(rng.integers(1, 4))),
                "plan_ok": all_ok, "changed": False if all_ok else None,
                "max_shift_m": 0.0 if all_ok else math.nan, "why": "",
                "blocking_dropped": None, "changed_1s": False if all_ok else None,
                "unsafe": False if all_ok else None,
            })  # fmt: skip
            for name in FILTERS:
                ok = bool(rng.random() < 0.85)
                changed = None if not (ok or all_ok) else bool(rng.random() < 0.3)
                rows.append({
                    **common, "filter": name, "n_agents": int(rng.integers(0, others + 1)),
                    "filter_ms": round(float(rng.exponential(0.2)), 2),
                    "plan_ms": round(float(rng.lognormal(0.5, 0.5)), int(rng.integers(1, 4))),
                    "plan_ok": ok, "changed": changed,
                    "max_shift_m": float(rng.exponential(2)) if ok and all_ok else math.nan,
                    "why": str(rng.choice(WHYS)) if changed else "",
                    "blocking_dropped": [None, True, False][int(rng.integers(0, 3))],
                    "changed_1s": None if changed is None else bool(rng.random() < 0.2),
                    "unsafe": None if changed is None else bool(rng.random() < 0.1),
                })  # fmt: skip
    return pl.DataFrame(rows, infer_schema_length=None)


def closed_rows(rng: np.random.Generator, scene: str, dataset: str, egos: range) -> pl.DataFrame:
    """The closed-loop rows of some egos of a scene: all agents and two filters each."""
    rows = []
    for ego, name in itertools.product(egos, (ALL_AGENTS, *FILTERS)):
        hits = [int(rng.poisson(0.3)) for _ in range(5)]
        rows.append({
            "scene": scene, "dataset": dataset, "planner": "idm", "ego_id": ego,
            "agents": "reactive", "tracker": "lqr", "filter": name,
            "collisions": sum(hits), "stopped_ego_collisions": hits[0],
            "stopped_track_collisions": hits[1], "front_collisions": hits[2],
            "rear_end_collisions": hits[3], "lateral_collisions": hits[4],
            "at_fault_collisions": int(rng.integers(0, 2)),
            "drivable_area_ok": bool(rng.random() < 0.9),
            "progress_m": float(rng.uniform(0, 200)),
            "progress_ratio": float(rng.uniform(0, 1.2)),
            "min_ttc_s": float(rng.exponential(3)) if rng.random() < 0.8 else math.inf,
            "comfortable": bool(rng.random() < 0.8), "score": float(rng.uniform(0, 1)),
            "min_gap_m": float(rng.exponential(5)) if rng.random() < 0.9 else math.inf,
            "time_headway_below_1s_s": round(float(rng.exponential(1)), 1),
            "plan_ms_median": float(rng.lognormal(1, 0.3)),
            "plan_ms_p95": float(rng.lognormal(1.5, 0.3)),
            "plan_failures": int(rng.integers(0, 3)),
            "mean_agents": float(rng.uniform(0, 40)),
        })  # fmt: skip
    return pl.DataFrame(rows)


def write_parts(root: pathlib.Path, tables: list[pl.DataFrame]) -> TableParts:
    """The tables as part files, in the order given (the job runner's key order)."""
    files = []
    for k, df in enumerate(tables):
        path = root / f"part-{k:03d}.parquet"
        df.write_parquet(path)
        files.append(path)
    return TableParts(tuple(files))


def scene_names(n: int) -> list[tuple[str, str]]:
    return sorted((f"set{'AB'[k % 2]}/scene-{k}", f"set{'AB'[k % 2]}") for k in range(n))


BASE = {"scenes": 0, "ego_frames": 0, "ego_frames_without_path": 0, "ego_kinds": "all",
        "skipped_ego_frames_by_kind": {}, "skipped_egos_by_kind": {}}  # fmt: skip


def same(streamed: Any, oracle: Any, path: str = "") -> None:
    """Equal to the bit, NaN equal to NaN; the closed loop's means of non-integer values
    (:data:`ROUNDED`, the ``mean`` of :data:`ROUNDED_MEANS`) up to float rounding."""
    if isinstance(oracle, dict):
        assert isinstance(streamed, dict) and streamed.keys() == oracle.keys(), path
        for key in oracle:
            rounded = key in ROUNDED or (key == "mean" and path.rsplit("/", 1)[-1] in ROUNDED_MEANS)
            if rounded and oracle[key] is not None:
                assert streamed[key] == pytest.approx(oracle[key], rel=1e-12, nan_ok=True), path
            else:
                same(streamed[key], oracle[key], f"{path}/{key}")
    elif isinstance(oracle, (list, tuple)):
        assert len(streamed) == len(oracle), path
        for k, (s, o) in enumerate(zip(streamed, oracle, strict=True)):
            same(s, o, f"{path}/{k}")
    elif isinstance(oracle, float) and math.isnan(oracle):
        assert isinstance(streamed, float) and math.isnan(streamed), path
    else:
        assert streamed == oracle and type(streamed) is type(oracle), (path, streamed, oracle)


# ---------------------------------------------------------------------- the summaries
@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_scenes=st.integers(1, 6))
def test_the_streamed_open_loop_summary_equals_the_full_tables(seed, n_scenes):
    rng = np.random.default_rng(seed)
    tables = [plan_rows(rng, s, d) for s, d in scene_names(n_scenes)]
    with tempfile.TemporaryDirectory() as tmp:
        parts = write_parts(pathlib.Path(tmp), tables)
        streamed, points = summarize_plans(parts.frames, BASE, n_boot=N_BOOT, seed=3)
        full = parts.collect()
    oracle = oracle_summarize(SimpleNamespace(plans=full, **_counts()), n_boot=N_BOOT, seed=3)
    same(streamed, oracle)
    assert points is not None and points.planner == "idm"
    # below the cap every row where the plan exists is a point, in the table's order
    ok = full.filter(pl.col("plan_ok"))
    for name, others, total in points.filters:
        rows = ok.filter(pl.col("filter") == name)
        assert np.array_equal(others, rows["n_others"].to_numpy())
        assert np.array_equal(total, (rows["filter_ms"] + rows["plan_ms"]).to_numpy())


def _counts() -> dict[str, Any]:
    return {"scenes": (), "ego_frames": 0, "no_path": 0, "ego_kinds": "all",
            "skipped_ego_frames": {}, "skipped_egos": {}}  # fmt: skip


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_scenes=st.integers(1, 5))
def test_the_streamed_closed_loop_summary_equals_the_full_table(seed, n_scenes):
    rng = np.random.default_rng(seed)
    tables = []
    for scene, dataset in scene_names(n_scenes):
        egos = int(rng.integers(1, 7))
        cut = int(rng.integers(1, egos + 1))  # a scene's egos in two tasks, as ego_tasks
        tables.append(closed_rows(rng, scene, dataset, range(cut)))
        if cut < egos:
            tables.append(closed_rows(rng, scene, dataset, range(cut, egos)))
    with tempfile.TemporaryDirectory() as tmp:
        parts = write_parts(pathlib.Path(tmp), tables)
        streamed = summarize_closed_loop(parts.frames, n_boot=N_BOOT, seed=5)
        oracle = oracle_closed_loop(parts.collect(), n_boot=N_BOOT, seed=5)
    same(streamed, oracle)


def test_a_part_whose_column_is_all_null_reads_with_the_others_type(tmp_path):
    rng = np.random.default_rng(9)
    tables = [plan_rows(rng, s, d) for s, d in scene_names(3)]
    nulls = ("changed", "blocking_dropped", "changed_1s", "unsafe", "max_shift_m")
    tables[1] = tables[1].with_columns(pl.lit(None).alias(c) for c in nulls)  # type Null
    parts = write_parts(tmp_path, tables)
    streamed, _ = summarize_plans(parts.frames, BASE, n_boot=N_BOOT)
    oracle = oracle_summarize(SimpleNamespace(plans=parts.collect(), **_counts()), n_boot=N_BOOT)
    same(streamed, oracle)


def test_an_empty_table_summarises_to_nothing():
    summary, points = summarize_plans(TableParts().frames, BASE)
    assert summary == {**BASE, "distinct_egos": 0, "filters": {}, "by_agent_count": {}}
    assert points is None
    assert summarize_closed_loop(TableParts().frames) == {"runs": 0, "filters": {}}


def test_a_rerun_and_another_part_order_give_the_same_summary(tmp_path):
    rng = np.random.default_rng(7)
    tables = [plan_rows(rng, s, d) for s, d in scene_names(5)]
    parts = write_parts(tmp_path, tables)
    first, _ = summarize_plans(parts.frames, BASE, n_boot=N_BOOT)
    again, _ = summarize_plans(parts.frames, BASE, n_boot=N_BOOT)
    shuffled = list(parts.files)
    random.Random(1).shuffle(shuffled)
    other, _ = summarize_plans(TableParts(tuple(shuffled)).frames, BASE, n_boot=N_BOOT)
    assert json.dumps(first) == json.dumps(again)
    # the bootstrap numbers scenes by name: the order in which parts come does not matter
    assert other == first


def test_in_memory_rows_give_the_summary_of_their_parts(tmp_path):
    rng = np.random.default_rng(11)
    parts = write_parts(tmp_path, [plan_rows(rng, s, d) for s, d in scene_names(4)])
    from_parts, _ = summarize_plans(parts.frames, BASE, n_boot=N_BOOT)
    in_memory, _ = summarize_plans(frames_of(parts.collect()), BASE, n_boot=N_BOOT)
    same(in_memory, from_parts)


def test_scene_sums_go_on_adding_a_scene_in_row_order():
    # 0.1 + 0.2 + 0.3 in row order differs from 0.1 + (0.2 + 0.3): a scene split over
    # two parts must add as one
    sums = SceneSums()
    sums.add(np.array(["a", "a"]), np.array([0.1, 0.2]))
    sums.add(np.array(["b", "a"]), np.array([1.0, 0.3]))
    assert sums.total == {"a": (0.1 + 0.2) + 0.3, "b": 1.0}
    assert sums.rows == {"a": 3, "b": 1}
    whole = np.bincount(np.array([0, 0, 0]), weights=np.array([0.1, 0.2, 0.3]))[0]
    assert sums.total["a"] == whole


def test_plot_points_beyond_the_cap_are_every_kth_row_in_key_order(tmp_path, monkeypatch):
    monkeypatch.setattr(streaming, "PLOT_POINTS", 7)
    rng = np.random.default_rng(3)
    parts = write_parts(tmp_path, [plan_rows(rng, s, d) for s, d in scene_names(4)])
    _, points = summarize_plans(parts.frames, BASE, n_boot=N_BOOT)
    ok = parts.collect().filter(pl.col("plan_ok"))
    assert points is not None
    for name, others, total in points.filters:
        rows = ok.filter(pl.col("filter") == name)
        step = math.ceil(rows.height / 7)
        assert others.size <= 7
        assert np.array_equal(others, rows["n_others"].to_numpy()[::step])
        assert np.array_equal(total, (rows["filter_ms"] + rows["plan_ms"]).to_numpy()[::step])


# ---------------------------------------------------------------------- merged tables
def test_the_merged_table_is_the_concatenation_of_the_parts(tmp_path):
    rng = np.random.default_rng(5)
    tables = [plan_rows(rng, s, d) for s, d in scene_names(3)]
    tables[1] = tables[1].drop("unsafe")  # a part without a column: nulls there
    tables[2] = tables[2].with_columns(pl.col("ego_id").cast(pl.Int32))  # widened
    parts = write_parts(tmp_path, tables)
    out = parts.write(tmp_path / "plans.parquet")
    merged = pl.read_parquet(out)
    assert merged.equals(pl.concat(tables, how="diagonal_relaxed"))
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp left


def test_no_part_writes_an_empty_table(tmp_path):
    out = TableParts().write(tmp_path / "plans.parquet")
    assert pl.read_parquet(out).is_empty()


# ---------------------------------------------------------------------- order statistics
@settings(max_examples=60, deadline=None)
@given(
    values=st.lists(
        st.one_of(st.floats(-1e6, 1e6, allow_nan=False), st.sampled_from([0.0, -0.0, 1.5])),
        min_size=1, max_size=300,
    ),
    pieces=st.integers(1, 5),
    max_bins=st.sampled_from([2, 16, 1 << 16]),
    q=st.sampled_from([0.0, 0.05, 0.5, 0.95, 1.0]),
)  # fmt: skip
def test_order_statistics_give_numpys_median_and_quantile(values, pieces, max_bins, q):
    v = np.array(values)
    split = np.array_split(v, pieces)
    stats = OrderStatistics(max_bins=max_bins)
    for piece in split:
        stats.count(piece)
    stats.want([*median_ranks(v.size), *quantile_ranks(v.size, q)[:2]])
    for piece in reversed(split):  # any order
        stats.keep(piece)
    assert stats.median() == float(np.median(v))
    assert stats.quantile(q) == float(np.quantile(v, q))


def test_the_kth_smallest_distance_is_polars_bottom_k(tmp_path):
    rng = np.random.default_rng(2)
    tables = [pl.DataFrame({"distance_m": rng.exponential(20, 50).round(1)}) for _ in range(4)]
    parts = write_parts(tmp_path, tables)
    whole = pl.concat(tables)["distance_m"]
    for k in (1, 17, 200):
        assert _kth_smallest(parts, "distance_m", k) == whole.bottom_k(k).max()
    assert _kth_smallest(parts, "distance_m", 201) == 0.0


# ---------------------------------------------------------------------- a real run
def test_a_plan_run_summarises_its_written_tables_as_the_oracle(tmp_path):
    corpus = tmp_path / "corpus"
    road_corpus(corpus, broken=False)
    out = tmp_path / "out"
    result = CliRunner().invoke(main, [
        "plan", str(corpus), "-o", str(out), "--every", "5", "--filter", "cascade",
        "--filter", "nearest:match", "--closed-loop", "--closed-loop-sample", "2",
        "--agents", "log", "--tracker", "perfect", "--no-progress", "--workers", "1",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())["planners"]["idm"]
    plans = pl.read_parquet(out / "plans.parquet")
    counts = {**_counts(), "scenes": (1, 2, 3), "ego_frames": summary["ego_frames"],
              "no_path": summary["ego_frames_without_path"],
              "ego_kinds": summary["ego_kinds"],
              "skipped_ego_frames": summary["skipped_ego_frames_by_kind"],
              "skipped_egos": summary["skipped_egos_by_kind"]}  # fmt: skip
    oracle = oracle_summarize(SimpleNamespace(plans=plans, **counts))
    closed = summary.pop("closed_loop")
    assert json.loads(json.dumps(oracle_json(oracle))) == summary
    oracle_closed = oracle_closed_loop(pl.read_parquet(out / "closed_loop.parquet"))
    closed.pop("egos")
    same(untimed(closed), untimed(json.loads(json.dumps(oracle_json(oracle_closed)))))
    assert (out / "plan_time.png").is_file() and (out / "plan_changed.png").is_file()


def oracle_json(value: Any) -> Any:
    from replay.analysis.planner_eval.study import json_safe

    return json_safe(value)


# ---------------------------------------------------------------------- the oracle
# main's full-table summaries before issue 38, verbatim but for their names: they hold
# every row of the table at once.
def _float(value: Any) -> float:
    return float(value)


def share_with_interval(
    hits: np.ndarray, scenes: np.ndarray, *, n_boot: int, seed: int
) -> dict[str, Any]:
    """Share of True in ``hits`` with a 95 % scene-bootstrap interval."""
    n = int(hits.size)
    if n == 0:
        return {"share": None, "ci95": None, "n": 0, "count": 0}
    codes, counts = bootstrap_weights(scenes, n_boot=n_boot, seed=seed)
    per_scene_hits = np.bincount(codes, weights=hits.astype(np.float64), minlength=counts.shape[1])
    per_scene_n = np.bincount(codes, minlength=counts.shape[1]).astype(np.float64)
    num = counts @ per_scene_hits
    den = counts @ per_scene_n
    with np.errstate(invalid="ignore", divide="ignore"):
        reps = num / den
    lo, hi = percentile_interval(reps)
    return {
        "share": float(hits.mean()),
        "ci95": [lo, hi],
        "n": n,
        "count": int(hits.sum()),
    }


def _quantiles(values: np.ndarray) -> dict[str, float | None]:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return {"median": None, "p95": None}
    return {"median": float(np.median(v)), "p95": float(np.quantile(v, 0.95))}


def oracle_summarize(tables: Any, *, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
    """Per filter: kept agents, plan success, changed share (scene-bootstrap 95 %), times
    (all agents vs the filter's time plus the filtered plan) overall and by agent-count
    bins, and how often the filter dropped the agent that constrained the full plan."""
    df = tables.plans
    out: dict[str, Any] = {
        "scenes": len(tables.scenes),
        "ego_frames": tables.ego_frames,
        "ego_frames_without_path": tables.no_path,
        "ego_kinds": tables.ego_kinds,
        "skipped_ego_frames_by_kind": tables.skipped_ego_frames,
        "skipped_egos_by_kind": tables.skipped_egos,
        "distinct_egos": 0,
        "filters": {},
        "by_agent_count": {},
    }
    if df.is_empty():
        return out
    out["planner"] = str(df["planner"][0])
    out["distinct_egos"] = df.select(["scene", "ego_id"]).unique().height
    key = ["scene", "ego_id", "frame"]
    reference = df.filter(pl.col("filter") == ALL_AGENTS).select(
        [*key, pl.col("plan_ms").alias("all_plan_ms"), pl.col("plan_ok").alias("all_ok"),
         pl.col("n_agents").alias("all_agents")]
    )  # fmt: skip
    out["all_agents"] = {
        "plan_ok_share": _float(reference["all_ok"].mean() or 0.0),
        "mean_agents": _float(reference["all_agents"].mean() or 0.0),
        "plan_ms": _quantiles(reference.filter(pl.col("all_ok"))["all_plan_ms"].to_numpy()),
    }
    for name in df["filter"].unique(maintain_order=True).to_list():
        if name == ALL_AGENTS:
            continue
        rows = df.filter(pl.col("filter") == name).join(reference, on=key, how="left")
        comparable = rows.filter(pl.col("changed").is_not_null())
        both_ok = rows.filter(pl.col("plan_ok") & pl.col("all_ok"))
        total_ms = (both_ok["filter_ms"] + both_ok["plan_ms"]).to_numpy()
        all_ms = both_ok["all_plan_ms"].to_numpy()
        blocking = rows.filter(pl.col("blocking_dropped").is_not_null())
        ratio = None
        if total_ms.size:
            ratio = (
                float(np.median(total_ms) / np.median(all_ms)) if np.median(all_ms) > 0 else None
            )
        out["filters"][name] = {
            "ego_frames": rows.height,
            "mean_kept": _float(rows["n_agents"].mean() or 0.0),
            "plan_ok_share": _float(rows["plan_ok"].mean() or 0.0),
            "not_comparable": rows.height - comparable.height,
            "changed": share_with_interval(
                comparable["changed"].to_numpy().astype(bool),
                comparable["scene"].to_numpy(),
                n_boot=n_boot,
                seed=seed,
            ),
            **_safety_shares(rows, comparable, n_boot=n_boot, seed=seed),
            "changed_scenes": comparable.filter(pl.col("changed"))["scene"].n_unique(),
            "changed_why": _why_counts(comparable.filter(pl.col("changed"))),
            "changed_shift_m": _quantiles(
                comparable.filter(pl.col("changed") & pl.col("why").str.starts_with("shift"))[
                    "max_shift_m"
                ].to_numpy()
            ),
            "changed_egos": comparable.filter(pl.col("changed"))
            .select(["scene", "ego_id"])
            .unique()
            .height,
            "blocking_agent_dropped": share_with_interval(
                blocking["blocking_dropped"].to_numpy().astype(bool),
                blocking["scene"].to_numpy(),
                n_boot=n_boot,
                seed=seed,
            ),
            "filter_ms": _quantiles(rows["filter_ms"].to_numpy()),
            "filtered_plan_ms": _quantiles(both_ok["plan_ms"].to_numpy()),
            "filter_plus_plan_ms": _quantiles(total_ms),
            "all_agents_plan_ms": _quantiles(all_ms),
            "median_time_ratio": ratio,
        }
        out["by_agent_count"][name] = _by_bins(both_ok)
        out.setdefault("by_dataset", {})[name] = {
            str(d["dataset"]): {
                "ego_frames": int(d["n"]),
                "changed_share": None if d["share"] is None else float(d["share"]),
                "mean_kept": float(d["kept"]),
                "mean_others": float(d["others"]),
            }
            for d in rows.group_by("dataset")
            .agg(
                pl.len().alias("n"),
                pl.col("changed").cast(pl.Float64).mean().alias("share"),
                pl.col("n_agents").mean().alias("kept"),
                pl.col("n_others").mean().alias("others"),
            )
            .sort("dataset")
            .iter_rows(named=True)
        }
    return out


def _safety_shares(
    rows: pl.DataFrame, comparable: pl.DataFrame, *, n_boot: int, seed: int
) -> dict[str, Any]:
    """The changed share at other tolerances (``changed_at``: 0.5, 1, 2 m and
    ``speed_scaled``), ``changed_1s`` and ``unsafe``, each with a scene-bootstrap 95 %
    interval; empty for tables without those columns (runs before issue 37)."""
    if "unsafe" not in rows.columns or comparable.is_empty():
        return {}
    scenes = comparable["scene"].to_numpy()
    changed = comparable["changed"].to_numpy().astype(bool)
    decision = ~comparable["why"].fill_null("").str.starts_with("shift").to_numpy()
    shift = np.nan_to_num(comparable["max_shift_m"].to_numpy().astype(np.float64), nan=np.inf)
    tolerance = SHIFT_TOLERANCES_M[0]
    speed = comparable["ego_speed_mps"].to_numpy().astype(np.float64)
    scaled = np.maximum(tolerance, SPEED_SCALED_S * np.nan_to_num(speed))

    def share(hits: np.ndarray, where: np.ndarray) -> dict[str, Any]:
        return share_with_interval(hits, where, n_boot=n_boot, seed=seed)

    at = {
        f"{tol:g}": share(changed & (decision | (shift > tol)), scenes)
        for tol in SHIFT_TOLERANCES_M
    }
    at["speed_scaled"] = share(changed & (decision | (shift > scaled)), scenes)
    first = rows.filter(pl.col("changed_1s").is_not_null())
    judged = rows.filter(pl.col("unsafe").is_not_null())
    return {
        "changed_at": at,
        "changed_1s": share(first["changed_1s"].to_numpy().astype(bool), first["scene"].to_numpy()),
        "unsafe": share(judged["unsafe"].to_numpy().astype(bool), judged["scene"].to_numpy()),
    }


def _why_counts(changed: pl.DataFrame) -> dict[str, int]:
    """How many changed frames each rule caught first: shift, stop/go, lane, success."""
    kinds = changed["why"].str.split(" ").list.first().str.strip_chars(":")
    return {str(k): int(n) for k, n in kinds.value_counts(sort=True).iter_rows()}


def _by_bins(rows: pl.DataFrame) -> list[dict[str, Any]]:
    bins = []
    counts = rows["n_others"].to_numpy() if rows.height else np.zeros(0)
    for lo, hi in itertools.pairwise(COUNT_BINS):
        inside = (counts >= lo) & (counts < hi)
        if not inside.any():
            continue
        part = rows.filter(pl.Series(inside))
        total = (part["filter_ms"] + part["plan_ms"]).to_numpy()
        all_ms = part["all_plan_ms"].to_numpy()
        bins.append(
            {
                "agents": f"{lo}-{hi - 1}" if hi < 10**9 else f"{lo}+",
                "ego_frames": int(inside.sum()),
                "all_agents_plan_ms": _quantiles(all_ms),
                "filter_plus_plan_ms": _quantiles(total),
                "changed_share": _float(part["changed"].cast(pl.Float64).mean() or 0.0),
            }
        )
    return bins


def _mean_with_interval(
    values: np.ndarray, scenes: np.ndarray, *, n_boot: int, seed: int
) -> dict[str, Any]:
    """Mean of ``values`` with a 95 % scene-bootstrap interval (scenes resampled whole)."""
    n = int(values.size)
    if n == 0:
        return {"mean": None, "ci95": None, "n": 0}
    codes, counts = bootstrap_weights(scenes, n_boot=n_boot, seed=seed)
    per_scene = np.bincount(codes, weights=values.astype(np.float64), minlength=counts.shape[1])
    per_scene_n = np.bincount(codes, minlength=counts.shape[1]).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        reps = (counts @ per_scene) / (counts @ per_scene_n)
    lo, hi = percentile_interval(reps)
    return {"mean": float(values.mean()), "ci95": [lo, hi], "n": n}


def oracle_closed_loop(df: pl.DataFrame, *, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
    """Per filter: collisions by class, at-fault collisions (runs with one, with a 95 %
    scene-bootstrap interval), score, progress, TTC, comfort, planning time; and the
    paired differences against the all-agents run of the same ego (at-fault collisions,
    score, progress ratio) with 95 % scene-bootstrap intervals."""
    if df.is_empty():
        return {"runs": 0, "filters": {}}
    key = ["scene", "ego_id"]
    reference = df.filter(pl.col("filter") == ALL_AGENTS)
    out: dict[str, Any] = {
        "runs": reference.height,
        "distinct_egos": reference.select(key).unique().height,
        "scenes": reference["scene"].n_unique(),
        "datasets": {
            str(d): int(n) for d, n in reference["dataset"].value_counts(sort=True).iter_rows()
        },
        "agents": str(df["agents"][0]) if "agents" in df.columns else "log",
        "tracker": str(df["tracker"][0]) if "tracker" in df.columns else "perfect",
        "filters": {},
    }
    for name in df["filter"].unique(maintain_order=True).to_list():
        rows = df.filter(pl.col("filter") == name)
        scenes = rows["scene"].to_numpy()
        entry: dict[str, Any] = {
            "runs": rows.height,
            "collisions": int(rows["collisions"].sum()),
            "rear_end_collisions": int(rows["rear_end_collisions"].sum()),
            "collisions_by_class": {
                c: int(rows[f"{c}_collisions"].sum())
                for c in ("stopped_ego", "stopped_track", "front", "rear_end", "lateral")
            },
            "at_fault_collisions": int(rows["at_fault_collisions"].sum()),
            "runs_with_collision": int((rows["collisions"] > 0).sum()),
            "runs_at_fault": share_with_interval(
                (rows["at_fault_collisions"] > 0).to_numpy(), scenes, n_boot=n_boot, seed=seed
            ),
            "score": _mean_with_interval(
                rows["score"].to_numpy(), scenes, n_boot=n_boot, seed=seed
            ),
            "progress_ratio": _quantiles(rows["progress_ratio"].to_numpy()),
            "drivable_area_fails": int((rows["drivable_area_ok"] == False).sum()),  # noqa: E712
            "ttc_below_bound": int((rows["min_ttc_s"] < metrics.LEAST_TTC_S).sum()),
            "uncomfortable": int((~rows["comfortable"]).sum()),
            "min_gap_m": _quantiles(rows["min_gap_m"].to_numpy()),
            "time_headway_below_1s_s": float(rows["time_headway_below_1s_s"].sum()),
            "progress_m": _quantiles(rows["progress_m"].to_numpy()),
            "plan_ms_median": _quantiles(rows["plan_ms_median"].to_numpy())["median"],
            "plan_ms_p95": _quantiles(rows["plan_ms_p95"].to_numpy())["median"],
            "mean_agents": _float(rows["mean_agents"].mean() or 0.0),
            "plan_failures": int(rows["plan_failures"].sum()),
        }
        if name != ALL_AGENTS:
            paired = rows.join(reference, on=key, suffix="_all")
            pair_scenes = paired["scene"].to_numpy()
            differences = {
                column: _mean_with_interval(
                    (paired[column] - paired[f"{column}_all"]).cast(pl.Float64).to_numpy(),
                    pair_scenes,
                    n_boot=n_boot,
                    seed=seed,
                )
                for column in ("at_fault_collisions", "score", "progress_ratio")
            }

            entry["paired"] = {
                "runs": paired.height,
                "more_collisions": int((paired["collisions"] > paired["collisions_all"]).sum()),
                "fewer_collisions": int((paired["collisions"] < paired["collisions_all"]).sum()),
                "more_at_fault": int(
                    (paired["at_fault_collisions"] > paired["at_fault_collisions_all"]).sum()
                ),
                "fewer_at_fault": int(
                    (paired["at_fault_collisions"] < paired["at_fault_collisions_all"]).sum()
                ),
                "at_fault_difference": differences["at_fault_collisions"],
                "score_difference": differences["score"],
                "progress_ratio_difference": differences["progress_ratio"],
                "progress_change_m": _quantiles(
                    (paired["progress_m"] - paired["progress_m_all"]).to_numpy()
                ),
                "min_gap_change_m": _quantiles(
                    (paired["min_gap_m"] - paired["min_gap_m_all"]).to_numpy()
                ),
            }
        out["filters"][name] = entry
    return out
