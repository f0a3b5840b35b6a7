"""``replay run``: the cascade over every frame of a scene, into a Rerun recording."""

from __future__ import annotations

import pathlib
import warnings

import click

from base.guard import OutputGuard
from replay.commands.ego_options import ego_option, every_option
from replay.commands.settings_option import load_cascade, set_option
from replay.egos import ALL_EGOS, EgosSummary, pooled, run_every_ego
from replay.engine import ReplayWarning, RunSummary, Sink, Stride, run_scene
from replay.reader import open_scene
from replay.tally import HindsightTally, format_counts


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
    "--cascade", "cascade_file", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    help="Cascade TOML (stages, thresholds, tiers), e.g. from 'replay calibrate'. "
    "Default: the calibrated cascade shipped with riskreplay.",
)  # fmt: skip
@click.option(
    "--table", type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="Also write a frame x agent table of every model's risk and the cascade's "
    "decisions (.parquet or .csv, by suffix).",
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
    if no_rrd and output is not None:
        raise click.UsageError("--output names the recording; it cannot go with --no-rrd")
    if no_rrd and table is None and ego != ALL_EGOS:
        raise click.UsageError(
            "--no-rrd without --table would write nothing; add --table FILE (or --table"
            " /dev/null to print the summary only)"
        )
    inputs = (scene, cascade_file)
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
        with OutputGuard(inputs=inputs, files=(table,)):  # checked before the replay
            egos = run_every_ego(
                scene, sinks=make_sinks(None, table), cascade=cascade, every=every,
                progress=progress,
            )  # fmt: skip
        click.echo(format_egos_summary(egos))
        return
    rrd = None if no_rrd else (output or scene.with_suffix(".rrd"))
    with OutputGuard(inputs=inputs, files=(rrd, table)):  # checked before the replay
        tally = HindsightTally()
        sinks = [*make_sinks(rrd, table), tally]
        reader = open_scene(scene)
        if ego is None:  # the scene's own ego: say which agent it is and why
            click.echo(ego_note(reader.metadata), err=True)
        summary = run_with_warnings(
            reader, sinks=sinks, cascade=cascade, ego=ego, progress=progress, every=every
        )
    click.echo(format_summary(summary))
    if tally.counts is not None:
        click.echo(format_counts(tally.counts))


def ego_note(metadata: dict[str, str]) -> str:
    """Which agent the scene's own ego is, and why (the converter's choice, which it
    records in the scene metadata as ``ego_track`` and ``ego_choice``)."""
    track = metadata.get("ego_track") or metadata.get("ego_id", "?")
    why = metadata.get("ego_choice") or "the scene's ego"
    return f"Ego: agent {metadata.get('ego_id', '?')} (source track {track}): {why}"


def format_egos_summary(egos: EgosSummary) -> str:
    """The end-of-run summary of an every-ego replay: the egos, then the pooled funnel."""
    shown = ", ".join(str(e) for e in egos.egos[:12]) + (", ..." if len(egos.egos) > 12 else "")
    stride = f", {egos.every}" if egos.every != Stride() else ""
    head = (
        f"Egos: {len(egos.egos)} agents that move {egos.min_travel_m:g} m or more ({shown});"
        f" {egos.ego_frames} ego-frames{stride}"
    )
    body = format_summary(pooled(egos)).replace(", ego id -1,", ", every ego,")
    return head + "\n" + body.replace("frames", "ego-frames", 1)


def make_sinks(rrd: pathlib.Path | None, table: pathlib.Path | None) -> list[Sink]:
    """The sinks of a run: the Rerun recording and/or the table (both checked before the
    replay starts, so a bad path fails at once)."""
    # Each output's library is loaded only when it is asked for, and where there is a
    # second CPU by the output process (base.background), while this one replays: rerun
    # takes about 1 s and polars 0.3 s to import (python -X importtime). With both, the
    # output process takes the recording and this one the table: it is idle by then, and
    # the process's imports and writes one after the other made it the critical path
    # (`replay demo` 0.3 s slower, measured).
    sinks: list[Sink] = []
    if table is not None:
        from replay.tables import TableSink

        sinks.append(TableSink(table, background=rrd is None))
    if rrd is not None:
        from recordings import SceneRecorder

        sinks.append(SceneRecorder(rrd, background=True))
    return sinks


def run_with_warnings(scene, **kwargs) -> RunSummary:
    """``run_scene`` with its ReplayWarnings printed as ``Warning: ...`` on stderr."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ReplayWarning)
        summary = run_scene(scene, **kwargs)
    for w in caught:
        if issubclass(w.category, ReplayWarning):
            click.echo(f"Warning: {w.message}", err=True)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return summary


def format_summary(s: RunSummary, extra_outputs: tuple[pathlib.Path, ...] = ()) -> str:
    """The end-of-run summary: counts, the funnel, false negatives, times, files
    (``extra_outputs``: files written before the replay, listed first)."""
    skipped = f", {s.skipped_frames} skipped (ego missing)" if s.skipped_frames else ""
    name_w = max(len(n) for n in ("all other agents", *s.stage_names, *s.tier_names)) + 2
    lines = [
        f"Scene: {s.source or 'in memory'}",
        f"  {s.frames} frames{skipped}, ego id {s.ego_id}, {s.agents} agents, "
        f"{s.mean_others:.1f} other agents per frame",
        "Cascade (mean agents per frame; false negatives vs the survival baseline, "
        f"{s.baseline_agents} important agent-frames; compute time):",
        f"  {'all other agents':<{name_w}}{s.mean_others:7.1f}",
    ]
    for name, kept, fn, t in zip(
        s.stage_names, s.mean_kept, s.false_negatives, s.stage_time_s, strict=True
    ):
        lines.append(f"  {name:<{name_w}}{kept:7.1f}   FN {fn:<6d} {t:8.3f} s")
    tiers = ", ".join(f"{n} {k:.1f}" for n, k in zip(s.tier_names, s.mean_tier, strict=True))
    lines += [
        f"  tiers (survival sort): {tiers}   {s.sort_time_s:.3f} s",
        f"Time: cascade {sum(s.stage_time_s) + s.sort_time_s:.3f} s "
        f"(stages + sort) vs survival analysis on all agents {s.survival_all_time_s:.3f} s",
        "  "
        + ", ".join(
            [
                f"read {s.read_time_s:.2f} s",
                f"all models for the timelines {s.models_time_s:.2f} s",
                *(f"{k} {v:.2f} s" for k, v in s.sink_time_s.items()),
            ]
        ),
    ]
    outputs = (*extra_outputs, *s.outputs)
    if outputs:
        lines.append("Wrote:")
        lines += [f"  {p}" for p in outputs]
        rrd = [p for p in outputs if p.suffix == ".rrd"]
        if rrd:
            lines.append(f"Open the recording with: rerun {rrd[0]}")
    return "\n".join(lines)
