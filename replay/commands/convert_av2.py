"""``replay convert av2``: Argoverse 2 motion-forecasting scenarios into MCAP scenes."""

from __future__ import annotations

import pathlib

import click
from tqdm import tqdm

from converters.errors import ConversionError
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


@click.command("av2")
@click.argument("source", type=click.Path(exists=True, path_type=pathlib.Path))
@output_option
@path_options()
@skip_bad_option("scenarios")
@guard_outputs("source")
def av2(
    source: pathlib.Path,
    output: pathlib.Path,
    path_mode: str,
    horizon_s: float,
    margin_m: float,
    max_candidates: int,
    skip_bad: bool,
) -> None:
    """Convert Argoverse 2 motion-forecasting scenarios to MCAP scenes.

    SOURCE is a scenario_<id>.parquet file, a scenario folder (the parquet and its
    log_map_archive_<id>.json), or a split folder holding scenario folders. The AV track
    is the ego; Argoverse 2 has no object sizes, so documented defaults per object type
    are used; the focal and scored tracks travel as labels. Without a map JSON beside a
    parquet, every agent gets a straight path.

    \b
    Examples:
      replay convert av2 val/0a1e6f0a-1817-4a98-b02e-db8c9327d151 -o scene.mcap
      replay convert av2 val/ -o scenes/ --skip-bad
    """
    from converters.av2 import find_scenarios, parquet_to_scene
    from converters.mcap_io import write_scene

    settings = settings_from(horizon_s, margin_m, max_candidates)
    skipped = Skipped()
    parquets = find_scenarios(source)
    outputs = Outputs(output, len(parquets))
    for parquet in tqdm(parquets, desc="scenarios", unit="scenario", disable=len(parquets) < 2):
        try:
            scene = parquet_to_scene(
                parquet, paths=path_mode, settings=settings, progress=True,
                skip_bad=skip_bad, skipped=skipped,
            )  # fmt: skip
        except ConversionError as exc:
            if not skip_bad:
                raise
            skipped.add(str(exc))
            continue
        name = safe_name(scene.metadata["scenario_id"], parquet.stem)
        outputs.written.append(write_scene(outputs.path_for(name), scene, progress=True))
    finish(outputs.written, skipped)
