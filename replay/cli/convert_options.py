"""Options and output handling shared by the recorded-data converters' commands
(`replay convert <source>`, built in :mod:`replay.cli.commands.convert_source`)."""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Callable, Iterator, Sequence

import click

from converters.clock import TimeStep, parse_time_step
from converters.errors import ConversionError
from converters.lanegraph import PathSettings
from converters.tracks import PATH_MODES, Skipped
from outputs.atomic import safe_name as safe_name  # re-exported for the convert_* commands
from replay.cli.limits import FiniteRange
from risk.frame import MAX_CANDIDATES

MCAP_SUFFIX = ".mcap"


def path_options(default: str = "map") -> Callable:
    """``--paths``, ``--horizon-s``, ``--margin-m``, ``--map-path-m``, ``--max-candidates``."""

    def decorate(f: Callable) -> Callable:
        options = [
            click.option(
                "--paths",
                "path_mode",
                type=click.Choice(PATH_MODES),
                default=default,
                show_default=True,
                help="Where agent paths come from: 'map' follows the lane graph from each "
                "agent's matched lane (pedestrians and agents off every lane go straight "
                "along their heading); 'hindsight' uses each agent's own recorded future, "
                "extended straight beyond its last state.",
            ),
            click.option(
                "--horizon-s",
                type=FiniteRange(min=0.0),
                default=PathSettings.horizon_s,
                show_default=True,
                help="Prediction horizon T: paths are at least v*T + margin long.",
            ),
            click.option(
                "--margin-m",
                type=FiniteRange(min=0.0),
                default=PathSettings.margin_m,
                show_default=True,
                help="Path length beyond v*T (what a stopped agent gets).",
            ),
            click.option(
                "--map-path-m",
                type=FiniteRange(min=0.0),
                default=PathSettings.map_path_m,
                show_default=True,
                help="Map paths follow the lane graph this far beyond the agent, or to the "
                "graph's end (never shorter than v*T + margin); 0: v*T + margin only.",
            ),
            click.option(
                "--max-candidates",
                type=click.IntRange(1, MAX_CANDIDATES),  # (the replay's cap: risk.frame)
                default=PathSettings.max_candidates,
                show_default=True,
                help="Path candidates kept per agent where lanes fork (map paths).",
            ),
        ]
        for option in reversed(options):
            f = option(f)
        return f

    return decorate


def output_option(f: Callable) -> Callable:
    return click.option(
        "-o",
        "--output",
        required=True,
        type=click.Path(path_type=pathlib.Path),
        help="A folder (one NAME.mcap per scenario, created if needed) or, for a single "
        "scenario, a file path ending in .mcap.",
    )(f)


def _time_step(ctx: click.Context, param: click.Parameter, value: str) -> TimeStep:
    try:
        return parse_time_step(value)
    except ConversionError as exc:
        raise click.BadParameter(str(exc)) from None


def time_step_option(f: Callable) -> Callable:
    """``--time-step auto|file|SECONDS``: the clock check's choice (converters.clock)."""
    return click.option(
        "--time-step",
        default="auto",
        show_default=True,
        metavar="auto|file|SECONDS",
        callback=_time_step,
        help="The time step between recorded states. 'auto': the file's, unless the "
        "positions move a clean factor (2, 2.5, 3, 4, 5, 10 or its inverse) farther than "
        "the recorded speeds say, consistently across agents: then the file's times that "
        "factor, with a warning and the metadata time_step_corrected_from. 'file': the "
        "file's (still warns). SECONDS: this value. See docs/recorded-data.md.",
    )(f)


def clock_warning(scene: object) -> None:
    """Print the scene's clock-check warning (metadata ``clock_warning``) on stderr."""
    warning = getattr(scene, "metadata", {}).get("clock_warning")
    if warning:
        click.echo(warning, err=True)


def files_under(path: pathlib.Path | None) -> Iterator[pathlib.Path]:
    """The file itself, or every file below a folder (inputs a command must not overwrite)."""
    if path is None:
        return
    if path.is_dir():
        for root, _dirs, names in os.walk(path):
            yield from (pathlib.Path(root, n) for n in names)
    else:
        yield path


def skip_bad_option(what: str) -> Callable:
    def decorate(f: Callable) -> Callable:
        return click.option(
            "--skip-bad",
            is_flag=True,
            help=f"Skip {what} that cannot be read, and drop states with NaN, infinite or "
            "out-of-range values (counted in the scene's metadata as bad_states_dropped); "
            "convert the rest and list what was skipped or dropped (default: stop at the "
            "first bad record with an error naming it).",
        )(f)

    return decorate


def settings_from(
    horizon_s: float, margin_m: float, max_candidates: int, map_path_m: float = 300.0
) -> PathSettings:
    if not all(math.isfinite(v) for v in (horizon_s, margin_m, map_path_m)):
        raise click.BadParameter("--horizon-s, --margin-m and --map-path-m must be finite")
    return PathSettings(
        horizon_s=horizon_s, margin_m=margin_m, max_candidates=max_candidates,
        map_path_m=map_path_m,
    )  # fmt: skip


class Outputs:
    """Where each scenario goes: ``OUT`` itself when it ends in ``.mcap`` (only for a single
    scenario), else ``OUT/NAME.mcap``; a name used twice gets ``-2``, ``-3``, ..."""

    def __init__(self, out: pathlib.Path, n_scenarios: int) -> None:
        self.single = out.suffix.lower() == MCAP_SUFFIX
        if self.single and n_scenarios != 1:
            raise ConversionError(
                f"{out}: the input holds {n_scenarios} scenarios; give a folder as -o"
            )
        if self.single:
            out.parent.mkdir(parents=True, exist_ok=True)
        elif out.exists() and not out.is_dir():
            raise ConversionError(f"{out}: exists and is not a folder (or use a .mcap name)")
        self.out = out
        self._used: set[str] = set()
        self.written: list[pathlib.Path] = []

    def path_for(self, name: str) -> pathlib.Path:
        if self.single:
            return self.out
        self.out.mkdir(parents=True, exist_ok=True)
        stem, k = name, 1
        while stem in self._used:
            k += 1
            stem = f"{name}-{k}"
        self._used.add(stem)
        return self.out / f"{stem}{MCAP_SUFFIX}"


def finish(outputs: Sequence[pathlib.Path], skipped: Skipped) -> None:
    """Report what was skipped (stderr) and the written paths (stdout); fail when nothing
    was written."""
    if len(skipped):
        click.echo(f"Skipped {len(skipped)} bad record(s):", err=True)
        for line in skipped.what:
            click.echo(f"  {line}", err=True)
    if not outputs:
        raise ConversionError("nothing converted: every record was skipped")
    for path in outputs:
        click.echo(str(path))
