"""The planners by name: ``idm`` and ``pdm`` (numpy only, always there) and fiss-planner's
Frenet planners ``fop``, ``fiss``, ``fiss_plus`` (the optional extra ``riskreplay[planner]``)."""

from __future__ import annotations

from replay.planning.errors import PlannerUnavailable, UnknownPlanner
from replay.planning.frenet import VARIANTS, FrenetPlanner, load_fiss_planner
from replay.planning.idm import IdmPlanner
from replay.planning.pdm import PdmPlanner
from replay.planning.types import Planner

#: Every planner name, the default first.
PLANNERS: tuple[str, ...] = ("idm", *VARIANTS, "pdm")

#: Names that need the optional package fiss-planner.
NEEDS_EXTRA: frozenset[str] = frozenset(VARIANTS)


def make_planner(name: str) -> Planner:
    """A new planner by name; UnknownPlanner lists the valid names, PlannerUnavailable
    names the extra to install."""
    if name == "idm":
        return IdmPlanner()
    if name == "pdm":
        return PdmPlanner()
    if name in VARIANTS:
        return FrenetPlanner(name)
    raise UnknownPlanner(f"unknown planner {name!r}; expected one of {', '.join(PLANNERS)}")


def warm_up(planner: Planner) -> None:
    """Compile (or load from the cache) a planner's compiled code in this process, before
    worker processes start: they then load it instead of each compiling it. A planner
    without compiled code (no ``warm_up`` method) is left alone."""
    prepare = getattr(planner, "warm_up", None)
    if prepare is not None:
        prepare()


def available_planners() -> tuple[str, ...]:
    """The names that can run here (the Frenet planners only with fiss-planner installed)."""
    try:
        load_fiss_planner()  # 12 ms the first time (python -X importtime)
        has_extra = True
    except PlannerUnavailable:
        has_extra = False
    return tuple(n for n in PLANNERS if has_extra or n not in NEEDS_EXTRA)
