"""``replay convert``: traffic sources into MCAP scenes; ``replay convert synthetic`` here.

The group lists one subcommand per source; each lives in its own module and is imported
only when used (``replay.cli.app.LazyGroup``).
"""

from __future__ import annotations

import pathlib
import sys
from typing import TYPE_CHECKING

import click

from converters.sources import SOURCES as RECORDED
from outputs.transaction import OutputGuard
from replay.cli.app import LazyGroup
from replay.cli.limits import (
    AGENTS,
    ARM_LENGTHS,
    DURATIONS,
    PERIODS,
    SEEDS,
    SITUATIONS,
    check_frames,
)

if TYPE_CHECKING:
    from converters.synthetic import SyntheticSettings

SOURCES: dict[str, str] = {
    "synthetic": "replay.cli.commands.convert:synthetic",
    **{name: f"replay.cli.commands.convert_source:{name}" for name in RECORDED},
    "foxglove": "replay.cli.commands.convert_foxglove:foxglove",
}
"""``synthetic`` here; one command per recorded source of converters.sources.SOURCES;
``foxglove`` (an existing scene's Foxglove channels)."""


@click.group("convert", cls=LazyGroup, lazy_commands=SOURCES)
def convert() -> None:
    """Convert traffic into MCAP scenes that 'replay run' and 'replay inspect' read.

    Each source has its own subcommand. Scenes are written atomically: an interrupted
    conversion leaves no half-written .mcap behind.

    \b
    Examples:
      replay convert synthetic -o scene.mcap --agents 100
      replay convert synthetic --situations 500 -o situations/
    """


@click.command("synthetic")
@click.option(
    "-o", "--output", type=click.Path(path_type=pathlib.Path), default=None,
    help="The scene file to write, or with --situations the folder to fill (created if "
    "needed). Default: synthetic.mcap, or situations/ with --situations.",
)  # fmt: skip
@click.option(
    "--agents", type=AGENTS, default=None,
    help="Number of agents, the ego included. Default: drawn per scene from the paper's "
    "range, 30 to 100.",
)  # fmt: skip
@click.option(
    "--seed", type=SEEDS, default=0, show_default=True,
    help="Random seed; the same seed and options give the same scene. With --situations, "
    "situation k uses seed + k.",
)  # fmt: skip
@click.option(
    "--duration", "duration_s", type=DURATIONS, default=10.0,
    show_default=True, help="Scene length in seconds (ignored with --situations).",
)  # fmt: skip
@click.option(
    "--period", "frame_period_s", type=PERIODS, default=0.1,
    show_default=True, help="Frame period in seconds (0.1 = 10 Hz).",
)  # fmt: skip
@click.option(
    "--lanes", type=click.IntRange(1, 6), default=2, show_default=True,
    help="Lanes per direction on each of the four arms.",
)  # fmt: skip
@click.option(
    "--arm-length", "arm_length_m", type=ARM_LENGTHS, default=150.0,
    show_default=True, help="Length of each arm beyond the intersection box, in metres.",
)  # fmt: skip
@click.option(
    "--situations", type=SITUATIONS, default=None,
    help="Write this many single-frame situations (one MCAP each, situation_0000.mcap, "
    "...) instead of one scene, like the paper's dataset of ~500.",
)  # fmt: skip
@click.option(
    "--progress/--no-progress", default=True, show_default=True,
    help="Progress bar on stderr.",
)  # fmt: skip
def synthetic(
    output: pathlib.Path | None,
    agents: int | None,
    seed: int,
    duration_s: float,
    frame_period_s: float,
    lanes: int,
    arm_length_m: float,
    situations: int | None,
    progress: bool,
) -> None:
    """Synthetic traffic at a four-way intersection, like the paper's experiment.

    Two crossing roads (LANES lanes per direction, 3.5 m wide), routes straight on,
    left from the inner lane and right from the outer lane on smooth arcs; 30 to 100
    vehicles with 5 to 100 m gaps and speeds of 0 to 25 m/s, the ego on an incoming lane
    before the intersection. A scene lets them drive for DURATION seconds (Intelligent
    Driver Model car following; agents leave at their route's end); a situation is
    one frame.

    \b
    Examples:
      replay convert synthetic -o scene.mcap --agents 100 --seed 7
      replay convert synthetic --situations 500 -o situations/
    """
    from converters.intersection import IntersectionSettings
    from converters.synthetic import SyntheticSettings

    if situations is None:
        check_frames(duration_s, frame_period_s)
    settings = SyntheticSettings(
        intersection=IntersectionSettings(lanes_per_direction=lanes, arm_length_m=arm_length_m),
        n_agents=agents,
        duration_s=duration_s if situations is None else frame_period_s,
        frame_period_s=frame_period_s,
    )
    if situations is None:
        output = output or pathlib.Path("synthetic.mcap")
        if output.is_dir():
            raise click.UsageError(
                f"{output} is a folder; give a file name (e.g. {output}/scene.mcap)"
            )
        _one_scene(output, settings, seed)
    else:
        output = output or pathlib.Path("situations")
        if output.exists() and not output.is_dir():
            raise click.UsageError(
                f"{output} exists and is not a folder; --situations writes a folder"
            )
        with OutputGuard(folders=(output,)):  # all situations appear together, or none
            _situations(output, settings, seed, situations, progress)


def _one_scene(output: pathlib.Path, settings: SyntheticSettings, seed: int) -> None:
    from converters.scene.writer import write_scene
    from converters.synthetic import generate_scene

    with OutputGuard(files=(output,), create_folders=True) as guard:
        scene = generate_scene(settings, seed)
        write_scene(output, scene)
        size = guard.pending()[output].stat().st_size
    frames = scene.frames
    click.echo(
        f"{len(frames)} frames, {frames[0].n_agents} agents (seed {seed}), {size / 1024:.0f} KiB",
        err=True,
    )
    click.echo(str(output))


def _situations(
    folder: pathlib.Path, settings: SyntheticSettings, seed: int, count: int, progress: bool
) -> None:
    from tqdm import tqdm

    from converters.scene.writer import write_scene
    from converters.synthetic import generate_situation

    folder.mkdir(parents=True, exist_ok=True)
    digits = max(4, len(str(count - 1)))
    total_agents = 0
    for k in tqdm(
        range(count),
        desc="situations",
        unit="file",
        disable=None if progress else True,
        file=sys.stderr,
    ):
        scene = generate_situation(settings, seed + k)
        write_scene(folder / f"situation_{k:0{digits}d}.mcap", scene)
        total_agents += scene.frames[0].n_agents
    click.echo(
        f"{count} situations, {total_agents / count:.1f} agents on average (seeds {seed}"
        f"..{seed + count - 1})",
        err=True,
    )
    click.echo(str(folder))
