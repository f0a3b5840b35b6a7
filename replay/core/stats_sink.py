"""Collecting statistics while a scene replays: :class:`StatsSink` and the frames table.

The **agents** table is :class:`replay.core.tables.TableSink`'s, with a ``scene`` column in
front; the **frames** table has one row per situation (:func:`frame_columns`): agent and
baseline counts, the cascade's agents after each stage, its cumulative false negatives,
its tier sizes and its compute times (see ``docs/statistics.md``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import polars as pl

from outputs.sinks import FrameResult, SceneInfo
from replay.core.tables import TableSink
from replay.errors import StatsError
from risk.cascade import CascadeResult
from risk.hindsight import HindsightSettings
from risk.registry import MODELS

#: A situation is one frame of one scene.
SITUATION_KEY = ("scene", "ego_id", "frame")  # one situation: a frame seen by one ego


class StatsSink:
    """A :class:`outputs.sinks.Sink` that collects the agents and frames tables of one
    scene, named ``scene`` in the ``scene`` column of both."""

    def __init__(self, scene: str, *, hindsight: HindsightSettings | None = None):
        self.scene = scene
        self._table = TableSink(None, hindsight=hindsight)
        self._frames: list[dict[str, Any]] = []
        self._info: SceneInfo | None = None

    def begin(self, info: SceneInfo) -> None:
        self._info = info
        self._table.begin(info)  # rows accumulate over begin() calls: one per ego

    def add(self, result: FrameResult) -> None:
        info = self._require_info()
        self._table.add(result)
        row = cascade_frame_row(result.cascade, [t.name for t in info.cascade.tiers])
        self._frames.append(
            {
                "scene": self.scene,
                "ego_id": result.frame.ego_id,
                "frame": result.index,
                "t_s": result.frame.t,
                **row,
            }
        )

    def close(self) -> None:
        pass  # everything stays in memory until agents() / frames() are asked for

    def abort(self) -> None:
        self._frames = []
        self._table.abort()

    def agents(self) -> pl.DataFrame:
        """The agents table (TableSink columns with ``scene`` first)."""
        df = self._table.dataframe()
        return df.select(pl.lit(self.scene).alias("scene"), pl.all())

    def frames(self) -> pl.DataFrame:
        """The frames table (one row per processed frame, times included)."""
        info = self._require_info()
        return frames_table(
            self._frames, info.cascade.stage_names, [t.name for t in info.cascade.tiers], timed=True
        )

    def _require_info(self) -> SceneInfo:
        if self._info is None:
            raise StatsError("StatsSink: begin() must be called before add()")
        return self._info


def cascade_frame_row(res: CascadeResult, tier_names: Sequence[str]) -> dict[str, Any]:
    """One frames-table row (without scene, frame and time) from a cascade result."""
    row: dict[str, Any] = {
        "n_others": int(res.others.sum()),
        "n_baseline": int(res.baseline.sum()),
    }
    for name, kept in zip(res.stage_names, res.n_kept, strict=True):
        row[f"kept_{name}"] = int(kept)
    for name, fn in zip(res.stage_names, res.false_negatives, strict=True):
        row[f"fn_{name}"] = int(fn)
    for name, count in zip(tier_names, res.tier_counts(len(tier_names)), strict=True):
        row[f"tier_{name}"] = int(count)
    for name, t in zip(res.stage_names, res.stage_time_s, strict=True):
        row[f"time_{name}_s"] = float(t)
    row["sort_time_s"] = float(res.sort_time_s)
    row["survival_all_time_s"] = float(res.survival_all_time_s)
    return row


def frames_table(
    rows: Sequence[Mapping[str, Any]],
    stage_names: Sequence[str],
    tier_names: Sequence[str],
    *,
    timed: bool,
) -> pl.DataFrame:
    """The frames table from rows of :func:`cascade_frame_row` plus scene, frame, t_s.

    ``timed=False`` (tables read from disk) gives null time columns.
    """
    columns = frame_columns(stage_names, tier_names)
    schema = {
        c: _FRAME_DTYPES.get(c, pl.Int64 if not c.endswith("_s") else pl.Float64) for c in columns
    }
    df = pl.DataFrame([{c: r.get(c) for c in columns} for r in rows], schema=schema, orient="row")
    if not timed:
        df = df.with_columns(
            pl.lit(None, dtype=pl.Float64).alias(c) for c in time_columns(stage_names)
        )
    return df


_FRAME_DTYPES = {"scene": pl.String, "ego_id": pl.Int64, "frame": pl.Int64, "t_s": pl.Float64}


def frame_columns(stage_names: Sequence[str], tier_names: Sequence[str]) -> list[str]:
    """The frames-table columns, in order."""
    return [
        "scene",
        "ego_id",
        "frame",
        "t_s",
        "n_others",
        "n_baseline",
        *(f"kept_{s}" for s in stage_names),
        *(f"fn_{s}" for s in stage_names),
        *(f"tier_{t}" for t in tier_names),
        *time_columns(stage_names),
    ]


def time_columns(stage_names: Sequence[str]) -> list[str]:
    return [*(f"time_{s}_s" for s in stage_names), "sort_time_s", "survival_all_time_s"]


def stage_names_of(agents: pl.DataFrame) -> list[str]:
    """The cascade stages recorded in an agents table (``kept_<stage>`` columns, in order)."""
    return [c.removeprefix("kept_") for c in agents.columns if c.startswith("kept_")]


def model_names_of(agents: pl.DataFrame) -> list[str]:
    """The models whose risks an agents table holds, in registry order."""
    present = {c.removeprefix("risk_") for c in agents.columns if c.startswith("risk_")}
    return [m for m in MODELS if m in present]


def tier_names_of(agents: pl.DataFrame, fallback: Sequence[str] = ()) -> list[str]:
    """Tier names in cascade order: the Enum order of a Parquet table's ``tier`` column,
    else ``fallback`` (the cascade config's tiers), which must name every tier seen."""
    dtype = agents.schema.get("tier")
    if isinstance(dtype, pl.Enum):
        return list(dtype.categories)
    seen = (
        set(agents["tier"].drop_nulls().unique().to_list()) if "tier" in agents.columns else set()
    )
    missing = sorted(seen - set(fallback))
    if missing:
        raise StatsError(
            f"the table names tiers {missing} that the cascade configuration does not have "
            f"({', '.join(fallback) or 'none'}); a CSV table does not store the tier order: "
            "pass the cascade TOML it was made with (--cascade)"
        )
    return list(fallback)


def with_ego_column(agents: pl.DataFrame) -> pl.DataFrame:
    """The table with an ``ego_id`` column: hand-made tables without one have a single ego."""
    if "ego_id" in agents.columns:
        return agents
    return agents.with_columns(pl.lit(0, dtype=pl.Int64).alias("ego_id"))
