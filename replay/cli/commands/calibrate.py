"""``replay calibrate``: the cascade's thresholds from a set of scenes.

The maths is in :mod:`risk.calibration`, the data collection and the provenance record in
:mod:`replay.analysis.scene_calibration`; this module parses the options, writes the TOML and prints
the report.
"""

from __future__ import annotations

import math
import pathlib

import click

from outputs.atomic import write_text
from outputs.transaction import OutputGuard
from replay.analysis.scene_calibration import (
    DEFAULT_STAGES,
    DEFAULT_TIER_COUNTS,
    DEFAULT_TIERS,
    CalibrationData,
    calibrated_config,
    collect,
    model_parameters,
    provenance,
    seed_ranges,
    tier_means,
)
from replay.cli.limits import FiniteRange
from replay.errors import ReplayError
from risk.calibration import (
    Calibration,
)
from risk.cascade import CascadeConfig
from risk.registry import resolve_models


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
    "--max-fn-rate", type=FiniteRange(0, 1), default=0.0, show_default=True,
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
        *([f"Seeds: {seed_ranges(data.seeds)}"] if data.seeds else []),
        f"Model parameters: {model_parameters()}",
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
