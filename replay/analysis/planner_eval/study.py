"""``replay plan`` as a library: run the open loop over many scenes, summarise, write.

The summary answers the issue's two questions per filter: how much planning time does the
filter save (median and p95 of the filter's time plus the filtered plan against the
all-agents plan, overall and by agent-count bins), and how often does the plan change
(share of comparable ego-frames, with a 95 % scene-bootstrap interval: frames of one scene
are not independent, so scenes are resampled whole).

The study's driver never holds the corpus's rows (issue 38): the summaries, the merged
tables and the plot points come from the per-scene part files, one at a time
(:mod:`replay.analysis.planner_eval.streaming`).
"""

from __future__ import annotations

import contextlib
import dataclasses
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

from outputs.atomic import write_text
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
from replay.analysis.planner_eval.open_loop import PlanSettings
from replay.analysis.planner_eval.streaming import (  # the first four: this module's before
    COUNT_BINS as COUNT_BINS,
)
from replay.analysis.planner_eval.streaming import (
    SHIFT_TOLERANCES_M as SHIFT_TOLERANCES_M,
)
from replay.analysis.planner_eval.streaming import (
    SPEED_SCALED_S as SPEED_SCALED_S,
)
from replay.analysis.planner_eval.streaming import (
    PlotPoints,
    TableParts,
    frames_of,
    summarize_closed_loop,
    summarize_plans,
)
from replay.analysis.planner_eval.streaming import share_with_interval as share_with_interval
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
from risk.order_statistics import OrderStatistics


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
    #: The part files of the plans and (with truth) agents tables; ``plans`` and
    #: ``truth`` are empty when the rows were not read (``run_open_loop(read=False)``).
    parts: TableParts = dataclasses.field(default_factory=TableParts)
    truth_parts: TableParts = dataclasses.field(default_factory=TableParts)


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


def run_open_loop(
    scenes: Sequence[pathlib.Path],
    settings: PlanSettings,
    *,
    ego: int | str | None = None,
    every: Stride | int = 1,
    workers: int = 1,
    progress: bool = True,
    place: JobPlace | None = None,
    read: bool = True,
) -> PlanTables:
    """Every scene in open loop (:func:`plan_scene`), one job per scene on the engine of
    ``place`` (default: ``workers`` local processes). Scenes that fail are listed in
    ``PlanTables.jobs``' failures and left out. ``read``: read the rows back into
    ``plans`` and ``truth``; else only the part files are named (``parts``; they live in
    ``place``)."""
    settings.make_filters()  # a bad spec fails here, before any worker starts
    job = open_loop_job(OpenLoopSettings(settings, ego, Stride.of(every)))
    with _place_or_temp(place, workers, progress) as where:
        report = run_job(job, _refs(scenes), where, f"plan ({settings.planner})")
        every_done(report)
        parts = TableParts(tuple(report.parts(plans_table(settings.planner))))
        truth_parts = TableParts(tuple(report.parts(truth_table(settings.planner))))
        plans = parts.collect() if read else pl.DataFrame()
        truth = truth_parts.collect() if read and settings.truth else None
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
        parts=parts,
        truth_parts=truth_parts,
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
        if need > 0:
            parts = TableParts(tuple(report.parts("match_distances")))
            radius = _kth_smallest(parts, "distance_m", need)
    return {
        "ego_frames": frames,
        "cascade_mean_kept": mean_kept,
        "nearest_k": round(mean_kept),
        "radius_m": math.ceil(radius * 100.0) / 100.0,  # cm: never below the match
    }


def _kth_smallest(parts: TableParts, column: str, k: int) -> float:
    """The ``k``-th smallest (1 = the smallest) of ``column`` over the parts, 0.0 when
    there are fewer values: two passes, one part at a time, holding the value counts and
    one grid bin's values (:class:`risk.order_statistics.OrderStatistics`)."""
    stats = OrderStatistics()

    def values(df: pl.DataFrame) -> np.ndarray:
        v = df[column].drop_nulls().to_numpy().astype(np.float64)
        return v[~np.isnan(v)]

    for df in parts.frames([column]):
        stats.count(values(df))
    if stats.n < k:
        return 0.0
    stats.want([k - 1])
    for df in parts.frames([column]):
        stats.keep(values(df))
    return stats.value(k - 1)


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
def _base(tables: PlanTables) -> dict[str, Any]:
    """The summary's first keys: what the jobs' partials add up to."""
    return {
        "scenes": len(tables.scenes),
        "ego_frames": tables.ego_frames,
        "ego_frames_without_path": tables.no_path,
        "ego_kinds": tables.ego_kinds,
        "skipped_ego_frames_by_kind": tables.skipped_ego_frames,
        "skipped_egos_by_kind": tables.skipped_egos,
    }


def summarize(tables: PlanTables, *, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
    """Per filter: kept agents, plan success, changed share (scene-bootstrap 95 %), times
    (all agents vs the filter's time plus the filtered plan) overall and by agent-count
    bins, and how often the filter dropped the agent that constrained the full plan.
    From the part files one at a time (or the rows in memory, when read):
    :func:`replay.analysis.planner_eval.streaming.summarize_plans`."""
    frames = tables.parts.frames if not tables.parts.is_empty() else frames_of(tables.plans)
    return summarize_plans(frames, _base(tables), n_boot=n_boot, seed=seed)[0]


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
    egos), ``sampled`` egos driven. ``runs``: the rows' part files (in the job place's
    folder: give ``run_closed_loop`` a place to keep them)."""

    runs: TableParts
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
        runs = TableParts(tuple(report.parts(closed_loop_table(settings.planner))))
    return ClosedLoopRuns(
        runs=runs, vehicle_egos=vehicles, skipped_egos=skipped, sampled=len(picks),
        jobs=(found, report),
    )  # fmt: skip


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

    plans: TableParts
    truth: TableParts | None
    closed_loop: TableParts | None
    summary: dict[str, Any]
    jobs: tuple[JobReport, ...] = ()  # every pass's report
    failures: tuple[Failure, ...] = ()  # the scenes that failed in any pass
    #: Each planner's planning-time scatter (a capped sample; in planner order).
    points: tuple[PlotPoints, ...] = ()
    #: Without a job place: the temporary folder of the parts, kept with the result.
    scratch: tempfile.TemporaryDirectory[str] | None = None


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
    any pass go to ``place.out_dir/failures.csv`` and ``summary["failed_scenes"]``.
    The result names the tables' part files, never their rows (issue 38)."""
    summary: dict[str, Any] = {"planners": {}, "time_s": {}}
    reports: list[JobReport] = []
    plans: list[pathlib.Path] = []
    truths: list[pathlib.Path] = []
    closed: list[pathlib.Path] = []
    points: list[PlotPoints] = []
    scratch = None
    if place is None:  # the parts must outlive this call: write_study streams them
        scratch = tempfile.TemporaryDirectory(prefix="replay-plan-")
        place = JobPlace(pathlib.Path(scratch.name), "local", workers, None, progress)
    with shared_engine(place, len(scenes)) as where:
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
            tables = run_open_loop(scenes, own, ego=ego, every=every, place=where, read=False)
            assert tables.jobs is not None
            reports.append(tables.jobs)
            entry, scatter = summarize_plans(tables.parts.frames, _base(tables))
            summary["time_s"][f"open_loop:{name}"] = time.perf_counter() - start
            plans += tables.parts.files
            truths += tables.truth_parts.files
            if scatter is not None:
                points.append(scatter)
            if closed_loop:
                start = time.perf_counter()
                runs = run_closed_loop(
                    scenes, own, ego=ego, egos_per_scene=closed_loop_egos,
                    sample=closed_loop_sample, agents=agents, tracker=tracker, place=where,
                )  # fmt: skip
                reports += runs.jobs
                entry["closed_loop"] = summarize_closed_loop(runs.runs.frames)
                entry["closed_loop"]["egos"] = {
                    "vehicle_egos": runs.vehicle_egos,
                    "skipped_not_vehicles": runs.skipped_egos,
                    "sampled": runs.sampled,
                }
                summary["time_s"][f"closed_loop:{name}"] = time.perf_counter() - start
                closed += runs.runs.files
            summary["planners"][name] = entry
        failures = all_failures(reports)
        if scratch is None:  # every pass wrote its own; the study's lists them all
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
        plans=TableParts(tuple(plans)),
        truth=TableParts(tuple(truths)) if settings.truth else None,
        closed_loop=TableParts(tuple(closed)) if closed_loop else None,
        summary=summary,
        jobs=tuple(reports),
        failures=tuple(failures),
        points=tuple(points),
        scratch=scratch,
    )


def describe_jobs(result: StudyResult) -> str:
    """The end-of-run lines on the scenes: per pass, what was computed, skipped and
    failed; where the failures are listed."""
    return "\n".join(f"  {r.job}: {r.describe()}" for r in result.jobs)


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
    a closed loop), ``summary.json`` and the plots into ``out_dir``. The tables are
    streamed from the part files, each into a temporary file renamed into place when
    complete (:meth:`TableParts.write`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, pathlib.Path] = {}
    files["plans"] = result.plans.write(out_dir / "plans.parquet")
    if result.closed_loop is not None:
        files["closed_loop"] = result.closed_loop.write(out_dir / "closed_loop.parquet")
    if result.truth is not None:
        files["agents"] = result.truth.write(out_dir / "agents.parquet")
    files["summary"] = write_text(
        out_dir / "summary.json",
        json.dumps(json_safe(result.summary), indent=2, allow_nan=False) + "\n",
    )
    if plots and result.points:
        from replay.analysis.planner_eval import plots as planner_plots  # matplotlib: about 1 s

        files.update(planner_plots.write_plots(result.points, result.summary, out_dir))
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
