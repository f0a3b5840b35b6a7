"""``replay demo``: the main job on a built-in example (a synthetic intersection)."""

from __future__ import annotations

import pathlib

import click

from replay.cli.limits import SEEDS
from replay.core.scene_run import DEMO_AGENTS, DEMO_SEED, format_summary, run_demo


@click.command("demo")
@click.option(
    "-o", "--output-dir", type=click.Path(file_okay=False, path_type=pathlib.Path),
    default=pathlib.Path("replay-demo"), show_default=True,
    help="Folder for the scene (.mcap), the recording (.rrd) and the table (.parquet); "
    "created if needed.",
)  # fmt: skip
@click.option("--seed", type=SEEDS, default=DEMO_SEED, show_default=True,
              help="Seed of the synthetic traffic.")  # fmt: skip
@click.option("--agents", type=click.IntRange(2, 500), default=DEMO_AGENTS, show_default=True,
              help="Agents in the scene, the ego included.")  # fmt: skip
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
def demo(output_dir: pathlib.Path, seed: int, agents: int, progress: bool) -> None:
    """Generate a synthetic intersection (100 agents, 10 s at 10 Hz), replay it through
    the risk models and the default cascade, and write a Rerun recording to open.

    \b
    Writes, in the output folder:
      intersection.mcap     the scene (replay it again with 'replay run')
      intersection.rrd      the recording: open it with 'rerun intersection.rrd'
      intersection.parquet  every agent's risks and the cascade decisions, per frame
    """
    scene_path, summary = run_demo(
        output_dir, seed=seed, agents=agents, progress=progress,
        notify=lambda message: click.echo(message, err=True),
    )  # fmt: skip
    click.echo(format_summary(summary, extra_outputs=(scene_path,)))
