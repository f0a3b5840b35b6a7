"""``replay plan`` as a library: run the open loop over many scenes, summarise, write.

The summary answers the issue's two questions per filter: how much planning time does the
filter save (median and p95 of the filter's time plus the filtered plan against the
all-agents plan, overall and by agent-count bins), and how often does the plan change
(share of comparable ego-frames, with a 95 % scene-bootstrap interval: frames of one scene
are not independent, so scenes are resampled whole).
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import os
import pathlib
import tempfile
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import polars as pl

from outputs.atomic import atomic_write, write_text
from replay.analysis.planner_eval import metrics
from replay.analysis.planner_eval.closed_loop import (
    DEFAULT_AGENTS,
    DEFAULT_TRACKER,
    ClosedLoopSettings,
)
from replay.analysis.planner_eval.jobs import (
    ClosedLoopJobSettings,
    EgosSettings,
    MatchSettings,
    OpenLoopSettings,
    closed_loop_job,
    closed_loop_table,
    dataset_of,
    ego_tasks,
    egos_job,
    match_job,
    open_loop_job,
    plans_table,
    truth_table,
)
from replay.analysis.planner_eval.open_loop import ALL_AGENTS, PlanSettings
from replay.core.engine import Stride
from replay.jobs import Failure, JobReport, SceneRef
from replay.jobs.place import (
    JobPlace,
    all_failures,
    every_done,
    run_job,
    shared_engine,
    write_all_failures,
)
from replay.jobs.scenes import Inputs, distinct_files, scene_refs
from risk.evaluation import bootstrap_weights, percentile_interval

#: Agent-count bins of the timing table (others in the frame).
COUNT_BINS = (0, 10, 25, 50, 100, 10**9)
#: The changed share is also reported at these tolerances (m) ...
SHIFT_TOLERANCES_M = (0.5, 1.0, 2.0)
#: ... and at a speed-scaled one: the distance the ego travels in this time (one
#: re-planning period at 10 Hz), at least the run's tolerance. A plan shifted by less is
#: the same plan executed a re-planning period earlier or later.
SPEED_SCALED_S = 0.1


@dataclasses.dataclass(frozen=True)
class PlanTables:
    """The rows of a ``replay plan`` run and what it covered."""

    plans: pl.DataFrame
    truth: pl.DataFrame | None
    scenes: tuple[pathlib.Path, ...]
    ego_frames: int
    no_path: int
    datasets: dict[str, str]
    #: Ego-frames / distinct egos skipped for their kind (PlanSettings.ego_kinds), by kind.
    skipped_ego_frames: dict[str, int] = dataclasses.field(default_factory=dict)
    skipped_egos: dict[str, int] = dataclasses.field(default_factory=dict)
    ego_kinds: str = "vehicles"
    jobs: JobReport | None = None  # where the scenes ran, what failed


def _refs(scenes: Sequence[pathlib.Path]) -> list[SceneRef]:
    """The scenes with their unique keys (:func:`replay.jobs.scenes.scene_refs`), in the
    order given."""
    return scene_refs(Inputs(tuple(pathlib.Path(p) for p in scenes), ()))


@contextlib.contextmanager
def _place_or_temp(place: JobPlace | None, workers: int, progress: bool) -> Iterator[JobPlace]:
    """``place``, or local processes writing their parts into a temporary folder (a
    library caller without an output folder: the rows are read back before it goes)."""
    if place is not None:
        yield place
        return
    with tempfile.TemporaryDirectory(prefix="replay-plan-") as tmp:
        yield JobPlace(pathlib.Path(tmp), "local", workers, None, progress)


def read_table(report: JobReport, table: str) -> pl.DataFrame:
    """Every complete scene's ``table``, in key order (empty when no scene has rows)."""
    if not report.parts(table):
        return pl.DataFrame()
    return report.scan(table).collect()


def run_open_loop(
    scenes: Sequence[pathlib.Path],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    every: Stride | int = 1,
    workers: int = 1,
    progress: bool = True,
    place: JobPlace | None = None,
) -> PlanTables:
    """Every scene in open loop (:func:`plan_scene`), one job per scene on the engine of
    ``place`` (default: ``workers`` local processes). Scenes that fail are listed in
    ``PlanTables.jobs``' failures and left out."""
    settings.make_filters()  # a bad spec fails here, before any worker starts
    job = open_loop_job(OpenLoopSettings(settings, ego, Stride.of(every)))
    with _place_or_temp(place, workers, progress) as where:
        report = run_job(job, _refs(scenes), where, f"plan ({settings.planner})")
        every_done(report)
        plans = read_table(report, plans_table(settings.planner))
        truth = read_table(report, truth_table(settings.planner)) if settings.truth else None
    partials = [d.partial for d in report.done]
    return PlanTables(
        plans=plans,
        truth=truth,
        scenes=tuple(d.ref.path for d in report.done),
        ego_frames=sum(int(p["ego_frames"]) for p in partials),
        no_path=sum(int(p["no_path"]) for p in partials),
        datasets={d.ref.key: dataset_of(d.ref.path) for d in report.done},
        skipped_ego_frames=_add_counts(p["skipped_ego_frames"] for p in partials),
        skipped_egos=_add_counts(p["skipped_egos"] for p in partials),
        ego_kinds=settings.ego_kinds,
        jobs=report,
    )


def _add_counts(parts: Any) -> dict[str, int]:
    total: dict[str, int] = {}
    for part in parts:
        for key, n in part.items():
            total[key] = total.get(key, 0) + n
    return dict(sorted(total.items()))


# ---------------------------------------------------------------------- matched cuts
#: The spec suffix that asks for a nearest-K or radius cut matched to the cascade.
MATCH = "match"


def matched_cuts(
    scenes: Sequence[pathlib.Path],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    every: Stride | int = 1,
    workers: int = 1,
    progress: bool = True,
    place: JobPlace | None = None,
    reports: list[JobReport] | None = None,
) -> dict[str, Any]:
    """The nearest-K and radius cuts that keep as many agents per ego-frame, on average,
    as the cascade: K the rounded mean, R from the ego-frames' sorted distances (the mean
    count within R is a step function of R; R is the smallest radius reaching
    the cascade's mean). One job per scene (:func:`~replay.analysis.planner_eval.jobs.match_scene`); the driver sums the
    scenes' counts and reads the distances back lazily. ``reports`` receives the job's
    report."""
    job = match_job(MatchSettings(settings, ego, Stride.of(every)))
    with _place_or_temp(place, workers, progress) as where:
        report = run_job(job, _refs(scenes), where, "cascade (matching the cuts)")
        if reports is not None:
            reports.append(report)
        every_done(report)
        frames = sum(int(d.partial["ego_frames"]) for d in report.done)
        kept = sum(int(d.partial["kept"]) for d in report.done)
        mean_kept = kept / frames if frames else 0.0
        # The mean count within R is (number of distances <= R) / frames: the smallest R
        # with at least mean_kept * frames distances at or below it.
        need = math.ceil(mean_kept * frames - 1e-9)
        radius = 0.0
        if need > 0 and report.parts("match_distances"):
            column = report.scan("match_distances").select("distance_m")
            if column.select(pl.len()).collect().item() >= need:
                nearest = column.select(pl.col("distance_m").bottom_k(need).max())
                radius = float(nearest.collect().item())
    return {
        "ego_frames": frames,
        "cascade_mean_kept": mean_kept,
        "nearest_k": round(mean_kept),
        "radius_m": math.ceil(radius * 100.0) / 100.0,  # cm: never below the match
    }


def resolve_matched(settings: PlanSettings, matched: dict[str, Any]) -> PlanSettings:
    """``settings`` with ``nearest:match`` and ``radius:match`` replaced by the cuts."""
    specs = []
    for spec in settings.filters:
        kind, _, arg = spec.partition(":")
        if arg == MATCH and kind == "nearest":
            spec = f"nearest:{matched['nearest_k']}"
        elif arg == MATCH and kind == "radius":
            spec = f"radius:{matched['radius_m']:g}"
        if spec not in specs:  # a matched cut equal to a given one is that filter (issue 36)
            specs.append(spec)
    return dataclasses.replace(settings, filters=tuple(specs))


def wants_matching(settings: PlanSettings) -> bool:
    return any(spec.partition(":")[2] == MATCH for spec in settings.filters)


# ---------------------------------------------------------------------- summary
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


def summarize(tables: PlanTables, *, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
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


def format_summary(summary: dict[str, Any]) -> str:
    """The end-of-run text of ``replay plan``."""
    lines = [
        f"Planner {summary.get('planner', '?')}: {summary['scenes']} scenes, "
        f"{summary['ego_frames']} ego-frames ({summary['distinct_egos']} distinct egos; "
        f"{summary['ego_frames_without_path']} without a path to plan along)",
    ]
    skipped = summary.get("skipped_ego_frames_by_kind") or {}
    if skipped:
        egos = summary.get("skipped_egos_by_kind") or {}
        lines.append(
            f"  skipped {sum(skipped.values())} ego-frames of {sum(egos.values())} egos that "
            "are not vehicles ("
            + ", ".join(f"{k}: {n}" for k, n in skipped.items())
            + "); --ego-kinds all plans for them too"
        )
    every = summary.get("all_agents")
    if every:
        ms = every["plan_ms"]
        lines.append(
            f"  all agents: {every['mean_agents']:.1f} agents per frame, plan found in "
            f"{100 * every['plan_ok_share']:.1f} %, plan {_ms(ms['median'])} median, "
            f"{_ms(ms['p95'])} p95"
        )
    for name, f in summary["filters"].items():
        ch = f["changed"]
        share = "n/a" if ch["share"] is None else f"{100 * ch['share']:.1f} %"
        ci = ch["ci95"]
        interval = "" if not ci or ci[0] is None or math.isnan(ci[0]) else (
            f" [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"
        )  # fmt: skip
        ratio = f["median_time_ratio"]
        lines.append(
            f"  {name}: {f['mean_kept']:.1f} agents kept; plan changed in {share}{interval} "
            f"of {ch['n']} comparable frames ({f['changed_egos']} egos, "
            f"{f['changed_scenes']} scenes); filter + plan {_ms(f['filter_plus_plan_ms']['median'])}"
            f" vs {_ms(f['all_agents_plan_ms']['median'])} median"
            + ("" if ratio is None else f" ({ratio:.2f}x)")
        )
    return "\n".join(lines)


def _ms(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f} ms"


# ---------------------------------------------------------------------- closed loop
@dataclasses.dataclass(frozen=True)
class ClosedLoopRuns:
    """The closed-loop rows and the egos they came from: ``vehicle_egos`` found in the
    scenes, ``skipped_egos`` that were pedestrians, cyclists or objects (no car-planner
    egos), ``sampled`` egos driven."""

    runs: pl.DataFrame
    vehicle_egos: int
    skipped_egos: int
    sampled: int
    jobs: tuple[JobReport, ...] = ()  # the vehicle-egos pass and the runs


def _spread(n: int, k: int) -> list[int]:
    """``k <= n`` indices spread evenly over ``range(n)``, first and last included."""
    if k <= 0:
        return []
    return [int(i) for i in np.round(np.linspace(0, n - 1, k)).astype(int)] if k > 1 else [0]


def closed_loop_sample(
    candidates: Sequence[tuple[pathlib.Path, tuple[int, ...]]], sample: int | None
) -> list[tuple[pathlib.Path, int]]:
    """``sample`` (scene, ego) pairs spread evenly over the datasets (a scene's folder),
    then over each dataset's scenes: datasets take one ego in turn until ``sample`` are
    taken or their egos run out; a dataset's share goes to scenes spread evenly over its
    list (first and last included) when it has more scenes than egos to take, else to
    every scene in turn. ``candidates``: each scene with its vehicle egos in the order
    to take them. All of them when ``sample`` is None."""
    usable = [(p, egos) for p, egos in candidates if egos]
    if sample is None:
        return [(p, e) for p, egos in usable for e in egos]
    by_dataset: dict[str, list[tuple[pathlib.Path, tuple[int, ...]]]] = {}
    for p, egos in usable:
        by_dataset.setdefault(dataset_of(p), []).append((p, egos))
    capacity = {d: sum(len(e) for _, e in rows) for d, rows in by_dataset.items()}
    quota = dict.fromkeys(by_dataset, 0)
    left = sample
    while left > 0 and any(quota[d] < capacity[d] for d in quota):
        for d in sorted(by_dataset):
            if left > 0 and quota[d] < capacity[d]:
                quota[d] += 1
                left -= 1
    picks: list[tuple[pathlib.Path, int]] = []
    for d in sorted(by_dataset):
        rows = by_dataset[d]
        take = [0] * len(rows)
        if quota[d] < len(rows):
            for i in _spread(len(rows), quota[d]):
                take[i] = 1
        else:
            need = quota[d]
            while need > 0:
                for i, (_, egos) in enumerate(rows):
                    if need > 0 and take[i] < len(egos):
                        take[i] += 1
                        need -= 1
        picks += [(p, e) for (p, egos), n in zip(rows, take, strict=True) for e in egos[:n]]
    return picks


def run_closed_loop(
    scenes: Sequence[pathlib.Path],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    workers: int = 1,
    progress: bool = True,
    egos_per_scene: int | None = None,
    sample: int | None = None,
    agents: str = DEFAULT_AGENTS,
    tracker: str = DEFAULT_TRACKER,
    place: JobPlace | None = None,
) -> ClosedLoopRuns:
    """Closed-loop runs (:func:`run_ego`): one row per (scene, ego, filter), vehicle
    egos only. ``sample``: that many egos in all (:func:`closed_loop_sample`);
    ``egos_per_scene``: at most that many per scene, those present longest. The
    vehicle egos are found by one job per scene, the sample is drawn here, then one job
    per scene drives that scene's sampled egos."""
    settings.make_filters()
    closed = ClosedLoopSettings(plan=settings, agents=agents, tracker=tracker)
    refs = _refs(scenes)
    with _place_or_temp(place, workers, progress) as where:
        found = run_job(egos_job(EgosSettings(ego)), refs, where, "closed loop (vehicle egos)")
        every_done(found)
        partial = {d.ref.key: d.partial for d in found.done}
        candidates = [
            (r.path, tuple(int(e) for e in partial[r.key]["vehicle_egos"])[:egos_per_scene])
            for r in refs
            if r.key in partial
        ]
        vehicles = sum(len(p["vehicle_egos"]) for p in partial.values())
        skipped = sum(int(p["egos"]) - len(p["vehicle_egos"]) for p in partial.values())
        picks = closed_loop_sample(candidates, sample)
        key_of = {r.path: r.key for r in refs}
        chosen: dict[str, list[int]] = {}
        for path, ego_id in picks:
            chosen.setdefault(key_of[path], []).append(ego_id)
        tasks = ego_tasks(chosen)
        job = closed_loop_job(
            ClosedLoopJobSettings(closed, tuple((t, (k, egos)) for t, k, egos in tasks))
        )
        desc = f"closed loop ({settings.planner}, {agents} agents)"
        ref_of = {r.key: r for r in refs}
        task_refs = [dataclasses.replace(ref_of[k], key=t) for t, k, _ in tasks]
        report = run_job(job, task_refs, where, desc)
        runs = read_table(report, closed_loop_table(settings.planner))
    return ClosedLoopRuns(
        runs=runs, vehicle_egos=vehicles, skipped_egos=skipped, sampled=len(picks),
        jobs=(found, report),
    )  # fmt: skip


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


def summarize_closed_loop(df: pl.DataFrame, *, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
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


def _interval(d: dict[str, Any], *, signed: bool = True, digits: int = 3) -> str:
    """``mean [lo, hi]`` of a :func:`_mean_with_interval` result (signed: a difference)."""
    if d.get("mean") is None:
        return "n/a"
    form = f"{'+' if signed else ''}.{digits}f"
    ci = d.get("ci95") or [None, None]
    if ci[0] is None or not math.isfinite(ci[0]):
        return f"{d['mean']:{form}}"
    return f"{d['mean']:{form}} [{ci[0]:{form}}, {ci[1]:{form}}]"


def format_closed_loop(summary: dict[str, Any]) -> str:
    """The closed-loop part of ``replay plan``'s end-of-run text."""
    egos = summary.get("egos", {})
    skipped = egos.get("skipped_not_vehicles", 0)
    note = f"; {skipped} pedestrian, cyclist or object egos skipped" if skipped else ""
    if not summary.get("runs"):
        return "Closed loop: no run" + note
    lines = [
        f"Closed loop: {summary['runs']} vehicle egos in {summary['scenes']} scenes, once "
        f"with all agents and once per filter ({summary.get('agents', 'log')} agents, "
        f"{summary.get('tracker', 'perfect')} tracker){note}"
    ]
    for name, f in summary["filters"].items():
        fault = f["runs_at_fault"]
        ci = fault.get("ci95") or [None, None]
        interval = "" if ci[0] is None or not math.isfinite(ci[0]) else (
            f" [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"
        )  # fmt: skip
        share = "n/a" if fault["share"] is None else f"{100 * fault['share']:.1f} %"
        lines.append(
            f"  {name}: {f['collisions']} collisions ({f['rear_end_collisions']} from behind), "
            f"{f['at_fault_collisions']} at fault; runs with an at-fault collision {share}"
            f"{interval}; score {_interval(f['score'], signed=False)}; progress "
            f"ratio {_ratio(f['progress_ratio']['median'])} median; plan "
            f"{_ms(f['plan_ms_median'])} median"
        )
        if "paired" in f:
            p = f["paired"]
            lines.append(
                f"    vs all agents ({p['runs']} pairs): at-fault collisions "
                f"{_interval(p['at_fault_difference'])}, score {_interval(p['score_difference'])}, "
                f"progress ratio {_interval(p['progress_ratio_difference'])} (mean difference "
                "[95 % scene bootstrap])"
            )
    return "\n".join(lines)


def _ratio(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def _m(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f} m"


# ---------------------------------------------------------------------- output
@dataclasses.dataclass(frozen=True)
class StudyResult:
    """Everything one ``replay plan`` run computed: the tables of every planner (told
    apart by their ``planner`` column) and the summary (``summary["planners"][name]``)."""

    plans: pl.DataFrame
    truth: pl.DataFrame | None
    closed_loop: pl.DataFrame | None
    summary: dict[str, Any]
    jobs: tuple[JobReport, ...] = ()  # every pass's report
    failures: tuple[Failure, ...] = ()  # the scenes that failed in any pass


def run_study(
    scenes: Sequence[pathlib.Path],
    settings: PlanSettings,
    *,
    planners: Sequence[str],
    ego: int | str | None = None,
    every: Stride | int = 1,
    workers: int = 1,
    progress: bool = True,
    closed_loop: bool = False,
    closed_loop_egos: int | None = None,
    closed_loop_sample: int | None = None,
    agents: str = DEFAULT_AGENTS,
    tracker: str = DEFAULT_TRACKER,
    notify: Any = None,
    place: JobPlace | None = None,
) -> StudyResult:
    """``replay plan``: the matched cuts (when asked for), then per planner the open loop
    and, with ``closed_loop``, the closed loop; one summary for all. Every pass runs one
    job per scene on the engine of ``place`` (one engine for them all; default:
    ``workers`` local processes and a temporary folder), its parts in
    ``place.out_dir/parts`` (a rerun skips complete scenes); the scenes that failed in
    any pass go to ``place.out_dir/failures.csv`` and ``summary["failed_scenes"]``."""
    summary: dict[str, Any] = {"planners": {}, "time_s": {}}
    reports: list[JobReport] = []
    plans, truths, closed = [], [], []
    with (
        _place_or_temp(place, workers, progress) as given,
        shared_engine(given, len(scenes)) as where,
    ):
        if wants_matching(settings):
            start = time.perf_counter()
            matched = matched_cuts(
                scenes, settings, ego=ego, every=every, place=where, reports=reports
            )
            settings = resolve_matched(settings, matched)
            summary["matched_cuts"] = matched
            summary["time_s"]["matching"] = time.perf_counter() - start
            if notify is not None:
                notify(
                    f"Matched to the cascade's {matched['cascade_mean_kept']:.1f} agents per "
                    f"ego-frame: nearest:{matched['nearest_k']}, radius:{matched['radius_m']:g}"
                )
        for name in planners:
            own = dataclasses.replace(settings, planner=name)
            start = time.perf_counter()
            tables = run_open_loop(scenes, own, ego=ego, every=every, place=where)
            assert tables.jobs is not None
            reports.append(tables.jobs)
            entry = summarize(tables)
            summary["time_s"][f"open_loop:{name}"] = time.perf_counter() - start
            plans.append(tables.plans)
            if tables.truth is not None:
                truths.append(tables.truth)
            if closed_loop:
                start = time.perf_counter()
                runs = run_closed_loop(
                    scenes, own, ego=ego, egos_per_scene=closed_loop_egos,
                    sample=closed_loop_sample, agents=agents, tracker=tracker, place=where,
                )  # fmt: skip
                reports += runs.jobs
                entry["closed_loop"] = summarize_closed_loop(runs.runs)
                entry["closed_loop"]["egos"] = {
                    "vehicle_egos": runs.vehicle_egos,
                    "skipped_not_vehicles": runs.skipped_egos,
                    "sampled": runs.sampled,
                }
                summary["time_s"][f"closed_loop:{name}"] = time.perf_counter() - start
                closed.append(runs.runs)
            summary["planners"][name] = entry
        failures = all_failures(reports)
        if place is not None:  # every pass wrote its own; the study's lists them all
            write_all_failures(place.out_dir, reports)
    if closed_loop:
        summary["closed_loop_selection"] = (
            f"{closed_loop_sample} vehicle egos in all, spread evenly over the datasets, "
            "then over each dataset's scenes (those present longest first)"
            if closed_loop_sample is not None
            else f"at most {closed_loop_egos} vehicle egos per scene, those present longest"
            if closed_loop_egos is not None
            else "every vehicle ego"
        )
        summary["closed_loop_agents"] = agents
        summary["closed_loop_tracker"] = tracker
    summary["filters"] = list(settings.filters)
    summary["tolerance_m"] = settings.tolerance_m
    summary["horizon_s"] = settings.horizon_s
    summary["failed_scenes"] = sorted({f.scene for f in failures})
    return StudyResult(
        plans=_concat(plans),
        truth=_concat(truths) if settings.truth else None,
        closed_loop=_concat(closed) if closed_loop else None,
        summary=summary,
        jobs=tuple(reports),
        failures=tuple(failures),
    )


def describe_jobs(result: StudyResult) -> str:
    """The end-of-run lines on the scenes: per pass, what was computed, skipped and
    failed; where the failures are listed."""
    return "\n".join(f"  {r.job}: {r.describe()}" for r in result.jobs)


def _concat(frames: list[pl.DataFrame]) -> pl.DataFrame:
    frames = [f for f in frames if not f.is_empty()]
    return pl.concat(frames, how="diagonal_relaxed") if frames else pl.DataFrame()


def format_study(summary: dict[str, Any]) -> str:
    """The end-of-run text of ``replay plan``: every planner's open and closed loop."""
    lines = []
    for entry in summary["planners"].values():
        lines.append(format_summary(entry))
        if "closed_loop" in entry:
            lines.append(format_closed_loop(entry["closed_loop"]))
    return "\n".join(lines)


def write_study(
    result: StudyResult, out_dir: pathlib.Path, *, plots: bool = True
) -> dict[str, pathlib.Path]:
    """``plans.parquet``, ``agents.parquet`` (with truth), ``closed_loop.parquet`` (with
    a closed loop), ``summary.json`` and the plots into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, pathlib.Path] = {}
    files["plans"] = atomic_write(out_dir / "plans.parquet", result.plans.write_parquet)
    if result.closed_loop is not None:
        files["closed_loop"] = atomic_write(
            out_dir / "closed_loop.parquet", result.closed_loop.write_parquet
        )
    if result.truth is not None:
        files["agents"] = atomic_write(out_dir / "agents.parquet", result.truth.write_parquet)
    files["summary"] = write_text(
        out_dir / "summary.json",
        json.dumps(json_safe(result.summary), indent=2, allow_nan=False) + "\n",
    )
    if plots and not result.plans.is_empty():
        from replay.analysis.planner_eval import plots as planner_plots  # matplotlib: about 1 s

        files.update(planner_plots.write_plots(result.plans, result.summary, out_dir))
    return files


def json_safe(value: Any) -> Any:
    """``value`` with every NaN or infinite float replaced by None (JSON has neither)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def scene_files(paths: Sequence[os.PathLike[str] | str]) -> list[pathlib.Path]:
    """The ``.mcap`` scenes among ``paths`` (folders searched recursively); one file given
    twice, through a folder, a symlink or a hard link, once (by device and inode)."""
    found: list[pathlib.Path] = []
    for p in map(pathlib.Path, paths):
        if p.is_dir():
            found += sorted(f for f in p.rglob("*.mcap") if f.is_file())
        else:
            found.append(p)
    return distinct_files(found)


def _float(value: Any) -> float:
    """A polars aggregate (typed as any Python literal) as a float."""
    return float(value)
