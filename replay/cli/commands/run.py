"""``replay run``: the cascade over every frame of a scene, into a Rerun recording."""

from __future__ import annotations

import pathlib
from typing import cast

import click

from replay.cli.ego_options import ego_option, every_option
from replay.cli.settings_option import CASCADE_NAMES_HELP, CascadeFile, load_cascade, set_option
from replay.core.egos import ALL_EGOS
from replay.core.engine import Stride
from replay.core.scene_run import (
    format_egos_summary,
    format_summary,
    replay_every_ego_to_table,
    replay_to_files,
)
from replay.core.tally import HindsightTally, format_counts
from replay.planning.annotator import PlannerAnnotator
from replay.planning.registry import PLANNERS, make_planner, warm_up


@click.command("run")
@click.argument("scene", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="The Rerun recording to write. Default: beside the scene, with suffix .rrd.",
)  # fmt: skip
@ego_option(
    "Default: the recording's ego. Frames where the ego is missing are skipped (with a "
    "warning). With 'all' no recording is written (it shows one ego's view) and the table "
    "defaults to SCENE.egos.parquet."
)
@every_option
@click.option(
    "--cascade", "cascade_file", type=CascadeFile(),
    help="Cascade TOML (stages, thresholds, tiers), e.g. from 'replay calibrate'. "
    "Default: the calibrated cascade shipped with riskreplay. " + CASCADE_NAMES_HELP,
)  # fmt: skip
@click.option(
    "--table", type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="Also write a frame x agent table of every model's risk and the cascade's "
    "decisions (.parquet or .csv, by suffix).",
)  # fmt: skip
@click.option(
    "--keep-lists", type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="Also write the cascade's answer for every frame by agent id, for a planner "
    "stack: kept ids (most important first), ids per planner tier, dropped ids with the "
    "stage that dropped them, the filter's time (.jsonl or .parquet, by suffix).",
)  # fmt: skip
@click.option(
    "--planner", type=click.Choice(list(PLANNERS)), default=None,
    help="Also plan every frame with this planner, once with all agents and once with the "
    "cascade's: the recording draws both plans (white: all agents, orange: the "
    "cascade's) and plots their planning times; with --table, the table gains "
    "planner_label / planner_shift_m (does removing the agent alone change the plan?). "
    "fop, fiss, fiss_plus need pip install 'riskreplay[planner]'.",
)  # fmt: skip
@click.option("--no-rrd", is_flag=True, help="Do not write the Rerun recording.")
@click.option(
    "--progress/--no-progress", default=True, show_default=True,
    help="Progress bar on stderr.",
)  # fmt: skip
@set_option
def run(
    scene: pathlib.Path,
    output: pathlib.Path | None,
    ego: int | str | None,
    every: Stride,
    cascade_file: pathlib.Path | None,
    table: pathlib.Path | None,
    no_rrd: bool,
    progress: bool,
    keep_lists: pathlib.Path | None = None,
    planner: str | None = None,
    sets: tuple[str, ...] = (),
) -> None:
    """Replay SCENE (an MCAP scene) through the nine risk models and the filter cascade.

    Every frame: each model on every agent (for the risk timelines), then the cascade
    (path distance -> trajectory distance -> 2D Gaussians, each on the survivors of the
    previous stage) and the survival-analysis sorting of the survivors into planner
    tiers, compared with survival analysis on all agents (false negatives, compute time).

    Writes SCENE.rrd (open it with 'rerun SCENE.rrd') and prints a summary.
    """
    cascade = load_cascade(cascade_file, sets)
    annotators = []
    planners = [] if planner is None else [make_planner(planner)]
    for chosen in planners:
        annotators.append(PlannerAnnotator(chosen, truth=table is not None))
    if no_rrd and output is not None:
        raise click.UsageError("--output names the recording; it cannot go with --no-rrd")
    if no_rrd and table is None and keep_lists is None and ego != ALL_EGOS:
        raise click.UsageError(
            "--no-rrd without --table would write nothing; add --table FILE (or --table"
            " /dev/null to print the summary only)"
        )
    for chosen in planners:  # compiled code loaded now, not inside the first plan's time
        warm_up(chosen)
    if ego == ALL_EGOS:
        if output is not None:
            raise click.UsageError(
                "--output names a recording, which shows one ego's view; --ego all writes "
                "the table only (--table)"
            )
        table = table or scene.with_name(scene.stem + ".egos.parquet")
        click.echo(
            "Note: --ego all writes no Rerun recording (it shows one ego's view); replay "
            "one ego with --ego ID to look at it.",
            err=True,
        )
        egos = replay_every_ego_to_table(
            scene, table=table, cascade=cascade, every=every, progress=progress,
            inputs=(cascade_file,), keep_lists=keep_lists, annotators=annotators,
        )  # fmt: skip
        click.echo(format_egos_summary(egos))
        for annotator in annotators:
            click.echo(annotator.summary())
        return
    tally = HindsightTally()
    summary = replay_to_files(
        scene, rrd=None if no_rrd else (output or scene.with_suffix(".rrd")), table=table,
        cascade=cascade, ego=cast(int | None, ego), every=every, progress=progress,
        inputs=(cascade_file,), keep_lists=keep_lists, annotators=annotators,
        notify=lambda message: click.echo(message, err=True), extra_sinks=(tally,),
    )  # fmt: skip
    for annotator in annotators:
        click.echo(annotator.summary())
    click.echo(format_summary(summary))
    if tally.counts is not None:
        click.echo(format_counts(tally.counts))
