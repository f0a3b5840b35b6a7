"""The ``--set KEY=VALUE`` option shared by ``run``, ``stats``, ``evaluate`` and ``batch``:
every baseline choice (model parameters, prediction, baseline threshold) from the command
line, parsed by :func:`risk.settings.parse_settings` on top of the cascade TOML's own
``[params.<model>]`` / ``[prediction]`` tables."""

from __future__ import annotations

import pathlib
from collections.abc import Callable, Sequence
from typing import Any

import click

from risk.cascade import NAMED_CASCADES, CascadeConfig

SET_HELP = (
    "Set a model or baseline choice, KEY=VALUE (repeatable), on top of the cascade file's "
    "[params.<model>] / [prediction] tables, e.g. survival.escape_time_s=0.8, "
    "closest_encounter.encounter_time_max_s=inf (none: the paper's rule), "
    "circles.radius_rule=width, prediction.horizon_s=8, "
    "prediction.vehicle.time_growth_lon_mps=0.2, baseline.threshold=1e-4. "
    "A wrong key lists the valid ones. Default: the paper's values."
)


def set_option(func: Callable[..., Any]) -> Callable[..., Any]:
    """``--set KEY=VALUE`` (repeatable) into the parameter ``sets``."""
    return click.option("--set", "sets", multiple=True, metavar="KEY=VALUE", help=SET_HELP)(func)


def load_cascade(cascade_file: pathlib.Path | None, sets: Sequence[str] = ()) -> CascadeConfig:
    """The cascade of ``--cascade`` (default: the shipped one) with the ``--set`` settings
    on top. A bad key or value raises :class:`risk.settings.SettingsError` (one line)."""
    cascade = CascadeConfig.from_toml(cascade_file) if cascade_file else CascadeConfig.default()
    return cascade.with_settings(list(sets)) if sets else cascade


class CascadeFile(click.Path):
    """``--cascade``: a cascade TOML file, or the name of a shipped one (``planner``,
    ``survival``: :data:`risk.cascade.NAMED_CASCADES`), as the path of that file."""

    name = "cascade"

    def __init__(self) -> None:
        super().__init__(exists=True, dir_okay=False, path_type=pathlib.Path)

    def convert(self, value: Any, param: Any, ctx: Any) -> Any:
        if isinstance(value, str) and value in NAMED_CASCADES:
            return NAMED_CASCADES[value]
        return super().convert(value, param, ctx)


#: The help text's note on shipped names.
CASCADE_NAMES_HELP = f"A shipped cascade by name: {', '.join(NAMED_CASCADES)}."
