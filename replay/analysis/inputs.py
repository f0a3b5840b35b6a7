"""The inputs of ``replay stats`` and ``replay evaluate``: scenes (replayed in parallel)
and tables (read as written), into one agents table and one frames table."""

from __future__ import annotations

import functools
import pathlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import polars as pl

from replay.analysis.stats import (
    concat_agents,
    frames_from_agents,
    read_agents_table,
    stage_names_of,
    tier_names_of,
)
from replay.core.engine import EVERY_FRAME, Stride
from replay.core.pool import parallel_map
from replay.core.worker import SceneJob, replay_job
from replay.errors import ReplayError
from replay.planning.annotator import PlannerAnnotator
from replay.planning.registry import make_planner
from risk.cascade import CascadeConfig
from risk.hindsight import HindsightSettings
from risk.prediction import PredictionSettings

SCENE_SUFFIXES = (".mcap",)
TABLE_SUFFIXES = (".parquet", ".csv")


@dataclass(frozen=True)
class Inputs:
    """The files named on the command line, split by kind (each list sorted)."""

    scenes: tuple[pathlib.Path, ...]
    tables: tuple[pathlib.Path, ...]


def resolve_inputs(
    paths: Sequence[pathlib.Path],
    *,
    output_dir: pathlib.Path | None = None,
    output_stems: Sequence[str] = (),
) -> Inputs:
    """Scenes (``.mcap``) and tables (``.parquet``, ``.csv``) among ``paths``. A folder
    contributes its scenes, in sub-folders too (as ``replay batch`` finds them; hidden
    files and folders are left out), and the tables directly inside it (a folder's
    sub-folders hold other tables: ``replay batch`` writes frames tables beside its
    agents tables). Nothing inside ``output_dir`` (the command's own output folder) is
    taken from a folder, except, when the output folder is an input folder itself,
    files that are not outputs (``output_stems``: the names the command writes), so
    that a second ``replay stats DIR -o DIR`` does not read its own ``errors.csv``."""
    scenes: list[pathlib.Path] = []
    tables: list[pathlib.Path] = []
    out = None if output_dir is None else output_dir.absolute()
    stems = set(output_stems)

    def ours(f: pathlib.Path) -> bool:
        if out is None:
            return False
        where = f.absolute()
        if where.parent == out:
            return where.stem in stems or where.name == "summary.json"
        return where.is_relative_to(out)

    for p in paths:
        if p.is_dir():
            found = [f for f in sorted(p.rglob("*")) if _kind(f) == "scene" and _visible(f, p)]
            found = [f for f in found if f.is_file()]
            found += [f for f in sorted(p.iterdir()) if f.is_file() and _kind(f) == "table"]
            found = [f for f in found if not ours(f) and not f.name.startswith(".")]
            if not found:
                raise ReplayError(
                    f"{p}: no .mcap scene (in it or its sub-folders) or .parquet/.csv table"
                    " in this folder"
                )
        else:
            if not _kind(p):
                raise ReplayError(
                    f"{p}: expected an MCAP scene (.mcap) or a table (.parquet, .csv), "
                    f"got {p.suffix or 'no suffix'!r}"
                )
            found = [p]
        for f in found:
            (scenes if _kind(f) == "scene" else tables).append(f)
    return Inputs(tuple(dict.fromkeys(scenes)), tuple(dict.fromkeys(tables)))


def _visible(f: pathlib.Path, root: pathlib.Path) -> bool:
    return not any(part.startswith(".") for part in f.relative_to(root).parts)


def _kind(path: pathlib.Path) -> str:
    suffix = path.suffix.lower()
    if suffix in SCENE_SUFFIXES:
        return "scene"
    return "table" if suffix in TABLE_SUFFIXES else ""


def scene_names(paths: Sequence[pathlib.Path]) -> list[str]:
    """A short unique name per file: its stem, or its path when stems repeat."""
    stems = [p.stem for p in paths]
    return [s if stems.count(s) == 1 else str(p) for s, p in zip(stems, paths, strict=True)]


def planner_annotators(name: str) -> list[PlannerAnnotator]:
    """A planner annotator with planner truth (``planner_label`` columns), made in the
    worker process that replays the scene."""
    return [PlannerAnnotator(make_planner(name), truth=True, filtered=False)]


def collect(
    inputs: Inputs,
    cascade: CascadeConfig,
    *,
    models: Sequence[str] | None,
    workers: int,
    progress: bool,
    params: Mapping[str, Any] | None = None,
    prediction: PredictionSettings | None = None,
    hindsight: HindsightSettings | None = None,
    ego: int | str | None = None,
    every: Stride = EVERY_FRAME,
    planner: str | None = None,
) -> tuple[pl.DataFrame, pl.DataFrame, list[str], list[str]]:
    """Agents and frames tables of every input, with the stage and tier names.

    ``params``, ``prediction`` go to every model evaluation of the replayed scenes,
    ``hindsight`` (``risk.hindsight.HindsightSettings``) to their truth columns; tables
    are read as they were written. ``planner``: a planner's name
    (:func:`replay.planning.registry.make_planner`) whose truth the replayed scenes'
    tables carry (``planner_label``, ``planner_shift_m``)."""
    stage_names = list(cascade.stage_names)
    cascade_tiers = [t.name for t in cascade.tiers]
    tier_names = cascade_tiers
    agents: list[pl.DataFrame] = []
    frames: list[pl.DataFrame] = []
    names = scene_names([*inputs.scenes, *inputs.tables])
    if planner is not None:
        make_planner(planner)  # an unknown name or a missing extra: one error, before any work
    if inputs.scenes:
        tasks = [
            SceneJob(
                p,
                n,
                cascade,
                None if models is None else tuple(models),
                ego,
                every,
                params=params,
                prediction=prediction,
                hindsight=hindsight,
                annotators=None
                if planner is None
                else functools.partial(planner_annotators, planner),
            )
            for p, n in zip(inputs.scenes, names[: len(inputs.scenes)], strict=True)
        ]
        for a, f in parallel_map(
            replay_job,
            tasks,
            workers=min(workers, len(tasks)),
            progress=progress,
            desc="replaying scenes",
            unit="scene",
        ):
            agents.append(a)
            frames.append(f)
    for path, name in zip(inputs.tables, names[len(inputs.scenes) :], strict=True):
        table = read_agents_table(path, scene=name)
        stages = stage_names_of(table)
        if inputs.scenes and stages != stage_names:
            raise ReplayError(
                f"{path}: its cascade stages ({', '.join(stages)}) differ from the cascade "
                f"the scenes run with ({', '.join(stage_names)}); give --cascade"
            )
        stage_names = stages
        tier_names = tier_names_of(table, fallback=cascade_tiers)
        agents.append(table)
        frames.append(frames_from_agents(table, stages, tier_names))
    if not agents:
        raise ReplayError("no input")
    return concat_agents(agents), pl.concat(frames, how="diagonal_relaxed"), stage_names, tier_names
