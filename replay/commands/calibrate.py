"""``replay calibrate``: the cascade's thresholds from a set of scenes.

The maths is in :mod:`risk.calibration`; this module reads the scenes, evaluates the
stage models and survival analysis on every agent of every frame, and writes the TOML.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import itertools
import math
import pathlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import click
import numpy as np
from tqdm import tqdm

from replay.atomic import write_text
from replay.errors import ReplayError
from replay.guard import OutputGuard
from risk.calibration import (
    Calibration,
    calibrate_thresholds,
    cascade_keep,
    tier_thresholds_for_counts,
)
from risk.cascade import SURVIVAL_MODEL, CascadeConfig, Stage, Tier

DEFAULT_STAGES = ("path_distance", "trajectory_distance", "gaussian")
#: The paper's tiers (Sec. VI): behavior gets every baseline-important survivor,
#: interactive 3-8 agents, cooperative 1-2; caps at the upper ends.
DEFAULT_TIERS = (
    Tier("behavior", 1e-25),
    Tier("interactive", 0.0, max_agents=8),
    Tier("cooperative", 0.0, max_agents=2),
)
DEFAULT_TIER_COUNTS = (5, 2)


@dataclass(frozen=True)
class CalibrationData:
    """Flattened agent-frames of many scenes (valid non-ego agents only).

    ``stage_risks (S, A)``, ``survival (A,)``, ``frame_index (A,)`` (global frame number).
    """

    stage_risks: np.ndarray
    survival: np.ndarray
    frame_index: np.ndarray
    frames: int
    scenes: int
    skipped_frames: int
    sources: tuple[str, ...]  # distinct metadata "source"/"dataset" values
    seeds: tuple[int, ...] = ()  # metadata "seed" of synthetic scenes


def collect(
    paths: Sequence[pathlib.Path], models: Sequence[str], *, progress: bool = True
) -> CalibrationData:
    """Evaluate ``models`` and survival analysis on every agent of every frame."""
    from replay.reader import open_scene
    from risk import evaluate

    readers = [open_scene(p) for p in paths]
    names = [*models, SURVIVAL_MODEL]
    risks: list[list[np.ndarray]] = [[] for _ in names]
    frame_index: list[np.ndarray] = []
    frames = skipped = 0
    sources: set[str] = set()
    seeds: set[int] = set()
    total = sum(r.n_frames for r in readers)
    with tqdm(total=total, disable=not progress, file=sys.stderr, unit="frame",
              desc="calibrate", leave=False) as bar:  # fmt: skip
        for reader in readers:
            meta = dict(reader.metadata)
            sources.add(meta.get("dataset") or meta.get("source") or meta.get("converter", "?"))
            if meta.get("seed", "").lstrip("-").isdigit():
                seeds.add(int(meta["seed"]))
            for entry in reader.entries():
                bar.update()
                if entry.frame is None:
                    skipped += 1
                    continue
                frame = entry.frame
                values = evaluate(frame, models=names)
                others = frame.others
                for k, name in enumerate(names):
                    risks[k].append(np.asarray(values[name], dtype=np.float64)[others])
                frame_index.append(np.full(int(others.sum()), frames, dtype=np.int64))
                frames += 1
    if frames == 0:
        raise ReplayError("no usable frame in the given scenes (every frame lacks its ego)")
    stacked = [np.concatenate(r) for r in risks]
    return CalibrationData(
        stage_risks=np.stack(stacked[:-1]) if models else np.empty((0, 0)),
        survival=stacked[-1],
        frame_index=np.concatenate(frame_index),
        frames=frames,
        scenes=len(paths),
        skipped_frames=skipped,
        sources=tuple(sorted(sources)),
        seeds=tuple(sorted(seeds)),
    )


def calibrated_config(
    data: CalibrationData,
    models: Sequence[str],
    *,
    max_fn_rate: float,
    tiers: Sequence[Tier],
    tier_counts: Sequence[int],
    baseline_threshold: float = 1e-25,
) -> tuple[CascadeConfig, Calibration]:
    """Stage thresholds (sequential, FN budget) and tier minimums (target counts).

    The first tier's minimum is the baseline threshold (every baseline-important survivor
    reaches it); tier ``k >= 1`` gets the survival risk that gives ``tier_counts[k - 1]``
    agents in the median frame (:func:`risk.calibration.tier_thresholds_for_counts`).
    """
    baseline = data.survival >= baseline_threshold
    cal = calibrate_thresholds(
        data.stage_risks, baseline, data.frame_index, models=models, max_fn_rate=max_fn_rate
    )
    survivors = cascade_keep(data.stage_risks, cal.thresholds)[-1]
    minimums = tier_thresholds_for_counts(
        data.survival[survivors], data.frame_index[survivors], tier_counts
    )
    new_tiers = [Tier(tiers[0].name, baseline_threshold, tiers[0].max_agents)]
    for tier, minimum in zip(tiers[1:], minimums, strict=True):
        # Never below the tier before: tiers are nested.
        minimum = max(minimum, new_tiers[-1].min_survival_risk)
        new_tiers.append(Tier(tier.name, minimum, tier.max_agents))
    config = CascadeConfig(
        stages=tuple(Stage(m, t) for m, t in zip(models, cal.thresholds, strict=True)),
        tiers=tuple(new_tiers),
        baseline_threshold=baseline_threshold,
    )
    return config, cal


def tier_means(config: CascadeConfig, data: CalibrationData) -> list[float]:
    """Mean agents per frame in each tier when ``config`` runs on the calibration data."""
    from risk.cascade import assign_tiers

    survivors = cascade_keep(data.stage_risks, [s.threshold for s in config.stages])[-1]
    tier = np.full(data.survival.size, -1, dtype=np.int64)
    # Tiers are assigned per frame; agent-frames are stored frame after frame.
    idx = np.flatnonzero(survivors)
    frames = data.frame_index[idx]
    bounds = np.flatnonzero(np.r_[True, frames[1:] != frames[:-1], True])
    for a, b in itertools.pairwise(bounds):
        tier[idx[a:b]] = assign_tiers(data.survival[idx[a:b]], config.tiers)
    return [float((tier >= k).sum()) / data.frames for k in range(len(config.tiers))]


def provenance(
    config: CascadeConfig,
    cal: Calibration,
    data: CalibrationData,
    tier_mean: Sequence[float],
    command: str,
    tier_counts: Sequence[int],
    *,
    note: str = "",
) -> str:
    """The human-readable record of how the thresholds were made (kept in the TOML)."""
    try:
        version = importlib.metadata.version("riskreplay")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    today = datetime.datetime.now(datetime.UTC).date().isoformat()
    lines = [
        f"Made by: {command}",
        f"Date: {today}, riskreplay {version}",
        *([f"Note: {note.strip()}"] if note.strip() else []),
        f"Data: {data.scenes} scenes ({', '.join(data.sources)}), {data.frames} frames"
        f" ({data.skipped_frames} skipped: ego missing), {cal.agent_frames} agent-frames,"
        f" {cal.baseline_agents} baseline-important (survival R_S >= {config.baseline_threshold:g})",
        *([f"Seeds: {_ranges(data.seeds)}"] if data.seeds else []),
        f"Model parameters: {_model_parameters()}",
        f"Max FN rate per stage: {cal.max_fn_rate:g} (of all baseline-important agent-frames);"
        f" FN share of the whole cascade on this data: {cal.total_fn_share:.4g}",
        "Stages (threshold: agents reaching it -> removed per frame, share of its input removed):",
    ]
    for s in cal.stages:
        lines.append(
            f"  {s.model}: {s.threshold:.6g}: {s.agents_in / data.frames:.1f} -> "
            f"{s.mean_removed_per_frame:.1f} removed ({100 * s.removed_share:.1f} %),"
            f" FN {s.false_negatives}"
        )
    lines.append(
        "Tiers: the first gets every baseline-important survivor (min = baseline threshold);"
        f" the others the survival risk giving {', '.join(map(str, tier_counts))} agents in"
        " the median frame (median over frames of the k-th largest survivor risk), capped"
        " at max_agents. Mean agents per frame on this data: "
        + ", ".join(f"{t.name} {m:.2f}" for t, m in zip(config.tiers, tier_mean, strict=True))
    )
    return "\n".join(lines) + "\n"


def _ranges(values: Sequence[int]) -> str:
    """``1, 2, 3, 7`` -> ``1-3, 7``."""
    runs: list[list[int]] = []
    for v in sorted(values):
        if runs and v == runs[-1][1] + 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _model_parameters() -> str:
    """The settings the baseline depends on (prediction horizon and step, survival)."""
    from risk import MODELS, PredictionSettings

    pred = PredictionSettings()
    survival = MODELS[SURVIVAL_MODEL].params_type()
    return f"defaults: prediction horizon {pred.horizon_s:g} s, step {pred.dt_s:g} s; {survival!r}"


def _parse_list(value: str, what: str) -> list[str]:
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise click.BadParameter(f"give at least one {what}, comma-separated")
    return items


@click.command("calibrate")
@click.argument(
    "scenes", nargs=-1, required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
)  # fmt: skip
@click.option(
    "-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="The cascade TOML to write (use it with 'replay run --cascade').",
)  # fmt: skip
@click.option(
    "--max-fn-rate", type=click.FloatRange(0, 1), default=0.0, show_default=True,
    help="Share of the baseline-important agent-frames (survival R_S >= 1e-25) each stage "
    "may drop. 0: no stage drops any important agent of the calibration data.",
)  # fmt: skip
@click.option(
    "--stages", default=",".join(DEFAULT_STAGES), show_default=True,
    help="The filter stages in order, comma-separated model names (see 'replay models').",
)  # fmt: skip
@click.option(
    "--tier-counts", default=",".join(map(str, DEFAULT_TIER_COUNTS)), show_default=True,
    help="Agents in the median frame for each tier after the first (interactive, "
    "cooperative); the first tier gets every baseline-important survivor.",
)  # fmt: skip
@click.option(
    "--base", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    help="Take tier names and caps (max_agents) from this cascade TOML. Default: the "
    "paper's tiers: behavior, interactive (cap 8), cooperative (cap 2).",
)  # fmt: skip
@click.option(
    "--note", default="",
    help="A line to keep in the file's provenance, e.g. how the scenes were made.",
)  # fmt: skip
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
def calibrate(
    scenes: tuple[pathlib.Path, ...],
    output: pathlib.Path,
    max_fn_rate: float,
    stages: str,
    tier_counts: str,
    base: pathlib.Path | None,
    note: str,
    progress: bool,
) -> None:
    """Choose the cascade's thresholds on SCENES so that no stage drops (more than
    --max-fn-rate of) the agents survival analysis deems important.

    Over every frame of the scenes, stage 1 gets the highest threshold whose dropped
    share of baseline-important agents is <= the rate, then stage 2 on what stage 1
    kept, and so on, as the cascade runs. Prints each stage's threshold and how many
    agents it removes, and records how the file was made inside it.
    """
    from risk.registry import resolve_models

    models = _parse_list(stages, "stage model")
    resolve_models(models)  # an unknown name is an error listing the valid ones
    if len(set(models)) != len(models):
        raise click.BadParameter("a model may appear in only one stage", param_hint="--stages")
    try:
        counts = [int(c) for c in _parse_list(tier_counts, "tier count")]
    except ValueError:
        raise click.BadParameter(
            "expected integers, e.g. 5,2", param_hint="--tier-counts"
        ) from None
    if any(c < 1 for c in counts):
        raise click.BadParameter("counts must be >= 1", param_hint="--tier-counts")
    tiers = CascadeConfig.from_toml(base).tiers if base else DEFAULT_TIERS
    if len(counts) != len(tiers) - 1:
        raise click.BadParameter(
            f"expected {len(tiers) - 1} counts (tiers after {tiers[0].name!r}), got {len(counts)}",
            param_hint="--tier-counts",
        )
    if not output.parent.is_dir():
        raise ReplayError(f"{output}: the folder {output.parent} does not exist")

    with OutputGuard(inputs=(*scenes, base), files=(output,)):  # before any work
        data = collect(scenes, models, progress=progress)
        config, cal = calibrated_config(data, models, max_fn_rate=max_fn_rate, tiers=tiers,
                                        tier_counts=counts)  # fmt: skip
        means = tier_means(config, data)
        command = _command_line(scenes, output, max_fn_rate, models, counts, base)
        config = CascadeConfig(
            stages=config.stages, tiers=config.tiers,
            baseline_threshold=config.baseline_threshold,
            provenance=provenance(config, cal, data, means, command, counts, note=note),
        )  # fmt: skip
        write_text(output, config.to_toml_string())
    click.echo(_report(config, cal, data, means))
    click.echo(f"Wrote {output}")


def _command_line(scenes, output, max_fn_rate, models, counts, base) -> str:
    shown = " ".join(p.name for p in scenes[:3]) + (
        f" ... ({len(scenes)} files)" if len(scenes) > 3 else ""
    )
    parts = ["replay calibrate", shown, f"-o {output.name}", f"--max-fn-rate {max_fn_rate:g}",
             f"--stages {','.join(models)}", f"--tier-counts {','.join(map(str, counts))}"]  # fmt: skip
    if base:
        parts.append(f"--base {base.name}")
    return " ".join(parts)


def _report(config: CascadeConfig, cal: Calibration, data: CalibrationData, means) -> str:
    w = max(len(s.model) for s in cal.stages) + 2
    lines = [
        f"Calibrated on {data.scenes} scenes, {data.frames} frames, {cal.agent_frames} "
        f"agent-frames; {cal.baseline_agents} baseline-important "
        f"({100 * cal.baseline_agents / max(cal.agent_frames, 1):.1f} %)",
        *([f"Seeds: {_ranges(data.seeds)}"] if data.seeds else []),
        f"Model parameters: {_model_parameters()}",
        f"Max FN rate per stage: {cal.max_fn_rate:g}",
        f"  {'stage':<{w}}{'threshold':>12}{'in/frame':>10}{'removed/frame':>15}"
        f"{'removed %':>11}{'FN':>7}",
    ]
    for s in cal.stages:
        share = "n/a" if math.isnan(s.removed_share) else f"{100 * s.removed_share:.1f}"
        lines.append(
            f"  {s.model:<{w}}{s.threshold:>12.5g}{s.agents_in / data.frames:>10.1f}"
            f"{s.mean_removed_per_frame:>15.1f}{share:>11}{s.false_negatives:>7d}"
        )
    lines.append(f"  cascade FN share on this data: {cal.total_fn_share:.4g}")
    lines.append(
        "Tiers (min survival risk, cap, mean agents per frame): "
        + "; ".join(
            f"{t.name} >= {t.min_survival_risk:.3g}"
            + (f" (cap {t.max_agents})" if t.max_agents else "")
            + f": {m:.2f}"
            for t, m in zip(config.tiers, means, strict=True)
        )
    )
    return "\n".join(lines)
