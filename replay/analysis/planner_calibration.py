"""Calibrating the cascade against what planners react to (issue 37).

Three parts, each usable alone:

- :func:`scene_scores` (pure: a scene file and :class:`ScoreSettings` in, a polars table
  out, so that any job engine can run it, one scene per task): for every ego-frame at
  the stride, every valid other agent's nine risk scores, whether the reachability bound
  keeps it, what the corridor stage says, and its *planner truth* for each planner
  (:func:`replay.planning.truth.planner_truth`: removing it alone changes the plan);
- :func:`calibrated_planner_config`: the stage thresholds with the guarantee of
  :func:`risk.calibration.calibrate_with_guarantee`, on scene-level units, against the
  union of the planners' labels (the shipped cascade keeps what either reacts to);
- :func:`site_split`, :func:`held_out_report`, :func:`leave_one_dataset_out`: calibrate on
  some recording sites, report on the others with scene-bootstrap intervals.

These work on the whole scores table (:func:`collect_scores`, :func:`planner_calibration`):
small runs and the tests' oracle. ``replay calibrate`` runs
:func:`streamed_planner_calibration` on the scenes' parts (:func:`score_parts`) instead:
the same results from per-scene summaries, one scene read at a time (issue 38).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pathlib
import re
import tempfile
from collections.abc import Sequence
from typing import Any

import numpy as np
import polars as pl

from replay.analysis.planner_eval.open_loop import _egos, ego_frames, scene_key
from replay.analysis.planner_eval.study import share_with_interval
from replay.core.egos import load_scene
from replay.core.engine import Stride, seen_from
from replay.errors import ReplayError
from replay.jobs import Inputs, Job, JobReport, SceneOutput, SceneRef, fingerprint, scene_refs
from replay.jobs.place import JobPlace, every_done, run_job, shared_engine, write_all_failures
from replay.jobs.runner import PARTS, part_path
from replay.planning.errors import NoReferencePath
from replay.planning.inputs import plan_request
from replay.planning.registry import make_planner
from replay.planning.truth import planner_truth, target_speed
from risk import MODELS, evaluate
from risk.calibration import (
    CalibrationError,
    GuaranteedCalibration,
    calibrate_unit_minima,
    calibrate_with_guarantee,
    important_dropped,
    unit_minimum,
    with_agents_dropped,
)
from risk.cascade import (
    CascadeConfig,
    CorridorSettings,
    Stage,
    Tier,
    corridor_masks,
    reachable_mask,
)
from risk.evaluation import percentile_interval, scene_draws
from risk.registry import BASELINE_THRESHOLD

#: The units calibration may treat as independent: whole scenes (the default), or one
#: ego of one scene (several egos of a scene share its traffic: use only with one ego per
#: scene, or knowingly).
UNITS = ("scene", "ego")
#: The tables of the calibration's jobs (``OUT/parts/<table>/``).
SCORES = "scores"
CORRIDOR = "corridor"


@dataclasses.dataclass(frozen=True)
class ScoreSettings:
    """What :func:`scene_scores` computes. ``every_s``: one ego-frame per this many seconds;
    ``ego``: None (the recording's ego), an id, or "all" (every moving agent)."""

    planners: tuple[str, ...] = ("idm",)
    corridor: CorridorSettings | None = dataclasses.field(default_factory=CorridorSettings)
    every_s: float = 1.0
    ego: int | str | None = None
    tolerance_m: float = 0.5
    horizon_s: float = 5.0
    dt_s: float = 0.1
    baseline_threshold: float = BASELINE_THRESHOLD


def site_of(scene: str) -> str:
    """A scene's recording site from its file name: ``highd/DEU_LocationALower26-1_...``
    -> ``DEU_LocationA``, ``mona/C-DEU_MONAEast-2_...`` -> ``DEU_MONAEast``,
    ``sind/CHN_SIND-831_...`` -> ``CHN_SIND`` (the part before the first dash, without a
    ``C-`` prefix, and without a carriageway's Upper/Lower and its recording number)."""
    name = pathlib.PurePath(scene).name
    name = re.sub(r"^C-", "", name)
    base = name.split("-", 1)[0]
    return re.sub(r"(Upper|Lower)\d*$", "", base)


def scene_scores(source: str | os.PathLike[str], settings: ScoreSettings) -> pl.DataFrame:
    """One row per (ego-frame, valid other agent) of one scene; see the module docstring.

    Columns: ``scene``, ``dataset``, ``site``, ``ego_id``, ``frame``, ``t_s``,
    ``agent_id``, ``kind``, ``distance_m``, ``risk_<model>`` for the nine models,
    ``reachable`` (the bound keeps it), ``corridor`` and ``behind`` (the corridor stage
    keeps it, drops it; False without one), and per planner ``label_<planner>`` (null where the planner could not
    plan with all agents, or the ego had no path) and ``shift_<planner>`` (m)."""
    path = pathlib.Path(source)
    scene = load_scene(path)
    if not scene.indexed:
        raise ReplayError(f"{path}: the scene has no frames")
    planners = [make_planner(name) for name in settings.planners]
    tracks = scene.tracks()
    column_of = {int(i): c for c, i in enumerate(tracks.ids)}
    key = scene_key(path)
    columns: dict[str, list[np.ndarray]] = {}

    def put(name: str, values: Any) -> None:
        columns.setdefault(name, []).append(np.asarray(values))

    stride = Stride(seconds=settings.every_s)
    for ego_id, index, frame in ego_frames(scene, _egos(scene, settings.ego), stride):
        others = np.flatnonzero(frame.others)
        if others.size == 0:
            continue
        values = evaluate(frame, models=list(MODELS))
        reach = reachable_mask(frame, settings.baseline_threshold)
        protected, behind, _ = corridor_masks(frame, settings.corridor)
        d = frame.xy[others] - frame.xy[frame.ego]
        k = others.size
        put("ego_id", np.full(k, ego_id, np.int64))
        put("frame", np.full(k, index, np.int64))
        put("t_s", np.full(k, float(frame.t)))
        put("agent_id", frame.ids[others].astype(np.int64))
        put("kind", frame.kinds[others].astype(np.int64))
        put("distance_m", np.hypot(d[:, 0], d[:, 1]))
        for model in MODELS:
            put(f"risk_{model}", np.asarray(values[model], dtype=np.float64)[others])
        put("reachable", reach[others])
        put("corridor", np.zeros(k, bool) if protected is None else protected[others])
        put("behind", np.zeros(k, bool) if behind is None else behind[others])
        labels = _planner_labels(
            frame, others, scene, tracks, column_of[ego_id], planners, settings
        )
        for name, (label, shift) in labels.items():
            put(f"label_{name}", label)
            put(f"shift_{name}", shift)
    if not columns:
        return pl.DataFrame()
    data = {name: np.concatenate(parts) for name, parts in columns.items()}
    n = len(data["agent_id"])
    df = pl.DataFrame(
        {
            "scene": [key] * n,
            "dataset": [path.parent.name or "."] * n,
            "site": [site_of(key)] * n,
            **{k: v for k, v in data.items() if not k.startswith("label_")},
            **{
                k: pl.Series(k, [None if np.isnan(x) else bool(x) for x in v], dtype=pl.Boolean)
                for k, v in data.items()
                if k.startswith("label_")
            },
        }
    )
    return df


def _planner_labels(
    frame: Any,
    others: np.ndarray,
    scene: Any,
    tracks: Any,
    column: int,
    planners: Sequence[Any],
    settings: ScoreSettings,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per planner: label (1, 0, NaN unknown) and plan shift without the agent, for the
    agents ``others`` of ``frame``."""
    k = others.size
    unknown = {p.name: (np.full(k, np.nan), np.full(k, np.nan)) for p in planners}
    row = round((frame.t - tracks.t0_s) / tracks.dt_s)
    speed_now = float(frame.speed[frame.ego])
    target = target_speed(tracks, row, column, settings.horizon_s, speed_now)
    try:
        request = plan_request(
            frame, scene.map, target_speed_mps=target, horizon_s=settings.horizon_s,
            dt_s=settings.dt_s,
        )  # fmt: skip
    except NoReferencePath:
        return unknown
    position = {int(i): n for n, i in enumerate(frame.ids[others])}
    at = np.array([position.get(int(i), -1) for i in request.agents.ids], dtype=np.int64)
    out = {}
    for planner in planners:
        reference = planner.plan(request)
        truth = planner_truth(planner, request, reference, tolerance_m=settings.tolerance_m)
        label = np.zeros(k) if reference.ok else np.full(k, np.nan)
        shift = np.zeros(k) if reference.ok else np.full(k, np.nan)
        ok = at >= 0
        label[at[ok]] = truth.label[ok]
        shift[at[ok]] = truth.shift_m[ok]
        out[planner.name] = (label, shift)
    return out


def scores_scene(ref: SceneRef, settings: ScoreSettings) -> SceneOutput:
    """The scores job of one scene: :func:`scene_scores` keyed by the scene's unique key
    (the scene-level unit of the guarantee: two files never share one); no table when
    the scene has no ego-frame with another agent."""
    df = scene_scores(ref.path, settings)
    if df.is_empty():
        return SceneOutput({})
    return SceneOutput({SCORES: df.with_columns(pl.lit(ref.key).alias("scene"))})


def scores_job(settings: ScoreSettings) -> Job:
    """The scores job (:func:`scores_scene`) for ``settings`` without the corridor (its
    columns are :func:`corridor_scene`'s)."""
    plain = dataclasses.replace(settings, corridor=None)
    return Job("calibrate-scores", scores_scene, plain, _key("calibrate-scores", plain))


@dataclasses.dataclass(frozen=True)
class CorridorJobSettings:
    """The corridor pass: the corridor stage's settings and the folder of the scores'
    parts (it reads each scene's keys from there)."""

    corridor: CorridorSettings
    parts: str


def corridor_scene(ref: SceneRef, settings: CorridorJobSettings) -> SceneOutput:
    """The corridor job of one scene: :func:`with_corridor`'s two columns for the rows
    of the scene's scores part, in their order."""
    source = part_path(pathlib.Path(settings.parts), SCORES, ref.key)
    if not source.is_file():
        return SceneOutput({})
    keys = pl.read_parquet(source, columns=["ego_id", "frame", "agent_id"])
    return SceneOutput(
        {CORRIDOR: with_corridor(keys, ref.path, settings.corridor).select("corridor", "behind")}
    )


@dataclasses.dataclass(frozen=True)
class ScorePart:
    """One scene's parts: its scores table and, with a corridor, the corridor pass's
    two columns for the same rows (:meth:`read` joins them)."""

    key: str
    scores: pathlib.Path
    corridor: pathlib.Path | None = None

    def read(self) -> pl.DataFrame:
        df = pl.read_parquet(self.scores)
        if self.corridor is not None:
            extra = pl.read_parquet(self.corridor)
            df = df.with_columns(extra["corridor"], extra["behind"])
        return df


def score_parts(
    paths: Sequence[pathlib.Path],
    settings: ScoreSettings,
    place: JobPlace,
    *,
    reports: list[JobReport] | None = None,
) -> list[ScorePart]:
    """Run the scores job (:func:`scene_scores`, one task per scene) and, with a corridor,
    the corridor job on the engine of ``place``, and return every complete scene's parts
    in scene-key order (nothing read). Its parts are the cache: a rerun into the same
    folder with the same settings reads the complete scenes. The scores do not depend on
    the corridor settings: its columns are a second, cheap job (:func:`corridor_scene`),
    so that the corridor can be tuned without planning again. ``reports`` receives both
    jobs' reports (their failures: scenes left out)."""
    corridor = settings.corridor
    plain = dataclasses.replace(settings, corridor=None)
    refs = scene_refs(Inputs(tuple(pathlib.Path(p) for p in paths), ()))
    job = scores_job(plain)
    with shared_engine(place, len(refs)) as where:
        report = run_job(job, refs, where, "planner truth")
        found = [report]
        every_done(report)
        with_columns: dict[str, pathlib.Path] = {}
        if corridor is not None:
            parts = str(report.out_dir / PARTS)
            job_settings = CorridorJobSettings(corridor, parts)
            essential = (corridor, plain)  # the scores' settings decide the rows
            second = Job("calibrate-corridor", corridor_scene, job_settings,
                         _key("calibrate-corridor", essential))  # fmt: skip
            done = [d.ref for d in report.done]
            found.append(run_job(second, done, where, "corridor stage"))
            with_columns = {
                d.ref.key: pathlib.Path(d.tables[CORRIDOR])
                for d in found[-1].done
                if CORRIDOR in d.tables
            }
    if reports is not None:
        reports += found
    write_all_failures(place.out_dir, found)  # each pass wrote only its own
    out = []
    for d in report.done:
        if SCORES not in d.tables:
            continue
        if corridor is not None and d.ref.key not in with_columns:
            continue  # its corridor pass failed: listed, left out
        out.append(
            ScorePart(d.ref.key, pathlib.Path(d.tables[SCORES]), with_columns.get(d.ref.key))
        )
    if not out:
        raise ReplayError("no ego-frame with another agent in the given scenes")
    return out


def collect_scores(
    paths: Sequence[pathlib.Path],
    settings: ScoreSettings,
    *,
    workers: int = 1,
    progress: bool = True,
    place: JobPlace | None = None,
    reports: list[JobReport] | None = None,
) -> pl.DataFrame:
    """Every scene's scores (:func:`score_parts`, default: ``workers`` local processes
    writing into a temporary folder) concatenated in scene-key order: the whole table,
    for small runs and tests (``replay calibrate`` streams the parts instead:
    :func:`streamed_planner_calibration`)."""
    with contextlib.ExitStack() as stack:
        if place is None:
            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="replay-calibrate-"))
            place = JobPlace(pathlib.Path(tmp), "local", workers, None, progress)
        parts = score_parts(paths, settings, place, reports=reports)
        return pl.concat([part.read() for part in parts], how="diagonal_relaxed")


def cached_scores(
    paths: Sequence[pathlib.Path],
    settings: ScoreSettings,
    cache: pathlib.Path,
    *,
    workers: int = 1,
    progress: bool = True,
) -> pl.DataFrame:
    """:func:`collect_scores` with its parts kept in ``cache`` (local processes): scenes
    complete there (same settings) are read, the others computed."""
    place = JobPlace(cache, "local", workers, None, progress)
    return collect_scores(paths, settings, place=place)


def _key(name: str, settings: object) -> str:
    return fingerprint(name, {"settings": repr(settings)})


def with_corridor(
    df: pl.DataFrame, source: str | os.PathLike[str], corridor: CorridorSettings | None
) -> pl.DataFrame:
    """``df`` (one scene's scores) with its ``corridor`` (kept by the corridor stage) and
    ``behind`` (dropped by it) columns computed for ``corridor`` from the scene file
    (False throughout without one)."""
    if df.is_empty():
        return df
    keep = np.zeros(df.height, dtype=bool)
    drop = np.zeros(df.height, dtype=bool)
    if corridor is not None:
        scene = load_scene(source)
        frames = dict(scene.indexed)
        keys = df.select("ego_id", "frame", "agent_id")
        for (ego_id, index), rows in keys.with_row_index("row").group_by(
            "ego_id", "frame", maintain_order=True
        ):
            frame = seen_from(frames[int(index)], int(ego_id))
            if frame is None:
                continue
            mask, behind, _ = corridor_masks(frame, corridor)
            assert mask is not None and behind is not None
            at = rows["row"].to_numpy()
            keep[at] = np.isin(rows["agent_id"].to_numpy(), frame.ids[mask])
            drop[at] = np.isin(rows["agent_id"].to_numpy(), frame.ids[behind])
    return df.with_columns(pl.Series("corridor", keep), pl.Series("behind", drop))


# ---------------------------------------------------------------------- calibration
def label_planners(df: pl.DataFrame) -> tuple[str, ...]:
    return tuple(c.removeprefix("label_") for c in df.columns if c.startswith("label_"))


def important(df: pl.DataFrame, planners: Sequence[str]) -> np.ndarray:
    """``(A,)`` bool: important to any of ``planners`` (the union; unknown counts as not)."""
    missing = [p for p in planners if f"label_{p}" not in df.columns]
    if missing:
        raise ReplayError(
            f"no planner truth for {', '.join(missing)} in the scores "
            f"(they hold: {', '.join(label_planners(df)) or 'none'})"
        )
    out = np.zeros(df.height, dtype=bool)
    for p in planners:
        out |= df[f"label_{p}"].fill_null(False).to_numpy().astype(bool)
    return out


def units_of(df: pl.DataFrame, unit: str) -> np.ndarray:
    if unit == "scene":
        return df["scene"].to_numpy()
    if unit == "ego":
        return (df["scene"] + "#" + df["ego_id"].cast(pl.String)).to_numpy()
    raise ReplayError(f"unknown unit {unit!r}; expected one of {', '.join(UNITS)}")


def stage_scores(df: pl.DataFrame, models: Sequence[str], *, corridor: bool) -> np.ndarray:
    """``(S, A)``: each stage's risk; ``+inf`` where the corridor stage keeps the agent
    (when ``corridor``), ``-inf`` where the bound or the corridor stage drops it."""
    scores = np.stack([df[f"risk_{m}"].to_numpy().astype(np.float64) for m in models])
    shielded = df["corridor"].to_numpy().astype(bool) if corridor else np.zeros(df.height, bool)
    dropped = ~df["reachable"].to_numpy().astype(bool) & ~shielded
    if corridor and "behind" in df.columns:
        dropped |= df["behind"].to_numpy().astype(bool) & ~shielded
    scores[:, shielded] = np.inf
    scores[:, dropped] = -np.inf
    return scores


def calibrated_planner_config(
    df: pl.DataFrame,
    models: Sequence[str],
    *,
    planners: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str = "scene",
    corridor: CorridorSettings | None = None,
    tiers: Sequence[Tier],
    baseline_threshold: float = BASELINE_THRESHOLD,
) -> tuple[CascadeConfig, GuaranteedCalibration]:
    """The cascade ``corridor`` + ``models`` with thresholds of the stated guarantee
    against the union of ``planners``' truth (see the module docstring). The scores must
    have been computed with the same corridor settings (its column)."""
    try:
        cal = calibrate_with_guarantee(
            stage_scores(df, models, corridor=corridor is not None),
            important(df, planners),
            units_of(df, unit),
            models=models,
            miss_rate=miss_rate,
            confidence=confidence,
            unit=unit,
        )
    except CalibrationError as exc:
        raise ReplayError(str(exc)) from None
    return _guaranteed_config(cal, planners, corridor, tiers, baseline_threshold), cal


def _guaranteed_config(
    cal: GuaranteedCalibration,
    planners: Sequence[str],
    corridor: CorridorSettings | None,
    tiers: Sequence[Tier],
    baseline_threshold: float,
) -> CascadeConfig:
    guarantee = {**cal.guarantee(), "reference": "planner", "planners": list(planners)}
    return CascadeConfig(
        stages=tuple(Stage(s.model, s.threshold) for s in cal.stages),
        tiers=tuple(tiers),
        baseline_threshold=baseline_threshold,
        corridor=corridor,
        guarantee=guarantee,
    )


def cascade_keeps(df: pl.DataFrame, config: CascadeConfig) -> np.ndarray:
    """``(A,)`` bool: the agents ``config`` keeps, from the scores table (vectorised; as
    the cascade runs: the corridor's, then the bound and every stage)."""
    keep = df["reachable"].to_numpy().astype(bool)
    for stage in config.stages:
        risk = np.nan_to_num(df[f"risk_{stage.model}"].to_numpy().astype(np.float64), nan=-np.inf)
        keep &= risk >= stage.threshold
    if config.corridor is not None:
        if "behind" in df.columns:
            keep &= ~df["behind"].to_numpy().astype(bool)
        keep |= df["corridor"].to_numpy().astype(bool)
    return keep


# ---------------------------------------------------------------------- site split
def site_split(
    df: pl.DataFrame, holdout: Sequence[str] | str = "auto"
) -> tuple[np.ndarray, np.ndarray]:
    """``(calibrate, report)`` row masks: the held-out sites' scenes are reported on and
    never calibrated on. ``"auto"``: in every dataset with two or more sites, its
    smallest site (fewest scenes; ties: the last by name) is held out; datasets with
    one site are calibrated on only. Else the names of the sites to hold out."""
    chosen = held_out_sites(df, holdout)
    report = df["site"].is_in(sorted(chosen)).to_numpy()
    return ~report, report


def held_out_sites(scenes: pl.DataFrame, holdout: Sequence[str] | str = "auto") -> set[str]:
    """The sites :func:`site_split` holds out, from a table with the columns ``dataset``,
    ``site`` and ``scene`` (a row per agent-frame, or per scene)."""
    sites = scenes.select("dataset", "site", "scene").unique()
    if isinstance(holdout, str) and holdout == "auto":
        chosen: set[str] = set()
        per = sites.group_by("dataset", "site").agg(pl.len().alias("scenes"))
        for dataset in per["dataset"].unique().to_list():
            rows = per.filter(pl.col("dataset") == dataset).sort(
                ["scenes", "site"], descending=[False, True]
            )
            if rows.height >= 2:
                chosen.add(str(rows["site"][0]))
    else:
        chosen = set(holdout)
        known = set(sites["site"].to_list())
        unknown = sorted(chosen - known)
        if unknown:
            raise ReplayError(
                f"--holdout: no site {', '.join(unknown)} in the scenes; sites: {', '.join(sorted(known))}"
            )
    return chosen


def _share(hits: np.ndarray, clusters: np.ndarray, n_boot: int, seed: int) -> dict[str, Any]:
    return share_with_interval(hits, clusters, n_boot=n_boot, seed=seed)


def held_out_report(
    df: pl.DataFrame,
    config: CascadeConfig,
    planners: Sequence[str],
    *,
    unit: str = "scene",
    n_boot: int = 1000,
    seed: int = 0,
) -> dict[str, Any]:
    """Per dataset (and ``all``) of ``df``: planner-important agent-frames, the share the
    cascade drops and the share of units with one dropped (each with a 95 %
    scene-bootstrap interval), and agents kept per ego-frame of the others; per planner
    too."""
    keep = cascade_keeps(df, config)
    out: dict[str, Any] = {}
    for dataset in ["all", *sorted(df["dataset"].unique().to_list())]:
        rows = (
            np.ones(df.height, bool) if dataset == "all" else (df["dataset"] == dataset).to_numpy()
        )
        part = df.filter(pl.Series(rows))
        kept = keep[rows]
        scenes = part["scene"].to_numpy()
        entry: dict[str, Any] = {"scenes": int(np.unique(scenes).size)}
        frames = part.select("scene", "ego_id", "frame").n_unique()
        entry["ego_frames"] = frames
        entry["mean_others"] = part.height / max(frames, 1)
        entry["mean_kept"] = float(kept.sum()) / max(frames, 1)
        for name, who in [("union", list(planners)), *((p, [p]) for p in planners)]:
            imp = important(part, who)
            units = units_of(part, unit)
            missed_units = np.unique(units[imp & ~kept])
            unit_list, first = np.unique(units[imp], return_index=True)
            entry[name] = {
                "positives": int(imp.sum()),
                "dropped": _share(~kept[imp], scenes[imp], n_boot, seed),
                "units_missed": _share(
                    np.isin(unit_list, missed_units), scenes[imp][first], n_boot, seed
                ),
            }
        out[dataset] = entry
    return out


def leave_one_dataset_out(
    df: pl.DataFrame,
    models: Sequence[str],
    *,
    planners: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str,
    corridor: CorridorSettings | None,
    tiers: Sequence[Tier],
    n_boot: int = 1000,
) -> dict[str, Any]:
    """For every dataset: calibrate on the others, report on it (or why not)."""
    out: dict[str, Any] = {}
    for dataset in sorted(df["dataset"].unique().to_list()):
        mask = (df["dataset"] == dataset).to_numpy()
        try:
            config, cal = calibrated_planner_config(
                df.filter(pl.Series(~mask)), models, planners=planners, miss_rate=miss_rate,
                confidence=confidence, unit=unit, corridor=corridor, tiers=tiers,
            )  # fmt: skip
        except ReplayError as exc:
            out[dataset] = {"error": str(exc)}
            continue
        report = held_out_report(
            df.filter(pl.Series(mask)), config, planners, unit=unit, n_boot=n_boot
        )
        out[dataset] = {
            "calibrated_units": cal.units,
            "thresholds": {s.model: s.threshold for s in cal.stages},
            **report[dataset],
        }
    return out


# ---------------------------------------------------------------------- one run
@dataclasses.dataclass(frozen=True)
class PlannerCalibration:
    """What ``replay calibrate --reference planner`` computed."""

    config: CascadeConfig
    calibration: GuaranteedCalibration
    calibrated_on: dict[str, Any]  # scenes, datasets, sites, ego-frames, positives
    held_out: dict[str, Any] | None  # held_out_report of the held-out sites
    held_out_sites: tuple[str, ...]
    leave_one_dataset_out: dict[str, Any] | None


def describe(df: pl.DataFrame, planners: Sequence[str]) -> dict[str, Any]:
    return {
        "scenes": df["scene"].n_unique(),
        "datasets": sorted(df["dataset"].unique().to_list()),
        "sites": sorted(df["site"].unique().to_list()),
        "ego_frames": df.select("scene", "ego_id", "frame").n_unique(),
        "agent_frames": df.height,
        "positives": {p: int(important(df, [p]).sum()) for p in planners}
        | {"union": int(important(df, planners).sum())},
    }


def planner_calibration(
    df: pl.DataFrame,
    models: Sequence[str],
    *,
    planners: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str,
    corridor: CorridorSettings | None,
    tiers: Sequence[Tier],
    holdout: Sequence[str] | str | None = None,
    lodo: bool = False,
    n_boot: int = 1000,
) -> PlannerCalibration:
    """Calibrate (without the held-out sites when ``holdout``), then report on them and,
    with ``lodo``, leave each dataset out in turn."""
    calibrate_rows = np.ones(df.height, bool)
    held_out = None
    sites: tuple[str, ...] = ()
    if holdout is not None:
        calibrate_rows, report_rows = site_split(df, holdout)
        sites = tuple(sorted(df.filter(pl.Series(report_rows))["site"].unique().to_list()))
    calibration_df = df.filter(pl.Series(calibrate_rows))
    config, cal = calibrated_planner_config(
        calibration_df, models, planners=planners, miss_rate=miss_rate, confidence=confidence,
        unit=unit, corridor=corridor, tiers=tiers,
    )  # fmt: skip
    if holdout is not None and not calibrate_rows.all():
        held_out = held_out_report(
            df.filter(pl.Series(~calibrate_rows)), config, planners, unit=unit, n_boot=n_boot
        )
    loo = None
    if lodo:
        loo = leave_one_dataset_out(
            df, models, planners=planners, miss_rate=miss_rate, confidence=confidence,
            unit=unit, corridor=corridor, tiers=tiers, n_boot=n_boot,
        )  # fmt: skip
    return PlannerCalibration(
        config=config,
        calibration=cal,
        calibrated_on=describe(calibration_df, planners),
        held_out=held_out,
        held_out_sites=sites,
        leave_one_dataset_out=loo,
    )


# ---------------------------------------------------------------------- in bounded memory
# ``replay calibrate`` never holds the corpus's rows (issue 38): a first pass over the
# parts, one scene at a time, keeps what no threshold changes (counts, and each unit's
# least stage score among its planner-important agents: all the guarantee's rule needs);
# the thresholds follow from those; a second pass counts what the chosen cascades keep
# (the dropped important agent-frames of the calibration scenes, the held-out and
# leave-one-dataset-out figures). The held memory grows with scenes and units, not with
# agent-frames. :func:`planner_calibration` on the whole table is the tests' oracle.


@dataclasses.dataclass(frozen=True, slots=True)
class SceneSummary:
    """One scene's part of the calibration that no threshold changes. ``positives``:
    planner-important agent-frames per planner and of their ``union``; ``minima (S, U)``:
    per stage, the least stage score of the union-important agents of each of the
    scene's ``U`` units that has one (:func:`risk.calibration.unit_minimum`)."""

    scene: str
    dataset: str
    site: str
    ego_frames: int
    agent_frames: int
    positives: dict[str, int]
    minima: np.ndarray


def summarize_scene(
    df: pl.DataFrame, models: Sequence[str], *, planners: Sequence[str], unit: str, corridor: bool
) -> SceneSummary:
    """The :class:`SceneSummary` of one scene's scores table (pass 1)."""
    imp = important(df, planners)
    units = units_of(df, unit)
    scores = stage_scores(df, models, corridor=corridor)
    minima = (
        np.stack([unit_minimum(scores[s], imp, units) for s in range(len(models))])
        if models
        else np.empty((0, np.unique(units[imp]).size))
    )
    return SceneSummary(
        scene=str(df["scene"][0]),
        dataset=str(df["dataset"][0]),
        site=str(df["site"][0]),
        ego_frames=df.select("scene", "ego_id", "frame").n_unique(),
        agent_frames=df.height,
        positives={p: int(important(df, [p]).sum()) for p in planners} | {"union": int(imp.sum())},
        minima=minima,
    )


@dataclasses.dataclass(frozen=True, slots=True)
class SceneKeeps:
    """What one cascade keeps of one scene (pass 2): the agent-frames kept and, per group
    (``union`` and each planner), ``(positives, dropped, units with a positive, units
    with one dropped)``."""

    kept: int
    groups: dict[str, tuple[int, int, int, int]]


def scene_keeps(
    df: pl.DataFrame, config: CascadeConfig, planners: Sequence[str], unit: str
) -> SceneKeeps:
    """The :class:`SceneKeeps` of ``config`` on one scene's scores table."""
    keep = cascade_keeps(df, config)
    units = units_of(df, unit)
    groups = {}
    for name, who in [("union", list(planners)), *((p, [p]) for p in planners)]:
        imp = important(df, who)
        missed = imp & ~keep
        groups[name] = (
            int(imp.sum()),
            int(missed.sum()),
            int(np.unique(units[imp]).size),
            int(np.unique(units[missed]).size),
        )
    return SceneKeeps(int(keep.sum()), groups)


def _share_of_sums(hits: Sequence[int], n: Sequence[int], n_boot: int, seed: int) -> dict[str, Any]:
    """:func:`share_with_interval` from per-scene sums, the scenes in key order (sorted,
    as its clusters are) and only those with ``n > 0``: the same draws, so the same
    interval (every sum it forms is an exact integer)."""
    total = int(sum(n))
    if total == 0:
        return {"share": None, "ci95": None, "n": 0, "count": 0}
    counts = scene_draws(len(n), n_boot=n_boot, seed=seed)
    num = counts @ np.asarray(hits, dtype=np.float64)
    den = counts @ np.asarray(n, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        reps = num / den
    lo, hi = percentile_interval(reps)
    count = int(sum(hits))
    return {"share": float(np.float64(count) / total), "ci95": [lo, hi], "n": total, "count": count}


def summaries_report(
    summaries: Sequence[SceneSummary],
    keeps: dict[str, SceneKeeps],
    planners: Sequence[str],
    *,
    n_boot: int = 1000,
    seed: int = 0,
) -> dict[str, Any]:
    """:func:`held_out_report` from the scenes' summaries and what the cascade kept of
    each (``keeps`` by scene)."""
    out: dict[str, Any] = {}
    for dataset in ["all", *sorted({s.dataset for s in summaries})]:
        chosen = sorted(
            (s for s in summaries if dataset == "all" or s.dataset == dataset),
            key=lambda s: s.scene,
        )
        frames = sum(s.ego_frames for s in chosen)
        entry: dict[str, Any] = {
            "scenes": len(chosen),
            "ego_frames": frames,
            "mean_others": sum(s.agent_frames for s in chosen) / max(frames, 1),
            "mean_kept": float(sum(keeps[s.scene].kept for s in chosen)) / max(frames, 1),
        }
        for name in ["union", *planners]:
            g = [keeps[s.scene].groups[name] for s in chosen]
            g = [x for x in g if x[0] > 0]  # the bootstrap's clusters: scenes with a positive
            entry[name] = {
                "positives": sum(x[0] for x in g),
                "dropped": _share_of_sums([x[1] for x in g], [x[0] for x in g], n_boot, seed),
                "units_missed": _share_of_sums([x[3] for x in g], [x[2] for x in g], n_boot, seed),
            }
        out[dataset] = entry
    return out


def _describe_summaries(
    summaries: Sequence[SceneSummary], planners: Sequence[str]
) -> dict[str, Any]:
    """:func:`describe` from the scenes' summaries."""
    return {
        "scenes": len(summaries),
        "datasets": sorted({s.dataset for s in summaries}),
        "sites": sorted({s.site for s in summaries}),
        "ego_frames": sum(s.ego_frames for s in summaries),
        "agent_frames": sum(s.agent_frames for s in summaries),
        "positives": {p: sum(s.positives[p] for s in summaries) for p in [*planners, "union"]},
    }


def _calibrate_summaries(
    summaries: Sequence[SceneSummary],
    models: Sequence[str],
    *,
    planners: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str,
    corridor: CorridorSettings | None,
    tiers: Sequence[Tier],
    baseline_threshold: float = BASELINE_THRESHOLD,
) -> tuple[CascadeConfig, GuaranteedCalibration]:
    """:func:`calibrated_planner_config` from the scenes' summaries; each stage's
    ``agents_dropped`` is 0 until the second pass counts it."""
    minima = (
        np.concatenate([s.minima for s in summaries], axis=1)
        if summaries
        else np.empty((len(models), 0))
    )
    try:
        cal = calibrate_unit_minima(
            minima, models=models, miss_rate=miss_rate, confidence=confidence, unit=unit,
            positives=sum(s.positives["union"] for s in summaries),
        )  # fmt: skip
    except CalibrationError as exc:
        raise ReplayError(str(exc)) from None
    return _guaranteed_config(cal, planners, corridor, tiers, baseline_threshold), cal


def streamed_planner_calibration(
    parts: Sequence[ScorePart],
    models: Sequence[str],
    *,
    planners: Sequence[str],
    miss_rate: float,
    confidence: float,
    unit: str,
    corridor: CorridorSettings | None,
    tiers: Sequence[Tier],
    holdout: Sequence[str] | str | None = None,
    lodo: bool = False,
    n_boot: int = 1000,
) -> PlannerCalibration:
    """:func:`planner_calibration` over the scenes' parts, one scene at a time (see the
    section comment): the same thresholds, guarantee and figures, in any order of the
    parts, without holding the corpus's rows."""
    shielded = corridor is not None
    summaries = [
        summarize_scene(part.read(), models, planners=planners, unit=unit, corridor=shielded)
        for part in parts
    ]
    held: set[str] = set()
    if holdout is not None:
        table = pl.DataFrame(
            {
                "dataset": [s.dataset for s in summaries],
                "site": [s.site for s in summaries],
                "scene": [s.scene for s in summaries],
            },
            schema={"dataset": pl.String, "site": pl.String, "scene": pl.String},
        )
        held = held_out_sites(table, holdout)
    calibration = [s for s in summaries if s.site not in held]
    reported = [s for s in summaries if s.site in held]
    settings = dict(planners=planners, miss_rate=miss_rate, confidence=confidence, unit=unit,
                    corridor=corridor, tiers=tiers)  # fmt: skip
    config, cal = _calibrate_summaries(calibration, models, **settings)  # type: ignore[arg-type]
    others: dict[str, tuple[CascadeConfig, GuaranteedCalibration] | str] = {}
    if lodo:
        for dataset in sorted({s.dataset for s in summaries}):
            rest = [s for s in summaries if s.dataset != dataset]
            try:
                others[dataset] = _calibrate_summaries(rest, models, **settings)  # type: ignore[arg-type]
            except ReplayError as exc:
                others[dataset] = str(exc)
    # pass 2: what the chosen cascades keep, one scene at a time
    dropped = np.zeros(len(models), dtype=np.int64)
    held_keeps: dict[str, SceneKeeps] = {}
    lodo_keeps: dict[str, SceneKeeps] = {}
    for part, summary in zip(parts, summaries, strict=True):
        df = part.read()
        if summary.site in held:
            held_keeps[summary.scene] = scene_keeps(df, config, planners, unit)
        else:
            scores = stage_scores(df, models, corridor=shielded)
            dropped += important_dropped(scores, important(df, planners), cal.thresholds)
        other = others.get(summary.dataset)
        if isinstance(other, tuple):
            lodo_keeps[summary.scene] = scene_keeps(df, other[0], planners, unit)
    cal = with_agents_dropped(cal, dropped.tolist())
    loo: dict[str, Any] | None = None
    if lodo:
        loo = {}
        for dataset, other in others.items():
            if isinstance(other, str):
                loo[dataset] = {"error": other}
                continue
            mine = [s for s in summaries if s.dataset == dataset]
            report = summaries_report(mine, lodo_keeps, planners, n_boot=n_boot)
            loo[dataset] = {
                "calibrated_units": other[1].units,
                "thresholds": {s.model: s.threshold for s in other[1].stages},
                **report[dataset],
            }
    return PlannerCalibration(
        config=config,
        calibration=cal,
        calibrated_on=_describe_summaries(calibration, planners),
        held_out=summaries_report(reported, held_keeps, planners, n_boot=n_boot)
        if reported
        else None,
        held_out_sites=tuple(sorted(held)),
        leave_one_dataset_out=loo,
    )


def _pct(share: dict[str, Any]) -> str:
    if share.get("share") is None:
        return "n/a"
    lo, hi = share["ci95"]
    ci = "" if lo is None or not np.isfinite(lo) else f" [{100 * lo:.1f}, {100 * hi:.1f}]"
    return f"{100 * share['share']:.1f} %{ci} of {share['n']}"


def format_report(result: PlannerCalibration, planners: Sequence[str]) -> str:
    """The end-of-run text: the guarantee, the thresholds, the held-out figures."""
    cal = result.calibration
    on = result.calibrated_on
    lines = [
        f"Calibrated on {on['scenes']} scenes ({', '.join(on['datasets'])}; sites "
        f"{', '.join(on['sites'])}), {on['ego_frames']} ego-frames, {on['agent_frames']} "
        f"agent-frames; planner-important: "
        + ", ".join(f"{k} {v}" for k, v in on["positives"].items()),
        f"Guarantee: {cal.statement()}.",
        f"  A = {cal.miss_rate:g}, C = {cal.confidence:g}, n = {cal.units} {cal.unit}s with a "
        f"planner-important agent (unit: {cal.unit}); per stage A/S = {cal.stage_miss_rate:.4g} "
        f"at {cal.stage_confidence:.4g}, {cal.stages[0].drops_allowed} calibration {cal.unit}s "
        "may fall below each threshold",
        "  corridor stage: " + ("on" if result.config.corridor is not None else "off"),
    ]
    for s in cal.stages:
        lines.append(
            f"  {s.model}: threshold {s.threshold:.6g}; drops important agents in "
            f"{s.units_dropped} {cal.unit}s ({s.agents_dropped} agent-frames) of the calibration data"
        )
    if result.held_out is not None:
        lines.append(
            f"Held out (sites {', '.join(result.held_out_sites)}; never calibrated on): "
            "planner-important agents dropped, scenes with one dropped, agents kept per ego-frame"
        )
        for dataset, entry in result.held_out.items():
            u = entry["union"]
            lines.append(
                f"  {dataset}: {entry['scenes']} scenes, {u['positives']} important; dropped "
                f"{_pct(u['dropped'])}; scenes missed {_pct(u['units_missed'])}; kept "
                f"{entry['mean_kept']:.1f} of {entry['mean_others']:.1f}"
            )
    if result.leave_one_dataset_out is not None:
        lines.append("Leave one dataset out (calibrated on the others, reported on it):")
        for dataset, entry in result.leave_one_dataset_out.items():
            if "error" in entry:
                lines.append(f"  {dataset}: not calibrated: {entry['error']}")
                continue
            u = entry["union"]
            lines.append(
                f"  {dataset}: {entry['scenes']} scenes, {u['positives']} important; dropped "
                f"{_pct(u['dropped'])}; scenes missed {_pct(u['units_missed'])}; kept "
                f"{entry['mean_kept']:.1f} of {entry['mean_others']:.1f}"
            )
    return "\n".join(lines)
