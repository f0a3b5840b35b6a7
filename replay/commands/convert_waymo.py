"""``replay convert waymo``: Waymo Open Motion TFRecord files into MCAP scenes."""

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


@click.command("waymo")
@click.argument("tfrecord", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@output_option
@path_options()
@skip_bad_option("records")
@guard_outputs("tfrecord")
def waymo(
    tfrecord: pathlib.Path,
    output: pathlib.Path,
    path_mode: str,
    horizon_s: float,
    margin_m: float,
    max_candidates: int,
    skip_bad: bool,
) -> None:
    """Convert a Waymo Open Motion Dataset TFRecord file (Scenario records) to MCAP scenes.

    Each Scenario becomes one scene: every track is an agent (valid where Waymo marks its
    state valid), the self-driving car is the ego, the lanes are the map, and
    objects_of_interest / tracks_to_predict travel as labels. No TensorFlow is needed.

    Every record's CRC is checked before anything is written, so a damaged file stops
    with an error naming the record (use --skip-bad to convert the others).

    \b
    Examples:
      replay convert waymo training.tfrecord-00000-of-01000 -o scenes/
      replay convert waymo one_scenario.tfrecord -o scene.mcap --paths hindsight
    """
    from converters.mcap_io import write_scene
    from converters.tfrecord import RecordError, read_records
    from converters.waymo import decode_scenario, scenario_to_scene

    settings = settings_from(horizon_s, margin_m, max_candidates)
    skipped = Skipped()
    # Pass 1: framing and CRCs of every record (cheap), so corruption stops us early.
    n_good = 0
    for item in read_records(tfrecord):
        if isinstance(item, RecordError):
            if not skip_bad:
                raise item
            skipped.add(str(item))
        else:
            n_good += 1
    outputs = Outputs(output, n_good)
    # Pass 2: decode and convert the good records (bad ones were reported in pass 1).
    records = (r for r in read_records(tfrecord) if not isinstance(r, RecordError))
    with tqdm(total=n_good, desc="scenarios", unit="scenario", disable=n_good < 2) as bar:
        for record in records:
            try:
                msg = decode_scenario(record, tfrecord)
                scene = scenario_to_scene(
                    msg,
                    source=tfrecord,
                    record=record.index,
                    paths=path_mode,
                    settings=settings,
                    progress=True,
                    skip_bad=skip_bad,
                    skipped=skipped,
                )
            except ConversionError as exc:
                if not skip_bad:
                    raise
                skipped.add(str(exc))
                bar.update()
                continue
            name = safe_name(str(msg.scenario_id), f"record{record.index}")
            outputs.written.append(write_scene(outputs.path_for(name), scene, progress=True))
            bar.update()
    finish(outputs.written, skipped)
