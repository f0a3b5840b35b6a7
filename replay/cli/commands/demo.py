"""``replay demo``: the main job on a built-in example (a synthetic intersection)."""

from __future__ import annotations

import pathlib

import click

from converters.scene.writer import write_scene
from converters.synthetic import SyntheticSettings, generate_scene
from outputs.transaction import OutputGuard
from replay.cli.commands.run import format_summary, make_sinks, run_with_warnings
from replay.cli.limits import SEEDS
from risk.frame import Scene

DEMO_SEED = 7  # fixed so that every demo shows the same scene (not a calibration seed)
DEMO_AGENTS = 100
DEMO_DURATION_S = 10.0
DEMO_FRAME_PERIOD_S = 0.1


def demo_scene(
    *,
    n_agents: int = DEMO_AGENTS,
    seed: int = DEMO_SEED,
    duration_s: float = DEMO_DURATION_S,
    frame_period_s: float = DEMO_FRAME_PERIOD_S,
) -> Scene:
    """The demo's synthetic four-way intersection: ``n_agents`` vehicles (ego included)
    for ``duration_s`` at ``1 / frame_period_s`` Hz (shorter if the ego leaves the map)."""
    settings = SyntheticSettings(
        n_agents=n_agents, duration_s=duration_s, frame_period_s=frame_period_s
    )
    return generate_scene(settings, seed=seed)


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
    scene_path = output_dir / "intersection.mcap"
    rrd, table = scene_path.with_suffix(".rrd"), scene_path.with_suffix(".parquet")
    # All three files appear together or not at all; the folder is removed again on failure.
    with OutputGuard(files=(scene_path, rrd, table), folders=(output_dir,)) as guard:
        click.echo(
            f"Generating a synthetic intersection: {agents} agents, seed {seed} ...", err=True
        )
        write_scene(scene_path, demo_scene(n_agents=agents, seed=seed))
        guard.commit_now(scene_path)  # the replay reads it back
        sinks = make_sinks(rrd, table)
        summary = run_with_warnings(scene_path, sinks=sinks, progress=progress)
    click.echo(format_summary(summary, extra_outputs=(scene_path,)))
