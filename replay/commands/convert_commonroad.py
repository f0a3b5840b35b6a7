"""``replay convert commonroad``: a CommonRoad XML scenario into an MCAP scene."""

from __future__ import annotations

import pathlib

import click

from converters.tracks import Skipped
from replay.commands.convert_common import (
    Outputs,
    finish,
    guard_outputs,
    output_option,
    path_options,
    safe_name,
    settings_from,
    skip_bad_option,
)


@click.command("commonroad")
@click.argument("xml_file", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@output_option
@click.option(
    "--ego",
    type=int,
    default=None,
    help="Id of the dynamic obstacle to replay as the ego  [default: the one with the "
    "most states].",
)
@path_options()
@skip_bad_option("dynamic obstacles")
@guard_outputs("xml_file")
def commonroad(
    xml_file: pathlib.Path,
    output: pathlib.Path,
    ego: int | None,
    path_mode: str,
    horizon_s: float,
    margin_m: float,
    max_candidates: int,
    skip_bad: bool,
) -> None:
    """Convert a CommonRoad XML scenario (2018b/2020a) to an MCAP scene.

    Every dynamic obstacle is an agent; lanelets (centre line = mean of the two bounds)
    and their successor links are the map. A CommonRoad planning problem has no
    trajectory, so one of the dynamic obstacles is replayed as the ego. The frames are
    the time steps at which the ego has a state.

    \b
    Examples:
      replay convert commonroad USA_US101-5_1_T-1.xml -o us101.mcap
      replay convert commonroad ZAM_Tjunction-1_97_T-1.xml -o scenes/ --ego 2
    """
    from converters.commonroad import read_scene
    from converters.mcap_io import write_scene

    settings = settings_from(horizon_s, margin_m, max_candidates)
    skipped = Skipped()
    outputs = Outputs(output, 1)
    scene = read_scene(
        xml_file,
        ego=ego,
        paths=path_mode,
        settings=settings,
        skip_bad=skip_bad,
        skipped=skipped,
        progress=True,
    )
    name = safe_name(scene.metadata["scenario_id"], xml_file.stem)
    outputs.written.append(write_scene(outputs.path_for(name), scene, progress=True))
    finish(outputs.written, skipped)
