"""The engine options every corpus command shares: ``--engine``, ``--ray-address`` and
``--workers`` (where the per-scene jobs run; :mod:`replay.jobs`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from replay.jobs.engines import ENGINES, check_engine


def engine_options(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Adds ``engine``, ``ray_address`` and ``workers`` to a command."""
    fn = click.option(
        "--workers", type=click.IntRange(min=1), default=None,
        help="Worker processes (local engine) or CPUs of a local Ray instance. Default: the "
        "CPUs this process may use. Ignored on a Ray cluster (its CPUs decide).",
    )(fn)  # fmt: skip
    fn = click.option(
        "--ray-address", metavar="ADDR", default=None,
        help="Join this Ray cluster ('auto', 'HOST:6379' of a head started with 'ray start', "
        "or 'ray://HOST:10001'). Needs --engine ray; without it a local Ray instance is "
        "started and stopped by the command.",
    )(fn)  # fmt: skip
    fn = click.option(
        "--engine", type=click.Choice(ENGINES), default="local", show_default=True,
        help="Where the scenes run: 'local' worker processes, or 'ray' tasks (needs: pip "
        "install 'riskreplay[ray]'). Results go to OUT/parts/ as scenes finish; a rerun "
        "skips complete scenes.",
    )(fn)  # fmt: skip
    return fn


def check_engine_options(engine: str, ray_address: str | None) -> None:
    """Refuse ``--ray-address`` without ``--engine ray``, and Ray when not installed,
    before anything is written."""
    if ray_address and engine != "ray":
        raise click.UsageError("--ray-address needs --engine ray")
    check_engine(engine)
