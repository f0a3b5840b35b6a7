"""``replay convert foxglove``: a scene plus the channels that Foxglove draws."""

from __future__ import annotations

import pathlib

import click

from converters.errors import ConversionError
from converters.scene.reader import read_scene
from converters.scene.writer import write_scene
from outputs.transaction import OutputGuard


@click.command("foxglove")
@click.argument("scene_file", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, path_type=pathlib.Path), required=True,
    help="The scene file to write (.mcap); may not be the input.",
)  # fmt: skip
def foxglove(scene_file: pathlib.Path, output: pathlib.Path) -> None:
    """Copy a scene and add foxglove.SceneUpdate channels, so that Foxglove shows it.

    The copy holds every riskreplay channel unchanged (replay reads it as before) plus
    /foxglove/map (lanes, lane boundaries, road edges, crosswalks as lines) and
    /foxglove/scene (every agent as a cube, per frame, the ego green). Open it in
    Foxglove's 3D panel with the display frame "map". The channels about double the
    file, so converters leave them out; this command adds them on demand.

    \b
    Examples:
      replay convert foxglove scene.mcap -o scene.foxglove.mcap
    """
    if output.resolve() == scene_file.resolve():
        raise ConversionError(f"{output}: the output may not be the input; name another file")
    with OutputGuard(inputs=(scene_file,), files=(output,)):  # hard links, locks, stale temps
        scene = read_scene(scene_file)
        written = write_scene(output, scene, foxglove=True)
    click.echo(f"Wrote {written}")
