"""``replay calibrate``: the cascade's thresholds from a set of scenes.

The maths is in :mod:`risk.calibration`, the data collection and the provenance record in
:mod:`replay.analysis.scene_calibration`; this module parses the options, writes the TOML and prints
the report.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import pathlib
import tempfile

import click

from outputs.atomic import write_text
from outputs.transaction import OutputGuard
from replay.analysis.scene_calibration import (
    DEFAULT_STAGES,
    DEFAULT_TIER_COUNTS,
    DEFAULT_TIERS,
    CalibrationCorpus,
    model_parameters,
    provenance,
    risk_parts,
    seed_ranges,
    streamed_calibration,
)
from replay.cli.engine_options import check_engine_options, engine_options
from replay.cli.limits import FiniteRange
from replay.errors import ReplayError
from replay.jobs import JobReport
from replay.jobs.place import JobPlace, shared_engine
from replay.jobs.scenes import distinct_files
from risk.calibration import (
    Calibration,
)
from risk.cascade import CascadeConfig
from risk.registry import resolve_models

#: The stages of a planner-calibrated cascade when --stages is not given (after the
#: corridor stage; docs/cascade.md says why these).
DEFAULT_PLANNER_STAGES = ("gaussian",)


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
    "--stages", default=None,
    help="The filter stages in order, comma-separated model names (see 'replay models'). "
    f"Default: {','.join(DEFAULT_STAGES)}; with --reference planner "
    f"{','.join(DEFAULT_PLANNER_STAGES)} (after the corridor stage).",
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
@click.option(
    "--reference", type=click.Choice(["survival", "planner"]), default="survival",
    show_default=True,
    help="What the cascade must not drop: agents survival analysis deems important "
    "(R_S >= 1e-25), or agents a planner reacts to (removing one alone changes its plan).",
)  # fmt: skip
@click.option(
    "--planner", "planners", multiple=True,
    help="With --reference planner: a planner whose truth counts (repeat for several: "
    "the cascade keeps what any of them reacts to). See 'replay plan --help'.",
)  # fmt: skip
@click.option(
    "--miss-rate", type=FiniteRange(0, 1, min_open=True, max_open=True), default=0.01,
    show_default=True,
    help="With --reference planner: the guaranteed bound A on the chance that a new scene "
    "has a planner-important agent dropped.",
)  # fmt: skip
@click.option(
    "--confidence", type=FiniteRange(0, 1, min_open=True, max_open=True), default=0.95,
    show_default=True, help="With --reference planner: the probability C of that bound.",
)  # fmt: skip
@click.option(
    "--unit", type=click.Choice(["scene", "ego"]), default="scene", show_default=True,
    help="With --reference planner: the independent unit of the guarantee.",
)  # fmt: skip
@click.option(
    "--corridor/--no-corridor", default=True, show_default=True,
    help="With --reference planner: lead with the corridor stage (leaders along the "
    "ego's route and crossing agents; docs/cascade.md).",
)  # fmt: skip
@click.option(
    "--every", "every_s", type=FiniteRange(0, min_open=True), default=1.0,
    show_default=True, help="With --reference planner: one ego-frame per this many seconds.",
)  # fmt: skip
@click.option(
    "--holdout", default=None, metavar="auto|SITE,...",
    help="With --reference planner: calibrate without these recording sites and report on "
    "them ('auto': the smallest site of every dataset with two or more).",
)  # fmt: skip
@click.option(
    "--leave-one-dataset-out", is_flag=True,
    help="With --reference planner: also calibrate without each dataset and report on it.",
)  # fmt: skip
@click.option(
    "--scores-cache", type=click.Path(file_okay=False, path_type=pathlib.Path),
    metavar="DIR",
    help="The folder of the per-scene jobs (docs/batch.md): each scene's scores (and, with "
    "--reference planner, its planner truth) in DIR/parts/, the scenes that failed in "
    "DIR/failures.csv. A rerun with the same scoring settings reads the complete scenes "
    "(other --miss-rate, --stages or --holdout plan nothing). Default: OUTPUT.parts/ "
    "beside the TOML.",
)  # fmt: skip
@click.option(
    "--report", "report_path", type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="With --reference planner: write the guarantee and the held-out figures as JSON.",
)  # fmt: skip
@click.option(
    "--ego", default=None, metavar="ID|all",
    help="With --reference planner: the ego of every scene (default: the recording's; "
    "'all': every moving agent, which gives more planner-important agents per scene, not "
    "more units).",
)  # fmt: skip
@click.option(
    "--preliminary", is_flag=True,
    help="With --reference planner: mark the file's guarantee as preliminary (status).",
)  # fmt: skip
@engine_options
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
def calibrate(
    scenes: tuple[pathlib.Path, ...],
    output: pathlib.Path,
    max_fn_rate: float,
    stages: str | None,
    tier_counts: str,
    base: pathlib.Path | None,
    note: str,
    reference: str,
    planners: tuple[str, ...],
    miss_rate: float,
    confidence: float,
    unit: str,
    corridor: bool,
    every_s: float,
    holdout: str | None,
    leave_one_dataset_out: bool,
    scores_cache: pathlib.Path | None,
    report_path: pathlib.Path | None,
    ego: str | None,
    preliminary: bool,
    workers: int | None,
    progress: bool,
    engine: str = "local",
    ray_address: str | None = None,
) -> None:
    """Choose the cascade's thresholds on SCENES.

    --reference survival (the default): no stage drops (more than --max-fn-rate of) the
    agents survival analysis deems important. Over every frame of the scenes, stage 1
    gets the highest threshold whose dropped share of baseline-important agents is <=
    the rate, then stage 2 on what stage 1 kept, and so on, as the cascade runs.

    --reference planner: with probability >= --confidence, a new scene like these has
    a planner-important agent dropped with probability <= --miss-rate (order-statistic
    rule on scene-level units, Bonferroni over the stages; the guarantee goes into the
    file). Too few scenes with a planner-important agent is an error saying how many are
    needed (299 for 1 % at 95 % with one stage). Planner truth comes from 'replay plan
    --truth's rule: removing the agent alone changes the plan.

    Prints each stage's threshold and how many agents it removes, and records how the
    file was made inside it.

    The scenes run as jobs on --engine (local processes or Ray; docs/batch.md), their
    parts in --scores-cache (default: OUTPUT.parts/). Scenes that fail are listed in
    its failures.csv and left out, and the command says so; it exits non-zero when
    every scene failed. The thresholds come from the parts read back one scene at a
    time (per-scene summaries), never from all agent-frames at once.

    \b
    Example (the shipped planner cascade, recalibrated for your own scenes):
      replay calibrate scenes/*.mcap --reference planner --planner idm --planner fop \\
          --miss-rate 0.01 --confidence 0.95 -o my_cascade.toml
    """
    check_engine_options(engine, ray_address)
    with contextlib.ExitStack() as stack:
        parts = scores_cache or _default_parts(output, stack)
        place = JobPlace(parts, engine, workers, ray_address, progress)
        if reference == "planner":
            _calibrate_planner(
                scenes, output, stages, base, note, planners, miss_rate, confidence, unit,
                corridor, every_s, holdout, leave_one_dataset_out, place, report_path, ego,
                preliminary,
            )  # fmt: skip
        else:
            _calibrate_survival(
                scenes, output, max_fn_rate, stages, tier_counts, base, note, planners, place
            )


def _default_parts(output: pathlib.Path, stack: contextlib.ExitStack) -> pathlib.Path:
    """``OUTPUT.parts/`` beside the TOML; a temporary folder when the output is no
    regular file's path (``-o /dev/null``: nothing to keep beside it)."""
    if output.exists() and not output.is_file():
        return pathlib.Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="calibrate-")))
    return output.with_name(output.name + ".parts")


def _calibrate_survival(
    scenes: tuple[pathlib.Path, ...],
    output: pathlib.Path,
    max_fn_rate: float,
    stages: str | None,
    tier_counts: str,
    base: pathlib.Path | None,
    note: str,
    planners: tuple[str, ...],
    place: JobPlace,
) -> None:
    """``--reference survival``: the FN-budget thresholds of :mod:`risk.calibration`."""
    if planners:
        raise click.BadParameter("needs --reference planner", param_hint="--planner")
    stages = stages or ",".join(DEFAULT_STAGES)
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

    reports: list[JobReport] = []
    scenes = tuple(distinct_files(scenes))
    with OutputGuard(inputs=(*scenes, base), files=(output,), folders=(place.out_dir,)):
        with shared_engine(place, len(scenes)) as where:
            parts = risk_parts(scenes, models, where, reports=reports)
        config, cal, data, means = streamed_calibration(
            parts, models, max_fn_rate=max_fn_rate, tiers=tiers, tier_counts=counts
        )
        command = _command_line(scenes, output, max_fn_rate, models, counts, base)
        config = CascadeConfig(
            stages=config.stages, tiers=config.tiers,
            baseline_threshold=config.baseline_threshold,
            provenance=provenance(config, cal, data, means, command, counts, note=note),
        )  # fmt: skip
        write_text(output, config.to_toml_string())
    click.echo(_report(config, cal, data, means))
    _scenes_line(reports)
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


def _report(config: CascadeConfig, cal: Calibration, data: CalibrationCorpus, means) -> str:
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


def _calibrate_planner(
    scenes: tuple[pathlib.Path, ...],
    output: pathlib.Path,
    stages: str | None,
    base: pathlib.Path | None,
    note: str,
    planners: tuple[str, ...],
    miss_rate: float,
    confidence: float,
    unit: str,
    corridor: bool,
    every_s: float,
    holdout: str | None,
    leave_one_dataset_out: bool,
    place: JobPlace,
    report_path: pathlib.Path | None,
    ego: str | None = None,
    preliminary: bool = False,
) -> None:
    """``--reference planner``: the guarantee of :mod:`replay.analysis.planner_calibration`."""
    import json

    from replay.analysis.planner_calibration import (
        ScoreSettings,
        format_report,
        score_parts,
        streamed_planner_calibration,
    )
    from replay.analysis.planner_eval.study import json_safe
    from replay.planning.registry import available_planners, make_planner, warm_up
    from risk.cascade import CorridorSettings

    if not planners:
        raise click.BadParameter("give at least one --planner NAME", param_hint="--planner")
    for name in planners:
        planner = make_planner(name)  # an unknown name is an error listing the valid ones
        if name not in available_planners():
            raise ReplayError(f"planner {name!r} needs an optional extra: see 'replay plan --help'")
        warm_up(planner)  # compiled code once here, not in every worker
    models = _parse_list(stages or ",".join(DEFAULT_PLANNER_STAGES), "stage model")
    resolve_models(models)
    if len(set(models)) != len(models):
        raise click.BadParameter("a model may appear in only one stage", param_hint="--stages")
    split: list[str] | str | None = None
    if holdout is not None:
        split = "auto" if holdout.strip() == "auto" else _parse_list(holdout, "site")
    for path in (output, report_path):
        if path is not None and not path.parent.is_dir():
            raise ReplayError(f"{path}: the folder {path.parent} does not exist")
    tiers = (CascadeConfig.from_toml(base) if base else CascadeConfig.named("survival")).tiers
    settings = ScoreSettings(
        planners=tuple(dict.fromkeys(planners)),
        corridor=CorridorSettings() if corridor else None,
        every_s=every_s,
        ego=_ego_choice(ego),
    )
    files = (output,) if report_path is None else (output, report_path)
    # one file given twice (or through a link) is one scene unit of the guarantee, not two
    scenes = tuple(distinct_files(scenes))
    reports: list[JobReport] = []
    with OutputGuard(inputs=(*scenes, base), files=files, folders=(place.out_dir,)):
        parts = score_parts(scenes, settings, place, reports=reports)
        result = streamed_planner_calibration(
            parts, models, planners=settings.planners, miss_rate=miss_rate, confidence=confidence,
            unit=unit, corridor=settings.corridor, tiers=tiers, holdout=split,
            lodo=leave_one_dataset_out,
        )  # fmt: skip
        text = format_report(result, settings.planners)
        command = " ".join(
            ["replay calibrate", " ".join(p.name for p in scenes[:3])
             + (f" ... ({len(scenes)} files)" if len(scenes) > 3 else ""),
             "--reference planner", *(f"--planner {p}" for p in settings.planners),
             f"--miss-rate {miss_rate:g}", f"--confidence {confidence:g}", f"--unit {unit}",
             f"--stages {','.join(models)}", f"--every {every_s:g}",
             *(["--no-corridor"] if not corridor else []),
             *([f"--holdout {holdout}"] if holdout else []),
             *([f"--ego {ego}"] if ego else []), *(["--preliminary"] if preliminary else []),
             f"-o {output.name}"]
        )  # fmt: skip
        provenance = "\n".join(
            [f"Made by: {command}", *([f"Note: {note.strip()}"] if note.strip() else []),
             f"Model parameters: {model_parameters()}", text]
        ) + "\n"  # fmt: skip
        guarantee = dict(result.config.guarantee)
        if preliminary:
            guarantee["status"] = "preliminary"
        config = dataclasses.replace(result.config, provenance=provenance, guarantee=guarantee)
        write_text(output, config.to_toml_string())
        if report_path is not None:
            payload = {
                "guarantee": result.config.guarantee,
                "thresholds": {s.model: s.threshold for s in result.config.stages},
                "calibrated_on": result.calibrated_on,
                "held_out_sites": list(result.held_out_sites),
                "held_out": result.held_out,
                "leave_one_dataset_out": result.leave_one_dataset_out,
            }
            write_text(report_path, json.dumps(json_safe(payload), indent=2) + "\n")
    click.echo(text)
    _scenes_line(reports)
    click.echo(f"Wrote {output}")


def _scenes_line(reports: list[JobReport]) -> None:
    """What the jobs did: computed, skipped (complete from an earlier run), failed."""
    for report in reports:
        click.echo(f"Scenes ({report.job}): {report.describe()}")


def _ego_choice(ego: str | None) -> int | str | None:
    if ego is None or ego == "all":
        return ego
    try:
        return int(ego)
    except ValueError:
        raise click.BadParameter("expected an agent id or 'all'", param_hint="--ego") from None
