"""Outcome evaluation of a corpus: every model against the survival baseline and against
what really happened (the hindsight truth), with scene-bootstrap intervals.

The input is an agents table (the columns of ``replay run --table`` plus ``scene``, as
``replay stats`` collects them, see :func:`replay.analysis.inputs.collect`);
:func:`evaluate_table` turns it into arrays and calls the pure
:func:`risk.evaluation.evaluate_references`; :func:`write_evaluation` writes
``summary.json``, tables and plots. ``docs/evaluation.md`` describes every field.

Replaying scenes or reading tables first (``replay stats``' input collection,
:mod:`replay.analysis.inputs`) is :func:`evaluate_inputs`.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import re
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import polars as pl

from outputs.atomic import atomic_output
from replay.analysis.evaluation_plots import plot_evaluation
from replay.analysis.inputs import collect, resolve_inputs, scene_names
from replay.core.engine import Stride
from replay.errors import ReplayError
from risk.cascade import CascadeConfig
from risk.evaluation import FPR_POINTS, TPR_TARGETS, evaluate_references, pooled_roc
from risk.hindsight import HindsightSettings
from risk.prediction import PredictionSettings
from risk.registry import BASELINE_THRESHOLD, MODELS

#: Groupings the evaluation can break results down by.
GROUPINGS = ("dataset", "kind", "site")
DEFAULT_GROUPINGS = ("dataset", "kind")
REFERENCES = ("survival", "hindsight")
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
) -> dict[str, Any]:
    """The evaluation summary of an agents table (one row per scene, frame, ego, agent).

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
    df = agents.sort("scene", "frame", "ego_id", maintain_order=True)
    scenes = df["scene"].cast(pl.String).to_numpy()
    dataset = _datasets(df, datasets)
    unique_scenes, scene_index = np.unique(scenes, return_inverse=True)
    site = np.array([site_of(s) for s in unique_scenes], dtype=str)[scene_index]
    kind = df["kind"].cast(pl.String).fill_null("other").to_numpy().astype(str)
    agent_key = (
        df.select(pl.struct("scene", "ego_id", "agent_id").rank("dense").cast(pl.Int64))
        .to_series()
        .to_numpy()
    )
    if "risk_survival" in df.columns:
        surv = df["risk_survival"].to_numpy()
        baseline = np.nan_to_num(surv, nan=-np.inf) >= settings.baseline_threshold
    else:
        baseline = df["baseline"].to_numpy().astype(bool)
    label = df["truth_label"]
    truth = np.where(
        label.is_null().to_numpy(), -1, label.fill_null(False).to_numpy().astype(np.int8)
    )
    truth = truth.astype(np.int8)
    if not (truth == 1).any():
        raise EvaluationError(_no_positive_message(df, truth, hindsight))
    stages = [c.removeprefix("kept_") for c in df.columns if c.startswith("kept_")]
    kept = np.column_stack([df[f"kept_{s}"].to_numpy() for s in stages]) if stages else None
    groups = {"dataset": dataset, "kind": kind, "site": site}
    calibration = (
        list(settings.calibration_sites)
        if settings.calibration_sites is not None
        else default_calibration_sites(list(site))
    )
    unknown_sites = sorted(set(calibration) - set(site))
    if unknown_sites:
        raise EvaluationError(
            f"unknown calibration site {unknown_sites[0]!r}; the sites are: "
            f"{', '.join(sorted(set(site)))}"
        )
    scores = {m: df[f"risk_{m}"].to_numpy().astype(np.float64) for m in models}
    result = evaluate_references(
        scores,
        {"survival": baseline, "hindsight": truth},
        scenes=scenes,
        agents=agent_key,
        groups={g: groups[g] for g in groupings},
        kept=kept,
        stage_names=stages,
        sites=site,
        calibration_sites=calibration,
        situations=df.select(pl.struct("scene", "ego_id", "frame").rank("dense"))
        .to_series()
        .to_numpy(),
        targets=TPR_TARGETS,
        fpr_points=FPR_POINTS,
        n_boot=settings.n_boot,
        level=settings.level,
        seed=settings.seed,
    )
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
        "scenes": int(np.unique(scenes).size),
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
    }


def _datasets(df: pl.DataFrame, datasets: Mapping[str, str] | None) -> np.ndarray:
    if datasets:
        return (
            df["scene"].cast(pl.String).replace_strict(dict(datasets), default="unknown").to_numpy()
        ).astype(str)
    if "dataset" in df.columns:
        return df["dataset"].cast(pl.String).fill_null("unknown").to_numpy().astype(str)
    return np.full(df.height, "unknown")


def _no_positive_message(df: pl.DataFrame, truth: np.ndarray, hs: HindsightSettings | None) -> str:
    hs = hs or HindsightSettings()
    return (
        f"no agent came close in hindsight (box gap <= {hs.gap_m:g} m or PET <= "
        f"{hs.pet_s:g} s within {hs.horizon_s:g} s) in {df.height} agent-frames of "
        f"{df['scene'].n_unique()} scene(s) ({int((truth == -1).sum())} censored): every "
        "rate against hindsight is undefined; add scenes or loosen --truth-gap / --truth-pet"
    )


def _short_scenes(df: pl.DataFrame, hs: HindsightSettings) -> list[str]:
    """Scenes whose recorded span is shorter than the horizon (every window censored)."""
    span = df.group_by("scene").agg((pl.col("t_s").max() - pl.col("t_s").min()).alias("span"))
    return sorted(span.filter(pl.col("span") < hs.horizon_s - 1e-9)["scene"].to_list())


# ---------------------------------------------------------------------- output
def positives_table(
    agents: pl.DataFrame, datasets: Mapping[str, str] | None = None
) -> pl.DataFrame:
    """One row per distinct agent that really came close (scene, ego, agent): its kind,
    dataset, first and last frame labelled positive, least gap and PET, and the cascade
    stage that dropped it at a positive frame (null: kept at every positive frame)."""
    pos = agents.filter(pl.col("truth_label").fill_null(False))
    if pos.height == 0:
        return pl.DataFrame()
    dropped = (
        pl.col("dropped_by").cast(pl.String).drop_nulls().first()
        if "dropped_by" in pos.columns
        else pl.lit(None, dtype=pl.String)
    )
    out = (
        pos.group_by("scene", "ego_id", "agent_id", maintain_order=True)
        .agg(
            pl.col("kind").cast(pl.String).first(),
            pl.col("frame").min().alias("first_frame"),
            pl.col("frame").max().alias("last_frame"),
            pl.len().alias("positive_frames"),
            pl.col("truth_gap_m").min().alias("min_gap_m"),
            pl.col("truth_pet_s").min().alias("min_pet_s"),
            dropped.alias("dropped_by"),
        )
        .sort("scene", "ego_id", "agent_id")
    )
    ds = dict(datasets or {})
    return out.with_columns(
        pl.col("scene")
        .replace_strict(ds, default="unknown", return_dtype=pl.String)
        .alias("dataset")
    )


def roc_table(
    agents: pl.DataFrame, models: Sequence[str], summary: Mapping[str, Any]
) -> pl.DataFrame:
    """Pooled ROC points of every model against both references (at most
    :data:`ROC_TABLE_POINTS` per curve, evenly spread; the ends are kept)."""
    truth = agents["truth_label"]
    refs = {
        "survival": np.nan_to_num(agents["risk_survival"].to_numpy(), nan=-np.inf)
        >= summary["baseline"]["threshold"]
        if "risk_survival" in agents.columns
        else agents["baseline"].to_numpy().astype(bool),
        "hindsight": np.where(
            truth.is_null().to_numpy(), -1, truth.fill_null(False).to_numpy().astype(np.int8)
        ).astype(np.int8),
    }
    frames = []
    for m in models:
        s = agents[f"risk_{m}"].to_numpy().astype(np.float64)
        for name, ref in refs.items():
            roc = pooled_roc(s, ref)
            k = roc.thresholds.size
            idx = (
                np.unique(np.linspace(0, k - 1, min(k, ROC_TABLE_POINTS)).round().astype(int))
                if k
                else np.empty(0, int)
            )
            frames.append(
                pl.DataFrame(
                    {
                        "model": [m] * idx.size,
                        "reference": [name] * idx.size,
                        "threshold": roc.thresholds[idx],
                        "tpr": roc.tpr[idx],
                        "fpr": roc.fpr[idx],
                    }
                )
            )
    return pl.concat(frames) if frames else pl.DataFrame()


def miss_table(summary: Mapping[str, Any]) -> pl.DataFrame:
    """Miss rates as rows: group (``all`` or grouping=value) x model x reference x
    threshold, with the interval, missed agent-frames and agents, kept share."""
    rows = []

    def add(group: str, block: Mapping[str, Any]) -> None:
        for model, per_ref in block["models"].items():
            for ref, ev in per_ref.items():
                for thr, mr in ev["miss_rate"].items():
                    ci = mr.get("ci", [None, None])
                    rows.append(
                        {
                            "group": group, "model": model, "reference": ref,
                            "operating_threshold": thr, "threshold": mr["threshold"],
                            "positives": ev["positives"], "miss_rate": mr["value"],
                            "ci_lo": ci[0], "ci_hi": ci[1],
                            "missed_agent_frames": mr["missed_agent_frames"],
                            "missed_agents": mr["missed_agents"], "kept_share": mr["kept_share"],
                            "auc": ev["auc"]["value"],
                        }
                    )  # fmt: skip

    add("all", summary)
    for grouping, blocks in summary.get("by", {}).items():
        for value, block in blocks.items():
            add(f"{grouping}={value}", block)
    return pl.DataFrame(rows, infer_schema_length=None)


#: Tables that ``replay evaluate`` writes into its output folder (with the sweep's):
#: never read back as inputs from there.
EVALUATION_TABLES = (
    "roc", "miss_rates", "positives", "sensitivity", "sensitivity_ranking",
    "sensitivity_findings",
)  # fmt: skip


def write_evaluation(
    summary: Mapping[str, Any],
    agents: pl.DataFrame,
    out_dir: str | os.PathLike[str],
    *,
    datasets: Mapping[str, str] | None = None,
    plots: bool = True,
) -> dict[str, pathlib.Path]:
    """``summary.json``, the tables (``roc``, ``miss_rates``, ``positives``, Parquet and
    CSV) and the plots into ``out_dir``, each file atomically. Returns name -> path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    models = summary["settings"]["models"]
    tables = {
        "roc": roc_table(agents, models, summary),
        "miss_rates": miss_table(summary),
        "positives": positives_table(agents, datasets),
    }
    for name, df in tables.items():
        for suffix in (".parquet", ".csv"):
            path = out / f"{name}{suffix}"
            with atomic_output(path) as tmp:
                if suffix == ".csv":
                    df.write_csv(tmp)
                else:
                    df.write_parquet(tmp, compression="zstd")
            written[path.name] = path
    if plots:
        written.update(plot_evaluation(summary, tables["roc"], out, threshold=HEADLINE_THRESHOLD))
    path = out / "summary.json"
    text = json.dumps(
        _jsonable({**summary, "files": sorted([*written, "summary.json"])}),
        indent=2,
        allow_nan=False,
    )
    with atomic_output(path) as tmp:
        pathlib.Path(tmp).write_text(text + "\n", encoding="utf-8")
    written[path.name] = path
    return written


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


# ---------------------------------------------------------------------- text
#: How these AUCs are computed, and why ``replay stats``' differ (issue 31).
EVALUATION_AUC_NOTE = (
    "AUC: one ROC curve pooled over every agent-frame of every scene; 'replay stats'"
    " averages per-situation curves (the paper's measure), so its AUCs differ"
)


def format_evaluation(summary: Mapping[str, Any]) -> str:
    """The end-of-run text: counts, each model's AUC against both references with
    intervals, and its miss rate against hindsight at the headline threshold."""
    ref = summary["references"]
    h, s = ref["hindsight"], ref["survival"]
    level = summary["bootstrap"]["level"]
    lines = [
        f"{summary['scenes']} scenes, {summary['egos']} egos, {summary['situations']} "
        f"situations, {h['agent_frames']} agent-frames",
        f"Hindsight: {h['positive_agent_frames']} positive agent-frames ({h['positive_agents']} "
        f"distinct agents, in {h['scenes_with_positive']} scenes), {h['negative_agent_frames']} "
        f"negative, {h['unknown_agent_frames']} censored (left out)",
        f"Survival baseline: {s['positive_agent_frames']} important agent-frames "
        f"({s['positive_agents']} distinct agents)",
    ]
    short = summary.get("scenes_shorter_than_horizon") or []
    if short:
        hz = (summary.get("hindsight") or {}).get("horizon_s", HindsightSettings().horizon_s)
        shown = ", ".join(short[:5]) + (", ..." if len(short) > 5 else "")
        lines.append(
            f"Note: {len(short)} scene(s) shorter than the {hz:g} s horizon are evaluated on "
            f"censored frames only (their positives count, their negatives are unknown): {shown}"
        )
    pct = f"{100 * level:g} %"
    lines.append(EVALUATION_AUC_NOTE)
    lines.append(
        f"  {'model':<22}{'AUC survival':>14} {'[' + pct + ']':<15}{'AUC hindsight':>14} "
        f"{'[' + pct + ']':<15}{'miss (hindsight) @ keep all survival':>38}"
    )
    for model, per_ref in summary["models"].items():
        a_s, a_h = per_ref["survival"]["auc"], per_ref["hindsight"]["auc"]
        miss = per_ref["hindsight"]["miss_rate"].get(HEADLINE_THRESHOLD, {})
        lines.append(
            f"  {model:<22}{_f(a_s['value']):>14} {_ci(a_s):<15}{_f(a_h['value']):>14} "
            f"{_ci(a_h):<15}{_f(miss.get('value')):>12} {_ci(miss):<15} "
            f"{miss.get('missed_agents', 0)} agents, keeps {_f(miss.get('kept_share'))}"
        )
    cascade = summary.get("cascade", {}).get("hindsight")
    if cascade:
        parts = ", ".join(
            f"{st['stage']} {st['missed_agent_frames']} ({st['missed_agents']} agents)"
            for st in cascade
        )
        lines.append(f"Cascade misses against hindsight (cumulative agent-frames): {parts}")
    return "\n".join(lines)


def _f(value: Any) -> str:
    return (
        "n/a"
        if value is None or (isinstance(value, float) and not math.isfinite(value))
        else f"{value:.3f}"
    )


def _ci(block: Mapping[str, Any]) -> str:
    ci = block.get("ci")
    if not ci or ci[0] is None or not math.isfinite(ci[0]):
        return ""
    return f"[{ci[0]:.3f}, {ci[1]:.3f}]"


# ---------------------------------------------------------------------- inputs
def evaluate_inputs(
    paths: Sequence[str | os.PathLike[str]],
    *,
    cascade: CascadeConfig | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    settings: EvaluationSettings | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: int | Stride = 1,
) -> dict[str, Any]:
    """Replay (scenes) or read (tables) the inputs and evaluate them; the summary dict.

    ``params`` (model name -> parameters) and ``prediction`` go to every model evaluation
    of the replayed scenes; tables are read as they were written. This is what
    ``replay evaluate`` runs, without writing files."""
    agents, datasets, hs = collect_agents(
        paths, cascade=cascade, params=params, prediction=prediction, hindsight=hindsight,
        workers=workers, progress=progress, ego=ego, every=every,
    )  # fmt: skip
    return evaluate_table(
        agents, settings=settings, datasets=datasets, hindsight=hs,
        inputs=[str(p) for p in paths],
    )  # fmt: skip


def collect_agents(
    paths: Sequence[str | os.PathLike[str]],
    *,
    cascade: CascadeConfig | None = None,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: int | Stride = 1,
    models: Sequence[str] | None = None,
    output_dir: str | os.PathLike[str] | None = None,
) -> tuple[pl.DataFrame, dict[str, str], HindsightSettings]:
    """The agents table of scenes, tables or folders (as ``replay stats`` reads them),
    the dataset of each scene (the name of the folder its file is in) and the hindsight
    settings of its truth columns. ``models``: the risk columns to compute (default: all)."""
    found = resolve_inputs(
        [pathlib.Path(p) for p in paths],
        output_dir=None if output_dir is None else pathlib.Path(output_dir),
        output_stems=EVALUATION_TABLES,
    )
    if found.tables and hindsight is not None and hindsight != HindsightSettings():
        raise EvaluationError(
            "tables carry the hindsight truth they were written with; to evaluate other "
            "--truth-* settings give the .mcap scenes"
        )
    hs = hindsight or HindsightSettings()
    agents, _, _, _ = collect(
        found,
        cascade or CascadeConfig.default(),
        models=models,
        workers=workers,
        progress=progress,
        params=params,
        prediction=prediction,
        hindsight=hs,
        ego=ego,
        every=Stride.of(every),
    )
    files = [*found.scenes, *found.tables]
    names = scene_names(files)
    datasets = {n: p.absolute().parent.name for n, p in zip(names, files, strict=True)}
    if "scene" in agents.columns:  # merged tables name their scenes themselves
        table_dirs = {p.absolute().parent.name for p in found.tables}
        for s in agents["scene"].unique().to_list():
            if s not in datasets and len(table_dirs) == 1:
                datasets[s] = next(iter(table_dirs))
    return agents, datasets, hs
