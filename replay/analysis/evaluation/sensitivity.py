"""The sensitivity sweep: the same outcome evaluation over the survival baseline's own
choices (issue 12 part 3), and which findings flip.

Each variant is a set of :mod:`risk.settings` keys on top of the defaults. A variant that
only moves ``baseline.threshold`` re-thresholds the defaults' part files (no replay); any
other variant replays the scenes evaluating only the models its keys change
(:func:`affected_models`) and takes every other model's risks from the defaults' parts.
Every variant is evaluated by the streamed evaluation, one scene's rows at a time: the
driver never holds a variant's whole table (issue 38).
``docs/evaluation.md`` (Sensitivity) describes the output.
"""

from __future__ import annotations

import math
import os
import pathlib
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import polars as pl
from scipy import stats as scipy_stats

from outputs.atomic import atomic_output
from replay.analysis.evaluation.corpus import (
    REFERENCES,
    EvaluationError,
    EvaluationSettings,
)
from replay.analysis.evaluation.plots import plot_sensitivity
from replay.analysis.evaluation.streaming import StreamSettings, evaluate_parts
from replay.analysis.stats.collect import TablesSettings, tables_job
from replay.core.engine import Stride
from replay.jobs import JobReport, SceneRef, resolve_inputs, run_jobs, scene_refs
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings
from risk.registry import BASELINE_MODEL, MODELS
from risk.settings import BASELINE_KEY, KINDS, parse_settings

#: Models that use no prediction (a horizon or step change leaves them alone).
PREDICTION_FREE = ("current_distance",)
#: Models that use the position uncertainty (prediction.<kind>.* keys).
UNCERTAINTY_MODELS = ("circles", "gaussian", "survival")
#: Models with the closest-encounter rule (``encounter_time_max_s``).
ENCOUNTER_MODELS = ("closest_encounter", "headway", "headway_2d")
#: The models ranked (survival is the survival reference itself).
RANKED = tuple(m for m in MODELS if m != BASELINE_MODEL)
KEYS = ("scene", "ego_id", "frame", "agent_id")


@dataclass(frozen=True)
class Variant:
    """One point of the sweep: a group (the choice varied), a label and its settings."""

    group: str
    label: str
    settings: Mapping[str, Any] = field(default_factory=dict)


def _all_kinds(**values: float) -> dict[str, float]:
    return {f"prediction.{k}.{f}": v for k in KINDS for f, v in values.items()}


def _growth_scaled(factor: float) -> dict[str, float]:
    table = parse_settings().prediction.uncertainty
    out: dict[str, float] = {}
    for k in KINDS:
        row = getattr(table, k)
        out[f"prediction.{k}.growth_lon"] = row.growth_lon * factor
        out[f"prediction.{k}.growth_lat"] = row.growth_lat * factor
    return out


def default_variants() -> list[Variant]:
    """The sweep of issue 12: survival threshold, tau_esc, uncertainty growth (with time
    growth for agents that stand now), horizon, closest-encounter rule, circle radii."""
    v = [
        Variant("baseline threshold", f"{t:g}", {BASELINE_KEY: t})
        for t in (1e-20, 1e-15, 1e-10, 1e-6, 1e-4)
    ]
    v += [Variant("tau_esc", f"{t:g} s", {"survival.escape_time_s": t}) for t in (0.2, 0.8, 1.6)]
    v += [
        Variant("uncertainty growth", "x0.5", _growth_scaled(0.5)),
        Variant("uncertainty growth", "x2", _growth_scaled(2.0)),
        Variant("uncertainty growth", "time 0.1 m/s",
                _all_kinds(time_growth_lon_mps=0.1, time_growth_lat_mps=0.1)),
        Variant("uncertainty growth", "time 0.3 m/s",
                _all_kinds(time_growth_lon_mps=0.3, time_growth_lat_mps=0.3)),
    ]  # fmt: skip
    v += [Variant("horizon", f"{h:g} s", {"prediction.horizon_s": h}) for h in (4.0, 8.0)]
    v.append(
        Variant("closest-encounter rule", "keep d_E",
                {f"{m}.encounter_time_max_s": math.inf for m in ENCOUNTER_MODELS})
    )  # fmt: skip
    v += [
        Variant("circle radii", "ego width", {"circles.radius_rule": "width"}),
        Variant("circle radii", "sigma_scale 1", {"circles.sigma_scale": 1.0}),
        Variant("circle radii", "sigma_scale 0", {"circles.sigma_scale": 0.0}),
    ]
    return v


def affected_models(settings: Mapping[str, Any]) -> list[str]:
    """The models whose risks the settings change (registry order); none for a
    baseline threshold alone."""
    hit: set[str] = set()
    for key in settings:
        head, _, rest = key.partition(".")
        if key == BASELINE_KEY:
            continue
        if head == "prediction":
            if "." in rest:
                hit.update(UNCERTAINTY_MODELS)
            else:
                hit.update(m for m in MODELS if m not in PREDICTION_FREE)
        else:
            hit.add(head)
    return [m for m in MODELS if m in hit]


def replace_risks(base: pl.DataFrame, new: pl.DataFrame, models: Sequence[str]) -> pl.DataFrame:
    """``base`` with the ``risk_<model>`` columns of ``new`` (the same rows, matched on
    scene, ego, frame and agent)."""
    cols = [f"risk_{m}" for m in models]
    keys = [k for k in KEYS if k in base.columns]
    joined = base.drop(cols).join(new.select([*keys, *cols]), on=keys, how="left")
    if joined.height != base.height or joined.select(pl.col(cols[0]).is_null().all()).item():
        raise EvaluationError("the variant's replay has other rows than the default's")
    return joined.select(base.columns)


@dataclass(frozen=True)
class SweepResult:
    """Per variant: AUC of every model against both references, rank correlation and
    flipped findings (see :func:`sweep_table`)."""

    rows: pl.DataFrame  # group, variant, settings, model, reference, auc, ci_lo, ci_hi, rank
    variants: pl.DataFrame  # group, variant, reference, spearman, kendall, flips, recomputed
    findings: pl.DataFrame  # group, variant, reference, finding, default, variant
    time_s: dict[str, float]


def _auc_rows(summary: Mapping[str, Any], variant: Variant) -> list[dict[str, Any]]:
    rows = []
    for ref in REFERENCES:
        # A reference without positives in this variant is left out of the summary
        # (reported there as such): its AUCs are undefined here.
        ranked = {
            m: summary["models"][m].get(ref, {"auc": {"value": None}})["auc"]
            for m in summary["models"]
        }
        values = {m: a["value"] for m, a in ranked.items() if m in RANKED}
        order = sorted(values, key=lambda m: -_num(values[m]))
        for m, a in ranked.items():
            ci = a.get("ci") or [None, None]
            rows.append({
                "group": variant.group, "variant": variant.label,
                "settings": ", ".join(f"{k}={v}" for k, v in variant.settings.items()) or "defaults",
                "model": m, "reference": ref, "auc": _num(a["value"]),
                "ci_lo": _num(ci[0]), "ci_hi": _num(ci[1]),
                "rank": order.index(m) + 1 if m in order else None,
            })  # fmt: skip
    return rows


def _num(x: Any) -> float:
    return float("nan") if x is None else float(x)


#: The findings checked per variant: name -> test on {model: (auc, lo, hi)} of one reference.
Findings = Callable[[Mapping[str, tuple[float, float, float]]], bool]


def _findings() -> dict[str, Findings]:
    def worst(m: str) -> Findings:
        return lambda a: min(RANKED, key=lambda x: a[x][0]) == m

    def best(m: str) -> Findings:
        return lambda a: max(RANKED, key=lambda x: a[x][0]) == m

    return {
        "current distance is the worst": worst("current_distance"),
        "2D Gaussians are closest to survival (best of the others)": best("gaussian"),
        "trajectory distance above closest encounter and 2D headway": lambda a: (
            a["trajectory_distance"][0] > a["closest_encounter"][0]
            and a["trajectory_distance"][0] > a["headway_2d"][0]
        ),
        "closest encounter below trajectory distance": lambda a: (
            a["closest_encounter"][0] < a["trajectory_distance"][0]
        ),
    }


FINDINGS = _findings()


def _separated(a: Mapping[str, tuple[float, float, float]]) -> set[tuple[str, str]]:
    """Ordered pairs (higher, lower) whose AUC intervals do not overlap."""
    out = set()
    for x in RANKED:
        for y in RANKED:
            if x != y and a[x][1] > a[y][2]:
                out.add((x, y))
    return out


def sweep_table(
    summaries: Sequence[tuple[Variant, Mapping[str, Any], Sequence[str]]],
) -> tuple[pl.DataFrame, pl.DataFrame, pl.DataFrame]:
    """Rows, per-variant rank correlations and finding flips of evaluated variants; the
    first entry is the defaults."""
    rows: list[dict[str, Any]] = []
    for variant, summary, _ in summaries:
        rows += _auc_rows(summary, variant)
    table = pl.DataFrame(rows)

    def aucs(label: str, group: str, ref: str) -> dict[str, tuple[float, float, float]]:
        sub = table.filter(
            (pl.col("variant") == label) & (pl.col("group") == group) & (pl.col("reference") == ref)
        )
        return {r["model"]: (r["auc"], r["ci_lo"], r["ci_hi"]) for r in sub.iter_rows(named=True)}

    d_var = summaries[0][0]
    per_variant: list[dict[str, Any]] = []
    flips: list[dict[str, Any]] = []
    for variant, _, recomputed in summaries:
        for ref in REFERENCES:
            base, now = aucs(d_var.label, d_var.group, ref), aucs(variant.label, variant.group, ref)
            x = np.array([base[m][0] for m in RANKED])
            y = np.array([now[m][0] for m in RANKED])
            ok = np.isfinite(x) & np.isfinite(y)
            rho = scipy_stats.spearmanr(x[ok], y[ok]).statistic if ok.sum() > 2 else math.nan
            tau = scipy_stats.kendalltau(x[ok], y[ok]).statistic if ok.sum() > 2 else math.nan
            n_flips = 0
            for name, test in FINDINGS.items():
                before, after = bool(test(base)), bool(test(now))
                if before != after:
                    n_flips += 1
                flips.append({
                    "group": variant.group, "variant": variant.label, "reference": ref,
                    "finding": name, "default": before, "variant_holds": after,
                    "flipped": before != after,
                })  # fmt: skip
            sep_b, sep_n = _separated(base), _separated(now)
            for hi, lo in sorted(sep_b ^ sep_n):
                if (lo, hi) in sep_b and (hi, lo) in sep_n:
                    continue  # a reversal shows once, from the default's side
                n_flips += 1
                flips.append({
                    "group": variant.group, "variant": variant.label, "reference": ref,
                    "finding": f"{hi} above {lo}, intervals apart",
                    "default": (hi, lo) in sep_b, "variant_holds": (hi, lo) in sep_n,
                    "flipped": True,
                })  # fmt: skip
            per_variant.append({
                "group": variant.group, "variant": variant.label, "reference": ref,
                "spearman": float(rho), "kendall": float(tau), "flips": n_flips,
                "recomputed": ", ".join(recomputed) or "none (re-threshold)",
            })  # fmt: skip
    return table, pl.DataFrame(per_variant), pl.DataFrame(flips)


def run_sweep(
    paths: Sequence[Any],
    *,
    defaults: JobReport | None = None,
    cascade: CascadeConfig | None = None,
    hindsight: HindsightSettings | None = None,
    settings: EvaluationSettings | None = None,
    variants: Sequence[Variant] | None = None,
    workers: int = 1,
    progress: bool = False,
    ego: int | str | None = None,
    every: int | Stride = 1,
    datasets: Mapping[str, str] | None = None,
    engine: str = "local",
    ray_address: str | None = None,
) -> SweepResult:
    """Evaluate the defaults and every variant on the same inputs, each by the streamed
    evaluation (:func:`replay.analysis.evaluation.streaming.evaluate_parts`: one scene's
    rows at a time, issue 38).

    ``defaults`` (with ``datasets``): the defaults' run when the caller already has it
    (``replay evaluate`` does: its part files are read, not replayed), else the scenes
    are replayed once. A variant that changes models replays the scenes on ``engine``
    into a scratch folder, and each scene's part is the defaults' part with those
    models' risks replaced (:func:`variant_parts`)."""
    cascade = cascade or CascadeConfig.default()
    settings = settings or EvaluationSettings()
    variants = list(default_variants() if variants is None else variants)
    hs = hindsight or HindsightSettings()
    times: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="replay-sweep-") as scratch:
        work = pathlib.Path(scratch)

        def replay(
            job_cascade: CascadeConfig,
            models: Sequence[str] | None,
            name: str,
            refs: Sequence[SceneRef],
        ) -> JobReport:
            job = tables_job(TablesSettings(
                cascade=job_cascade, models=None if models is None else tuple(models), ego=ego,
                every=Stride.of(every), hindsight=hs,
            ))  # fmt: skip
            report = run_jobs(
                job, refs, work / name, engine=engine, workers=workers,
                ray_address=ray_address, progress=progress, desc=f"sensitivity: {name}",
            )  # fmt: skip
            if report.failures:
                first = report.failures[0]
                raise EvaluationError(f"sensitivity ({name}): {first.scene} failed: {first.reason}")
            return report

        start = time.perf_counter()
        if defaults is None:
            found = resolve_inputs([pathlib.Path(p) for p in paths])
            if found.tables:
                raise EvaluationError("the sensitivity sweep replays scenes; give .mcap scenes")
            refs = scene_refs(found)
            if not refs:
                raise EvaluationError("no scene to replay")
            defaults = replay(cascade, None, "defaults", refs)
            datasets = {r.key: r.dataset for r in refs}
        default_parts = {d.ref.key: pathlib.Path(d.tables["agents"]) for d in defaults.done}
        refs = [d.ref for d in defaults.done]
        times["defaults"] = time.perf_counter() - start
        base_threshold = settings.baseline_threshold

        def evaluate(parts: Sequence[pathlib.Path], threshold: float) -> dict[str, Any]:
            variant_settings = replace(settings, baseline_threshold=threshold)
            return evaluate_parts(
                parts, StreamSettings.of(variant_settings, hs), datasets=datasets,
                hindsight=hs, evaluation=variant_settings,
            ).summary  # fmt: skip

        ordered = [default_parts[k] for k in sorted(default_parts)]
        defaults_variant = Variant("defaults", "paper", {})
        done: list[tuple[Variant, Mapping[str, Any], Sequence[str]]] = [
            (defaults_variant, evaluate(ordered, base_threshold), [])
        ]
        for k, variant in enumerate(variants):
            start = time.perf_counter()
            parsed = parse_settings(variant.settings)
            models = affected_models(variant.settings)
            threshold = (
                parsed.baseline_threshold if BASELINE_KEY in variant.settings else base_threshold
            )
            if not models:
                summary = evaluate(ordered, threshold)
            else:
                variant_cascade = cascade.with_settings(
                    {key: v for key, v in variant.settings.items() if key != BASELINE_KEY}
                )
                name = f"variant-{k}"
                report = replay(variant_cascade, models, name, refs)
                merged = variant_parts(
                    default_parts,
                    {d.ref.key: pathlib.Path(d.tables["agents"]) for d in report.done},
                    models, work / name / "merged",
                )  # fmt: skip
                summary = evaluate(merged, threshold)
                shutil.rmtree(work / name, ignore_errors=True)  # disk: one variant at a time
            done.append((variant, summary, models))
            times[f"{variant.group}: {variant.label}"] = time.perf_counter() - start
    rows, per_variant, findings = sweep_table(done)
    return SweepResult(rows, per_variant, findings, times)


def variant_parts(
    defaults: Mapping[str, pathlib.Path],
    variant: Mapping[str, pathlib.Path],
    models: Sequence[str],
    folder: pathlib.Path,
) -> list[pathlib.Path]:
    """Per scene (key order): the defaults' part with the ``risk_<model>`` columns of
    the variant's part (:func:`replace_risks`), written into ``folder``, one scene in
    memory at a time."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for j, key in enumerate(sorted(defaults)):
        if key not in variant:
            raise EvaluationError(f"the variant's replay has no scene {key}")
        base = pl.read_parquet(defaults[key])
        cols = [c for c in (*KEYS, *(f"risk_{m}" for m in models)) if c in base.columns]
        new = pl.read_parquet(variant[key], columns=cols)
        path = folder / f"{j}.parquet"
        replace_risks(base, new, models).write_parquet(path)
        out.append(path)
    return out


def write_sweep(
    result: SweepResult, out_dir: str | os.PathLike[str], *, plots: bool = True
) -> dict[str, pathlib.Path]:
    """``sensitivity.parquet/.csv`` (AUC rows), ``sensitivity_ranking.parquet/.csv``
    (rank correlation and flips per variant), ``sensitivity_findings.parquet/.csv`` and
    ``sensitivity.png``, each atomically. Returns name -> path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    tables = {
        "sensitivity": result.rows,
        "sensitivity_ranking": result.variants,
        "sensitivity_findings": result.findings,
    }
    for name, df in tables.items():
        for suffix in (".parquet", ".csv"):
            path = out / f"{name}{suffix}"
            with atomic_output(path) as tmp:
                if suffix == ".csv":
                    df.write_csv(tmp)
                else:
                    df.write_parquet(tmp)
            written[path.name] = path
    if plots:
        written["sensitivity.png"] = plot_sensitivity(result.rows, out / "sensitivity.png")
    return written


def format_sweep(result: SweepResult) -> str:
    """The ranking table printed by ``replay evaluate --sensitivity``."""
    lines = ["Sensitivity (rank correlation of the 8 models' AUC ranking against the defaults):"]
    lines.append(
        f"  {'choice':<24}{'variant':<16}{'ref':<10}{'Spearman':>9}{'Kendall':>9}{'flips':>6}  recomputed"
    )
    for r in result.variants.iter_rows(named=True):
        lines.append(
            f"  {r['group']:<24}{r['variant']:<16}{r['reference']:<10}"
            f"{r['spearman']:>9.3f}{r['kendall']:>9.3f}{r['flips']:>6}  {r['recomputed']}"
        )
    flipped = result.findings.filter(pl.col("flipped"))
    for r in flipped.iter_rows(named=True):
        lines.append(
            f"  flip: {r['group']} {r['variant']} ({r['reference']}): {r['finding']}: "
            f"{'holds' if r['default'] else 'does not hold'} at the defaults, "
            f"{'holds' if r['variant_holds'] else 'does not'} here"
        )
    return "\n".join(lines)


def sweep_subset(scenes: Sequence[Any], every_kth: int) -> list[Any]:
    """Every ``every_kth`` scene of each folder (the first, then every k-th after it, in
    sorted order): a spread subset that keeps every dataset in the sweep."""
    by_dir: dict[Any, list[Any]] = {}
    for s in sorted(pathlib.Path(p) for p in scenes):
        by_dir.setdefault(s.parent, []).append(s)
    return [s for files in by_dir.values() for s in files[::every_kth]]
