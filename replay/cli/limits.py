"""Bounds on what a user can ask for on the command line, checked before any allocation.

Each bound is a click parameter type, so a request beyond it is a one-line usage error
(exit 2) naming the option and its range, instead of an ``OverflowError``, a
``MemoryError`` after minutes, or a run without end.
"""

from __future__ import annotations

import math
import os
from typing import Any

import click
from click.core import ParameterSource

MAX_SEED = 2**63 - 1  # numpy seeds are non-negative; SeedSequence takes any such integer
MAX_WORKERS = max(8, 8 * (os.cpu_count() or 1))  # processes: more only thrash the machine
MAX_AGENTS = 10_000  # agents in one synthetic scene (the paper: 30 to 100)
MAX_SITUATIONS = 1_000_000  # synthetic situations of one command
MIN_PERIOD_S = 1e-3  # frame period: 1 kHz at most
MAX_PERIOD_S = 3600.0
MAX_DURATION_S = 24 * 3600.0
MAX_FRAMES = 1_000_000  # frames of one synthetic scene (duration / period)
MAX_ARM_LENGTH_M = 100_000.0  # a synthetic intersection's arms: 100 km


class FiniteRange(click.FloatRange):
    """A ``FloatRange`` that also refuses NaN and infinities (click's lets NaN through:
    every comparison with it is false). Every number option of the command line is one
    (``tests/test_reliability_round4.py`` checks)."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return rv


SEEDS = click.IntRange(0, MAX_SEED)
WORKERS = click.IntRange(1, MAX_WORKERS)
AGENTS = click.IntRange(1, MAX_AGENTS)
SITUATIONS = click.IntRange(1, MAX_SITUATIONS)
PERIODS = FiniteRange(MIN_PERIOD_S, MAX_PERIOD_S)
DURATIONS = FiniteRange(0, MAX_DURATION_S, min_open=True)
ARM_LENGTHS = FiniteRange(30, MAX_ARM_LENGTH_M)


def check_frames(duration_s: float, period_s: float) -> None:
    """Refuse a synthetic scene of more than :data:`MAX_FRAMES` frames."""
    frames = duration_s / period_s
    if frames > MAX_FRAMES:
        raise click.BadParameter(
            f"--duration {duration_s:g} s at --period {period_s:g} s is {frames:.3g} frames;"
            f" at most {MAX_FRAMES} are supported",
            param_hint="--duration/--period",
        )


#: A threshold on the survival risk, a probability.
RISK_THRESHOLDS = FiniteRange(0.0, 1.0)


def model_names(text: str | None) -> list[str] | None:
    """The names of a ``--models a,b`` option (None: the option was not given). An
    option given with no name at all (``--models ''``) is a usage error, not "all"."""
    if text is None:
        return None
    names = [x.strip() for x in text.split(",") if x.strip()]
    if not names:
        raise click.BadParameter(
            "no model name given; name one or more (see 'replay models'), or leave the"
            " option out for all",
            param_hint="--models",
        )
    return names


def refuse_idle(needs: str, enabled: bool, *names: str) -> None:
    """An option that does nothing in this combination is a usage error (issue 36):
    raise one naming it when any of the parameters ``names`` was given on the command
    line while ``needs`` (the option they serve) is off."""
    if enabled:
        return
    ctx = click.get_current_context()
    for name in names:
        source = ctx.get_parameter_source(name)
        if source in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP):
            continue
        option = next(p.opts[0] for p in ctx.command.params if p.name == name)
        raise click.UsageError(
            f"{option} does nothing without {needs}; add {needs} or leave it out"
        )
