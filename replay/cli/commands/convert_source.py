"""``replay convert SOURCE``: one command per entry of the source registry.

Every command is built from its :class:`converters.sources.SourceSpec` (argument, help,
and the options the source takes), so a new source needs no code here. The common flow:
read the input's scenes, convert each (with ``--skip-bad`` a bad one is listed and left
out), write each atomically, print which agent is the ego and why (stderr) and the
written paths (stdout).
"""

from __future__ import annotations

import itertools
import pathlib
from collections.abc import Callable
from typing import Any

import click

from converters.errors import ConversionError
from converters.scene.writer import write_scene
from converters.sources import SOURCES, ReadOptions, SourceInput, SourceSpec
from converters.tracks import Skipped
from outputs.transaction import OutputGuard
from replay.cli.convert_options import (
    MCAP_SUFFIX,
    Outputs,
    clock_warning,
    files_under,
    finish,
    output_option,
    path_options,
    safe_name,
    settings_from,
    skip_bad_option,
    time_step_option,
)


def _origin(ctx: click.Context, param: click.Parameter, value: str) -> tuple[float, float]:
    try:
        lat, lon = (float(v) for v in value.split(","))
    except ValueError:
        raise click.BadParameter("expected LAT,LON in degrees, e.g. 0,0") from None
    if not (-80.0 <= lat <= 84.0 and -180.0 <= lon <= 180.0):
        raise click.BadParameter("LAT must be in [-80, 84] (UTM) and LON in [-180, 180]")
    return lat, lon


def ego_line(name: str, scene: Any) -> str:
    """``NAME: ego TRACK (why)``: the agent a conversion made the ego, and the reason."""
    meta = scene.metadata
    why = meta.get("ego_choice") or "the recording's own ego"
    return f"{name}: ego {meta.get('ego_track', '?')} (id {scene.ego_id if scene.ego_id is not None else scene.frames[0].ego_id}): {why}"


def _companions(spec: SourceSpec, source: SourceInput) -> list[pathlib.Path]:
    """The other files the conversion reads (maps); none when they cannot be found yet
    (the conversion then reports that itself)."""
    try:
        return [pathlib.Path(p) for p in spec.companions(source)]
    except ConversionError:
        return []


def source_command(spec: SourceSpec) -> click.Command:
    """The ``replay convert`` subcommand of ``spec``."""

    def command(
        inputs: tuple[pathlib.Path, ...],
        output: pathlib.Path,
        path_mode: str,
        horizon_s: float,
        margin_m: float,
        map_path_m: float,
        max_candidates: int,
        skip_bad: bool,
        time_step: str | float = "auto",
        ego: int | None = None,
        map_osm: pathlib.Path | None = None,
        origin: tuple[float, float] = (0.0, 0.0),
        progress: bool = True,
    ) -> None:
        options = ReadOptions(
            paths=path_mode,
            settings=settings_from(horizon_s, margin_m, max_candidates, map_path_m),
            ego=ego,
            origin=origin,
            skip_bad=skip_bad,
            progress=progress,
            time_step=time_step,
        )
        source = SourceInput(source=spec.name, path=inputs[0], extra=inputs[1:], map=map_osm)
        # Every file the conversion reads is an input the outputs must not overwrite.
        read = [p for f in (*source.files, *_companions(spec, source)) for p in files_under(f)]
        single = output.suffix.lower() == MCAP_SUFFIX and not output.is_dir()
        with OutputGuard(
            inputs=read,
            files=(output,) if single else (),
            folders=() if single else (output,),
            create_folders=True,
        ):
            convert_input(spec, source, options, output)

    params: list[Callable[[Callable], Callable]] = [
        click.argument(
            "inputs",
            metavar=spec.argument + ("..." if spec.many_inputs else ""),
            nargs=-1 if spec.many_inputs else 1,
            required=True,
            type=click.Path(exists=True, dir_okay=spec.folder_input, path_type=pathlib.Path),
        ),
        output_option,
        path_options(),
        skip_bad_option(spec.records),
        time_step_option,
        click.option(
            "--progress/--no-progress",
            default=True,
            show_default=True,
            help="Progress bars on stderr (shown only on a terminal).",
        ),
    ]
    if spec.ego_option:
        params.append(
            click.option(
                "--ego",
                type=int,
                default=None,
                help="Track id to replay as the ego  [default: the vehicle that travels "
                "farthest; see docs/recorded-data.md].",
            )
        )
    if spec.map_option:
        params += [
            click.option(
                "--map",
                "map_osm",
                default=None,
                type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
                help="The Lanelet2 OSM map of the recording.  [default: the only *.osm "
                "beside the first input]",
            ),
            click.option(
                "--origin",
                default="0,0",
                show_default=True,
                callback=_origin,
                help="LAT,LON of the map's local origin (INTERACTION maps use 0,0).",
            ),
        ]

    def run(inputs: Any, **kwargs: Any) -> None:
        command(inputs if spec.many_inputs else (inputs,), **kwargs)

    for param in reversed(params):
        run = param(run)
    examples = "\n".join(f"  {e}" for e in spec.examples)
    return click.command(spec.name, help=f"{spec.help}\n\n\b\nExamples:\n{examples}")(run)


def convert_input(
    spec: SourceSpec, source: SourceInput, options: ReadOptions, output: pathlib.Path
) -> list[pathlib.Path]:
    """Convert every scene of ``source`` into ``output`` (a folder, or one ``.mcap``)."""
    skipped = Skipped()
    items = iter(spec.scenes(source, options, skipped))
    single = output.suffix.lower() == MCAP_SUFFIX
    if single:  # one scene into one file: know there is no second before writing
        head = list(itertools.islice(items, 2))
        if len(head) > 1:
            raise ConversionError(
                f"{output}: {source.path} holds several scenarios; give a folder as -o"
            )
        items = iter(head)
    outputs = Outputs(output, 1) if single else Outputs(output, 2)
    for label, build in items:
        try:
            scene = build()
        except ConversionError as exc:
            if not options.skip_bad:
                raise
            skipped.add(str(exc))
            continue
        name = safe_name(scene.metadata.get("scenario_id", ""), label)
        path = write_scene(outputs.path_for(name), scene, progress=options.progress)
        outputs.written.append(path)
        click.echo(ego_line(name, scene), err=True)
        clock_warning(scene)
    finish(outputs.written, skipped)
    return outputs.written


def __getattr__(name: str) -> click.Command:
    """``replay.cli.commands.convert_source:NAME``, for the lazy ``replay convert`` group."""
    if name in SOURCES:
        return source_command(SOURCES[name])
    raise AttributeError(name)
