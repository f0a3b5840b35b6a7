"""The ``--ego`` and ``--every`` options shared by ``run``, ``stats`` and ``batch``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from replay.cli.limits import MIN_PERIOD_S
from replay.core.egos import ALL_EGOS
from replay.core.engine import Stride
from replay.errors import ReplayError
from risk.motion import MIN_TRAVEL_M


class EgoParam(click.ParamType):
    """An agent id, or ``all`` for every agent that moves."""

    name = "ID|all"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if value is None or isinstance(value, int):
            return value
        text = str(value).strip()
        if text.lower() == ALL_EGOS:
            return ALL_EGOS
        try:
            return int(text)
        except ValueError:
            self.fail(f"{value!r} is neither an agent id (a whole number) nor 'all'", param, ctx)


def ego_option(default_help: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--ego ID|all``; ``default_help`` says what happens without it."""
    return click.option(
        "--ego", type=EgoParam(), default=None,
        help=f"Agent id to see the scene from, or 'all': every agent whose centre moves "
        f"{MIN_TRAVEL_M:g} m or more from where it was first seen becomes the ego in turn "
        f"(one replay per ego; tables gain one row set per ego, told apart by ego_id). "
        f"{default_help}",
    )  # fmt: skip


class StrideParam(click.ParamType):
    """A frame stride: ``K`` frames or ``Ts`` seconds."""

    name = "K|Ts"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, Stride):
            return value
        try:
            stride = Stride.parse(value)
        except ReplayError as exc:
            self.fail(str(exc), param, ctx)
        if stride.seconds is not None and stride.seconds < MIN_PERIOD_S:
            # (1e-9s rounded to one frame of every scene: it silently meant every frame)
            self.fail(
                f"{value!r} is shorter than any frame period ({MIN_PERIOD_S:g} s at least);"
                " for every frame give 1",
                param, ctx,
            )  # fmt: skip
        return stride


def every_option(func: Callable[..., Any]) -> Callable[..., Any]:
    """``--every K|Ts``: a frame stride."""
    return click.option(
        "--every", type=StrideParam(), default="1", show_default=True,
        help="Replay every K-th frame only (frame index a multiple of K), or one frame per "
        "T seconds of scene time ('1s': whatever the frame rate). Keeps dataset-wide runs "
        "affordable; hindsight truth still uses every recorded frame.",
    )(func)  # fmt: skip
