"""Outcome evaluation of a corpus: every model against the survival baseline and against
what really happened (the hindsight truth), with scene-bootstrap intervals.

The commands evaluate one scene at a time (:mod:`replay.analysis.evaluation.streaming`);
this module holds what both ways share (names, references, agreement, settings) and
:func:`evaluate_table`: the whole agents table at once, turned into arrays for the pure
:func:`risk.evaluation.evaluate_references` (exact every-score ROC curves). It is the
slow, obvious oracle the tests compare the streamed evaluation with; no command runs it.
``docs/evaluation.md`` describes every field.
"""

from __future__ import annotations

import pathlib
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import polars as pl

from converters.tracks import PATH_SOURCE_LABELS
from replay.errors import ReplayError
from risk.budgets import budget_recall
from risk.evaluation import (
    FPR_POINTS,
    TPR_TARGETS,
    bootstrap_weights,
    evaluate_references,
    reference_counts,
)
from risk.hindsight import HindsightSettings
from risk.registry import BASELINE_THRESHOLD, MODELS

#: Groupings the evaluation can break results down by.
GROUPINGS = ("dataset", "kind", "site")
DEFAULT_GROUPINGS = ("dataset", "kind")
REFERENCES = ("survival", "hindsight")
#: Which hindsight windows are scored (``--hindsight-windows``): ``complete``, only frames
#: whose whole horizon is recorded for the ego and the agent, positives and negatives
#: alike (the default: a censored window can only ever be positive, so the old rule
#: compares "moving and late in the scene" against "parked and early"); ``any``, also
#: positives seen in censored windows (the rule before issue 28).
HINDSIGHT_WINDOWS = ("complete", "any")
#: Prefix of the dataset's own labels as references (table columns ``label_<name>``).
DATASET_PREFIX = "dataset_"
#: At most this many points per ROC curve in the roc table (the AUC uses all of them).
ROC_TABLE_POINTS = 2000
#: The threshold whose miss rates the plots and the printed table show: the pooled
#: threshold that keeps every survival-baseline agent (the paper's filters drop none).
HEADLINE_THRESHOLD = "tpr1_survival"
TRUTH_COLUMNS = ("truth_gap_m", "truth_pet_s", "truth_label")


class EvaluationError(ReplayError):
    """An evaluation that cannot be done (the message says why and what to do)."""


# ---------------------------------------------------------------------- names
def site_of(scene: str) -> str:
    """The recording site of a scene name: ``C-DEU_AachenBendplatz-1_14320_T-399`` ->
    ``DEU_AachenBendplatz``, ``DEU_LocationALower26-1_26150_T-225`` ->
    ``DEU_LocationALower`` (the part before the first ``-``, without a ``C-`` prefix
    and trailing digits); a name without ``-`` is its own site."""
    name = pathlib.PurePath(scene).name
    name = name.removeprefix("C-")
    return re.sub(r"\d+$", "", name.split("-", 1)[0]) or name


def default_calibration_sites(sites: Sequence[str]) -> list[str]:
    """Every other site in sorted order (the first, third, ...): a deterministic split
    into calibration and test sites; empty when there are fewer than two sites."""
    distinct = sorted(set(sites))
    return distinct[::2] if len(distinct) >= 2 else []


def calibration_sites(asked: Sequence[str] | None, sites: Sequence[str]) -> list[str]:
    """The sites the evaluation treats as calibration sites: those ``asked``, or by
    default :func:`default_calibration_sites`; raises EvaluationError for a site that is
    not among ``sites``."""
    chosen = list(asked) if asked is not None else default_calibration_sites(sites)
    unknown = sorted(set(chosen) - set(sites))
    if unknown:
        raise EvaluationError(
            f"unknown calibration site {unknown[0]!r}; the sites are: "
            f"{', '.join(sorted(set(sites)))}"
        )
    return chosen


# ---------------------------------------------------------------------- arrays
@dataclass(frozen=True)
class EvaluationSettings:
    """What :func:`evaluate_table` computes (CLI options map one to one)."""

    models: tuple[str, ...] | None = None  # default: every risk_<model> column
    baseline_threshold: float = BASELINE_THRESHOLD
    groupings: tuple[str, ...] = DEFAULT_GROUPINGS
    calibration_sites: tuple[str, ...] | None = None  # None: every other site
    n_boot: int = 1000
    level: float = 0.95
    seed: int = 0
    hindsight_windows: str = "complete"  # one of HINDSIGHT_WINDOWS


def _codes(column: pl.Series) -> np.ndarray:
    """Label codes (1, 0, -1 null) of a nullable boolean column."""
    col = column.cast(pl.Boolean)
    return np.where(
        col.is_null().to_numpy(), -1, col.fill_null(False).to_numpy().astype(np.int8)
    ).astype(np.int8)


def reference_arrays(
    df: pl.DataFrame, *, baseline_threshold: float, windows: str = "complete"
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every reference the table carries, as ``(A,)`` label codes (or booleans), and a
    note for each reference it lacks (name -> why).

    - ``survival``: the survival baseline;
    - ``hindsight``: the hindsight truth under ``windows``, and ``hindsight_<other>`` under
      the other rule (both need ``truth_complete``; without it only ``any`` exists);
    - ``planner``: ``planner_label`` (a planner beside the replay);
    - ``dataset_<name>``: the dataset's own label lists (``label_<name>``; null in the
      scenes without that list).
    """
    if windows not in HINDSIGHT_WINDOWS:
        raise EvaluationError(
            f"unknown hindsight window rule {windows!r}; expected one of "
            f"{', '.join(HINDSIGHT_WINDOWS)}"
        )
    refs: dict[str, np.ndarray] = {}
    missing: dict[str, str] = {}
    if "risk_survival" in df.columns:
        surv = df["risk_survival"].to_numpy()
        refs["survival"] = np.nan_to_num(surv, nan=-np.inf) >= baseline_threshold
    else:
        refs["survival"] = df["baseline"].to_numpy().astype(bool)
    any_rule = _codes(df["truth_label"])
    if "truth_complete" in df.columns:
        complete = df["truth_complete"].fill_null(False).to_numpy().astype(bool)
        rules = {"any": any_rule, "complete": np.where(complete, any_rule, -1).astype(np.int8)}
        other = next(w for w in HINDSIGHT_WINDOWS if w != windows)
        refs["hindsight"] = rules[windows]
        refs[f"hindsight_{other}"] = rules[other]
    else:
        refs["hindsight"] = any_rule
        missing["hindsight_complete"] = (
            "the table has no truth_complete column (written before complete windows were "
            "recorded): hindsight is scored with censored positives ('any'); replay the scenes"
        )
        if windows == "complete":
            missing["hindsight"] = "scored on 'any' windows: the table cannot tell complete ones"
    if "planner_label" in df.columns:
        refs["planner"] = _codes(df["planner_label"])
    else:
        missing["planner"] = (
            "no planner_label column: give the scenes with --planner NAME, or tables written "
            "by 'replay run --table T --planner NAME'"
        )
    # The converters' path-source lists (which agents got lane-graph, recorded-future or
    # straight paths) travel on /labels too, but say nothing of importance.
    labels = [
        c
        for c in df.columns
        if c.startswith("label_") and c.removeprefix("label_") not in PATH_SOURCE_LABELS
    ]
    for c in labels:
        refs[DATASET_PREFIX + c.removeprefix("label_")] = _codes(df[c])
    if not labels:
        missing["dataset labels"] = (
            "no scene carries label lists (/labels: Waymo objects_of_interest / "
            "tracks_to_predict, AV2 focal / scored)"
        )
    return refs, missing


def check_groupings(names: Sequence[str]) -> tuple[str, ...]:
    bad = [g for g in names if g not in GROUPINGS]
    if bad:
        raise EvaluationError(
            f"unknown grouping {bad[0]!r}; valid groupings: {', '.join(GROUPINGS)}"
        )
    return tuple(dict.fromkeys(names))


def evaluate_table(
    agents: pl.DataFrame,
    *,
    settings: EvaluationSettings | None = None,
    datasets: Mapping[str, str] | None = None,
    hindsight: HindsightSettings | None = None,
    inputs: Sequence[str] = (),
    presorted: bool = False,
) -> dict[str, Any]:
    """The evaluation summary of an agents table (one row per scene, frame, ego, agent).

    ``presorted``: the rows are sorted by scene, frame and ego already (stable), as
    :func:`replay.analysis.evaluation.collect.evaluation_agents` reads them: no second
    copy is made.

    ``datasets``: scene name -> dataset (default: the ``dataset`` column, else
    ``unknown``); ``hindsight``: the settings the truth columns were made with (recorded
    in the summary). Raises :class:`EvaluationError` when the table has no hindsight
    columns, or when no agent really came close (every AUC against hindsight would be
    undefined).
    """
    settings = settings or EvaluationSettings()
    groupings = check_groupings(settings.groupings)
    missing = [
        c
        for c in ("scene", "agent_id", "ego_id", "kind", *TRUTH_COLUMNS)
        if c not in agents.columns
    ]
    if missing:
        raise EvaluationError(
            f"the table has no {', '.join(missing)} column(s): it was written before the "
            "hindsight truth existed; replay the scenes again (replay run --table, or give "
            "the .mcap scenes to replay evaluate)"
        )
    present = [m for m in MODELS if f"risk_{m}" in agents.columns]
    models = list(present if settings.models is None else settings.models)
    for m in models:
        if m not in present:
            raise EvaluationError(
                f"no risk_{m} column in the table; it has: {', '.join(present) or 'none'}"
            )
    if "risk_survival" not in agents.columns and "baseline" not in agents.columns:
        raise EvaluationError("the table has neither risk_survival nor baseline")
    df = agents if presorted else agents.sort("scene", "frame", "ego_id", maintain_order=True)
    # Scene codes follow the sorted names (as np.unique numbers them): the bootstrap's
    # clusters. Labels are object arrays of shared strings (8 bytes a row; numpy's
    # fixed-width strings took 4 bytes a character a row).
    unique_scenes, scene_index = _codes_of(df["scene"].cast(pl.String))
    scenes = scene_index
    dataset = _datasets(df, datasets)
    site_names = [site_of(s) for s in unique_scenes]
    site = np.array(site_names, dtype=object)[scene_index]
    kind = _labels(df["kind"].cast(pl.String).fill_null("other"))
    agent_key = (
        df.select(pl.struct("scene", "ego_id", "agent_id").rank("dense").cast(pl.Int64))
        .to_series()
        .to_numpy()
    )
    all_refs, absent = reference_arrays(
        df, baseline_threshold=settings.baseline_threshold, windows=settings.hindsight_windows
    )
    counts = {name: reference_counts(r, agent_key, scene_index) for name, r in all_refs.items()}
    refs = {n: r for n, r in all_refs.items() if counts[n]["positive_agent_frames"] > 0}
    no_positive = {
        n: (
            f"no positive among {c['agent_frames']} agent-frames ({c['negative_agent_frames']} "
            f"negative, {c['unknown_agent_frames']} unknown): every rate against it is undefined"
        )
        for n, c in counts.items()
        if n not in refs
    }
    if not refs:
        raise EvaluationError(
            no_positive_message(
                df.height, df["scene"].n_unique(), int((all_refs["hindsight"] == -1).sum()),
                hindsight,
            )
        )  # fmt: skip
    stages = [c.removeprefix("kept_") for c in df.columns if c.startswith("kept_")]
    kept = np.column_stack([df[f"kept_{s}"].to_numpy() for s in stages]) if stages else None
    groups = {"dataset": dataset, "kind": kind, "site": site}
    calibration = calibration_sites(settings.calibration_sites, site_names)
    scores = {m: df[f"risk_{m}"].to_numpy().astype(np.float64, copy=False) for m in models}
    situations = (
        df.select(pl.struct("scene", "ego_id", "frame").rank("dense")).to_series().to_numpy()
    )
    result = evaluate_references(
        scores,
        refs,
        scenes=scenes,
        agents=agent_key,
        groups={g: groups[g] for g in groupings},
        kept=kept,
        stage_names=stages,
        sites=site,
        calibration_sites=calibration,
        situations=situations,
        targets=TPR_TARGETS,
        fpr_points=FPR_POINTS,
        n_boot=settings.n_boot,
        level=settings.level,
        seed=settings.seed,
    )
    result["references"] = {**counts, **result["references"]}
    draws = (
        bootstrap_weights(scenes, n_boot=settings.n_boot, seed=settings.seed)[1]
        if settings.n_boot > 0
        else None
    )
    distance = (
        df["distance_m"].to_numpy().astype(np.float64, copy=False)
        if "distance_m" in df.columns
        else None
    )
    budgets = {
        name: budget_recall(
            scores,
            r,
            situations=situations,
            codes=scene_index,
            distance_m=distance,
            kept_sets={"cascade": kept[:, -1]} if kept is not None else None,
            draws=draws,
            level=settings.level,
        )
        for name, r in refs.items()
    }
    short = _short_scenes(df, hindsight or HindsightSettings())
    return {
        "inputs": list(inputs),
        # how every "auc" is computed (replay stats averages per situation; issue 31)
        "auc_method": "one ROC curve pooled over every agent-frame",
        "settings": {
            **{k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(settings).items()},
            "models": models,
            "calibration_sites": calibration,
        },
        "hindsight": asdict(hindsight) if hindsight is not None else None,
        "baseline": {"model": "survival", "threshold": settings.baseline_threshold},
        "scenes": len(unique_scenes),
        "egos": int(df.select(pl.struct("scene", "ego_id").n_unique()).item()),
        "situations": int(df.select(pl.struct("scene", "ego_id", "frame").n_unique()).item()),
        "scenes_shorter_than_horizon": short,
        "operating_thresholds": {
            "tpr0.95_survival": "highest threshold keeping 95 % of survival-baseline agent-frames (pooled)",
            "tpr1_survival": "highest threshold keeping every survival-baseline agent-frame",
            "tpr0.95_hindsight": "highest threshold keeping 95 % of hindsight positives",
            "tpr1_hindsight": "highest threshold keeping every hindsight positive",
        },
        **result,
        "reference_names": list(refs),
        "references_missing": absent,
        "references_without_positives": no_positive,
        "budgets": budgets,
        "agreement": agreement(all_refs, df, agent_key),
        "composition": composition(df, all_refs),
        "track_flags": _track_flags(df, dataset),
    }


#: The states of an agent-frame under a reference, as :func:`state_codes` codes them.
STATES = {"positive": 1, "negative": 0, "unknown": -1}


def state_codes(reference: np.ndarray) -> np.ndarray:
    """``(A,)`` int8 state codes (:data:`STATES`) of label codes or booleans (one byte a
    row: the names as strings took 32 bytes a row per reference)."""
    r = np.asarray(reference)
    if r.dtype == bool:
        return r.astype(np.int8)
    return np.where(r == 1, 1, np.where(r == 0, 0, -1)).astype(np.int8)


def _count(mask: np.ndarray, agent_key: np.ndarray) -> dict[str, int]:
    return {
        "agent_frames": int(mask.sum()),
        "agents": int(np.unique(agent_key[mask]).size),  # distinct (scene, ego, agent)
    }


def agreement(
    refs: Mapping[str, np.ndarray], df: pl.DataFrame, agent_key: np.ndarray
) -> dict[str, Any]:
    """How the references agree, as counts: every pair's 3 x 3 table of agent-frames
    (positive / negative / unknown under each), and for the planner-important agents
    what hindsight says and why (the ego yielded, the window was censored, a track was
    flagged). Agent counts are distinct (scene, ego, agent)."""
    names = list(refs)
    states = {n: state_codes(refs[n]) for n in names}
    pairs = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            table = {
                f"{sa}/{sb}": int(((states[a] == STATES[sa]) & (states[b] == STATES[sb])).sum())
                for sa in ("positive", "negative", "unknown")
                for sb in ("positive", "negative", "unknown")
            }
            pairs.append({"a": a, "b": b, "counts": table})
    out: dict[str, Any] = {"pairs": pairs}
    n = df.height
    yielded = (
        df["truth_yielded"].fill_null(False).to_numpy().astype(bool)
        if "truth_yielded" in df.columns
        else np.zeros(n, bool)
    )
    complete = (
        df["truth_complete"].fill_null(False).to_numpy().astype(bool)
        if "truth_complete" in df.columns
        else np.zeros(n, bool)
    )
    track_ok = (
        df["track_ok"].fill_null(True).to_numpy().astype(bool)
        if "track_ok" in df.columns
        else np.ones(n, bool)
    )
    out["has_yielded"] = "truth_yielded" in df.columns
    hind = [h for h in names if h.startswith("hindsight")]
    out["yielded"] = {
        "all": _count(yielded, agent_key),
        **{
            h: {st: _count(yielded & (states[h] == STATES[st]), agent_key) for st in
                ("positive", "negative", "unknown")}
            for h in hind
        },
    }  # fmt: skip
    if "planner" in refs:
        important = states["planner"] == STATES["positive"]
        block: dict[str, Any] = {"important": _count(important, agent_key)}
        for h in hind:
            pos = important & (states[h] == STATES["positive"])
            neg = important & (states[h] == STATES["negative"])
            unk = important & (states[h] == STATES["unknown"])
            block[h] = {
                "positive": _count(pos, agent_key),
                "negative": _count(neg, agent_key),
                "negative_yielded": _count(neg & yielded, agent_key),
                "unknown": _count(unk, agent_key),
                "unknown_yielded": _count(unk & yielded, agent_key),
                "unknown_censored": _count(unk & ~complete, agent_key),
                "unknown_track_flagged": _count(unk & ~track_ok, agent_key),
            }
        out["planner"] = block
    return out


def composition(df: pl.DataFrame, refs: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """What the positives and negatives of each hindsight rule are made of: agent-frames,
    median time since the scene's first frame (s), median agent speed (m/s), the share of
    standing agents (speed < 0.5 m/s) and the share from frames in the scene's first 2 s."""
    t0 = df.select(pl.col("t_s") - pl.col("t_s").min().over("scene")).to_series().to_numpy()
    speed = df["speed_mps"].to_numpy().astype(np.float64) if "speed_mps" in df.columns else None
    out: dict[str, Any] = {}
    for name, r in refs.items():
        if not name.startswith("hindsight"):
            continue
        st = state_codes(r)
        out[name] = {}
        for label in ("positive", "negative"):
            m = st == STATES[label]
            block: dict[str, Any] = {"agent_frames": int(m.sum())}
            if m.any():
                block["median_time_in_scene_s"] = float(np.median(t0[m]))
                block["share_first_2s"] = float((t0[m] <= 2.0 + 1e-9).mean())
                if speed is not None:
                    block["median_speed_mps"] = float(np.nanmedian(speed[m]))
                    block["share_standing"] = float((speed[m] < 0.5).mean())
            out[name][label] = block
    return out


def _track_flags(df: pl.DataFrame, dataset: np.ndarray) -> dict[str, Any]:
    """Rows whose ego or agent track is inconsistent in the window (kept out of the
    truth): count, share, distinct agents, per kind and the share per dataset."""
    if "track_ok" not in df.columns:
        return {"available": False}
    bad = ~df["track_ok"].fill_null(True)
    bad_np = bad.to_numpy().astype(bool)
    share_by_dataset = {str(d): float(bad_np[dataset == d].mean()) for d in np.unique(dataset)}
    flagged = df.filter(bad)
    return {
        "available": True,
        "agent_frames": int(flagged.height),
        "share": float(flagged.height / max(1, df.height)),
        "agents": int(flagged.select(pl.struct("scene", "agent_id").n_unique()).item())
        if flagged.height
        else 0,
        "scenes": int(flagged["scene"].n_unique()) if flagged.height else 0,
        "by_kind": {
            str(k): int(v)
            for k, v in flagged.group_by(pl.col("kind").cast(pl.String)).len().iter_rows()
        },
        "share_by_dataset": share_by_dataset,
    }


def _codes_of(column: pl.Series) -> tuple[list[str], np.ndarray]:
    """The sorted distinct strings of ``column`` and each row's index among them."""
    names = sorted(column.unique().to_list())
    codes = column.replace_strict(names, list(range(len(names))), return_dtype=pl.Int64)
    return names, codes.to_numpy()


def _labels(column: pl.Series) -> np.ndarray:
    """``column`` (strings, no nulls) as an object array of one string per distinct value."""
    names, codes = _codes_of(column)
    return np.array(names, dtype=object)[codes]


def _datasets(df: pl.DataFrame, datasets: Mapping[str, str] | None) -> np.ndarray:
    if datasets:
        scene = df["scene"].cast(pl.String)
        return _labels(scene.replace_strict(dict(datasets), default="unknown"))
    if "dataset" in df.columns:
        return _labels(df["dataset"].cast(pl.String).fill_null("unknown"))
    return np.full(df.height, "unknown", dtype=object)


def no_positive_message(
    agent_frames: int, scenes: int, censored: int, hs: HindsightSettings | None
) -> str:
    """The error when no agent came close in hindsight."""
    hs = hs or HindsightSettings()
    return (
        f"no agent came close in hindsight (box gap <= {hs.gap_m:g} m or PET <= "
        f"{hs.pet_s:g} s within {hs.horizon_s:g} s) in {agent_frames} agent-frames of "
        f"{scenes} scene(s) ({censored} censored): every "
        "rate against hindsight is undefined; add scenes or loosen --truth-gap / --truth-pet"
    )


def _short_scenes(df: pl.DataFrame, hs: HindsightSettings) -> list[str]:
    """Scenes whose recorded span is shorter than the horizon (every window censored)."""
    span = df.group_by("scene").agg((pl.col("t_s").max() - pl.col("t_s").min()).alias("span"))
    return sorted(span.filter(pl.col("span") < hs.horizon_s - 1e-9)["scene"].to_list())
