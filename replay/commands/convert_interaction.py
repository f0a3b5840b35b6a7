"""``replay convert interaction``: an INTERACTION track CSV with its Lanelet2 map."""

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


def _origin(ctx: click.Context, param: click.Parameter, value: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter("expected LAT,LON in degrees, e.g. 0,0") from None
    if not (-80.0 <= lat <= 84.0 and -180.0 <= lon <= 180.0):
        raise click.BadParameter("LAT must be in [-80, 84] (UTM) and LON in [-180, 180]")
    return lat, lon


@click.command("interaction")
@click.argument("tracks_csv", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option(
    "--map",
    "map_osm",
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
    help="The Lanelet2 OSM map of the recording location.",
)
@output_option
@click.option(
    "--ego",
    type=int,
    default=None,
    help="Track id to replay as the ego  [default: the track present in the most frames].",
)
@click.option(
    "--origin",
    default="0,0",
    show_default=True,
    callback=_origin,
    help="LAT,LON of the map's local origin (INTERACTION maps use 0,0); ignored when the "
    "map's nodes carry local_x/local_y.",
)
@path_options()
@skip_bad_option("CSV rows")
@guard_outputs("tracks_csv", "map_osm")
def interaction(
    tracks_csv: pathlib.Path,
    map_osm: pathlib.Path,
    output: pathlib.Path,
    ego: int | None,
    origin: tuple[float, float],
    path_mode: str,
    horizon_s: float,
    margin_m: float,
    max_candidates: int,
    skip_bad: bool,
) -> None:
    """Convert an INTERACTION (levelX-style) track CSV and its Lanelet2 map to a scene.

    The CSV needs track_id, frame_id, timestamp_ms, agent_type, x, y, vx, vy; psi_rad,
    length and width are used when present (pedestrian files lack them: the heading then
    follows the velocity and sizes are defaults per kind).

    \b
    Examples:
      replay convert interaction vehicle_tracks_000.csv --map DR_USA_Intersection_MA.osm -o ma.mcap
      replay convert interaction pedestrian_tracks_000.csv --map map.osm -o scenes/ --ego 3
    """
    from converters.interaction import read_scene
    from converters.mcap_io import write_scene

    settings = settings_from(horizon_s, margin_m, max_candidates)
    skipped = Skipped()
    outputs = Outputs(output, 1)
    scene = read_scene(
        tracks_csv,
        map_osm,
        ego=ego,
        origin=origin,
        paths=path_mode,
        settings=settings,
        skip_bad=skip_bad,
        skipped=skipped,
        progress=True,
    )
    name = safe_name(tracks_csv.stem, "tracks")
    outputs.written.append(write_scene(outputs.path_for(name), scene, progress=True))
    finish(outputs.written, skipped)
