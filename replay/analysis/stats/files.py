"""Statistics on disk: agents tables read back, the frames table derived from them, and
:func:`write_stats` (Parquet + CSV tables and ``summary.json``, each file atomically)."""

from __future__ import annotations

import functools
import json
import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

from outputs.atomic import atomic_write, write_text
from replay.analysis.stats.compute import DatasetStats
from replay.core import table_file
from replay.core.stats_sink import (
    SITUATION_KEY,
    frame_columns,
    model_names_of,
    time_columns,
    with_ego_column,
)
from replay.core.tablecheck import LABEL_PREFIXES, check_agents_table
from replay.errors import StatsError


# ---------------------------------------------------------------------- tables from disk
def frames_from_agents(
    agents: pl.DataFrame, stage_names: Sequence[str], tier_names: Sequence[str]
) -> pl.DataFrame:
    """The frames table of an agents table (no times; frames without agents are absent,
    because a table has no row for them)."""
    agents = with_ego_column(agents)
    tier_index = {name: k for k, name in enumerate(tier_names)}
    tier_code = (
        agents["tier"].cast(pl.String).replace_strict(tier_index, default=-1, return_dtype=pl.Int64)
        if "tier" in agents.columns
        else pl.Series([-1] * agents.height, dtype=pl.Int64)
    )
    base = pl.col("baseline")
    aggs = [
        pl.col("t_s").first().alias("t_s"),
        pl.len().cast(pl.Int64).alias("n_others"),
        base.sum().cast(pl.Int64).alias("n_baseline"),
        *(pl.col(f"kept_{s}").sum().cast(pl.Int64).alias(f"kept_{s}") for s in stage_names),
        *((base & ~pl.col(f"kept_{s}")).sum().cast(pl.Int64).alias(f"fn_{s}") for s in stage_names),
        *(
            (pl.col("_tier") >= k).sum().cast(pl.Int64).alias(f"tier_{t}")
            for k, t in enumerate(tier_names)
        ),
    ]
    df = (
        agents.with_columns(tier_code.alias("_tier"))
        .group_by(SITUATION_KEY, maintain_order=True)
        .agg(aggs)
        .sort(SITUATION_KEY)
    )
    df = df.with_columns(pl.lit(None, dtype=pl.Float64).alias(c) for c in time_columns(stage_names))
    return df.select(frame_columns(stage_names, tier_names))


# ---------------------------------------------------------------------- reading, writing
def read_agents_table(path: str | os.PathLike[str], scene: str | None = None) -> pl.DataFrame:
    """An agents table written by ``replay run --table`` (.parquet or .csv), with a
    ``scene`` column (kept when the table has one, else ``scene`` or the file name)."""
    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".parquet":
            df = pl.read_parquet(path)
        elif suffix == ".csv":
            df = pl.read_csv(path, infer_schema_length=None)
        else:
            raise StatsError(f"{path}: a table must end in .parquet or .csv")
    except (pl.exceptions.PolarsError, OSError) as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        # polars' own words ("parquet: File out of specification") do not help here
        detail = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        what = "a Parquet file" if suffix == ".parquet" else f"CSV ({detail})"
        raise StatsError(
            f"{path}: not a readable table (damaged, cut short or not {what}); write it"
            " again with 'replay run --table'"
        ) from None
    required = {"frame", "t_s", "agent_id", "baseline"}
    missing = sorted(required - set(df.columns))
    if missing or not model_names_of(df):
        what = ", ".join(missing) or "risk_<model>"
        raise StatsError(f"{path}: not a 'replay run --table' table (no {what} column)")
    check_agents_table(df, path)  # empty, non-numeric or out-of-range risks
    if df.schema["baseline"] != pl.Boolean:
        df = df.with_columns(pl.col("baseline").cast(pl.String).str.to_lowercase() == "true")
    words = [c for c in df.columns if c.startswith(LABEL_PREFIXES) and df.schema[c] != pl.Boolean]
    df = df.with_columns(  # true/false words of a CSV (checked above), nulls kept
        (pl.col(c).cast(pl.String).str.to_lowercase() == "true").alias(c) for c in words
    )
    if "scene" not in df.columns:
        df = df.select(pl.lit(scene or path.stem).alias("scene"), pl.all())
    return with_ego_column(df).with_columns(
        pl.col("scene").cast(pl.String),
        pl.col("ego_id").cast(pl.Int64),
        pl.col("frame").cast(pl.Int64),
    )


def concat_agents(tables: Sequence[pl.DataFrame]) -> pl.DataFrame:
    """Agents tables of several scenes as one (tier columns as strings when they differ)."""
    if not tables:
        raise StatsError("no tables to combine")
    dtypes = {str(t.schema.get("tier")) for t in tables}
    if len(dtypes) > 1:
        tables = [t.with_columns(pl.col("tier").cast(pl.String)) for t in tables]
    try:
        return pl.concat(tables, how="diagonal_relaxed")
    except pl.exceptions.PolarsError as exc:
        raise StatsError(f"the tables do not fit together: {exc}") from None


#: The tables :func:`write_stats` writes (as NAME.parquet and NAME.csv): never inputs.
OUTPUT_TABLES = ("roc", "errors", "funnel", "per_frame", "per_scene")


def write_stats(stats: DatasetStats, out_dir: str | os.PathLike[str]) -> dict[str, pathlib.Path]:
    """Write every table as Parquet and CSV and the summary as JSON into ``out_dir``
    (created if needed); each file atomically (the per-frame table of the streamed
    statistics is written piece by piece into its temporary file). Returns name -> path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    tables: dict[str, pl.DataFrame | Sequence[pathlib.Path]] = {
        "roc": stats.roc,
        "errors": stats.errors,
        "funnel": stats.funnel,
        "per_frame": stats.per_frame if stats.per_frame_pieces is None else stats.per_frame_pieces,
        "per_scene": stats.per_scene,
    }
    assert tuple(tables) == OUTPUT_TABLES
    for name, df in tables.items():
        for suffix in (".parquet", ".csv"):
            path = out / f"{name}{suffix}"
            atomic_write(path, functools.partial(_write_table, df, target=path))
            written[f"{name}{suffix}"] = path
    summary = {**stats.summary, "files": sorted(p.name for p in written.values())}
    path = out / "summary.json"
    text = json.dumps(_jsonable(summary), indent=2, allow_nan=False)
    write_text(path, text + "\n")
    written["summary.json"] = path
    return written


def _jsonable(value: Any) -> Any:
    """JSON-safe: NaN and infinities become null (JSON has neither), numpy scalars plain."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def _write_table(
    df: pl.DataFrame | Sequence[pathlib.Path], tmp: str, *, target: pathlib.Path
) -> None:
    if isinstance(df, pl.DataFrame):
        table_file.write_dataframe(df, tmp, target)
        return
    try:
        _write_pieces(df, tmp, csv=target.suffix.lower() == ".csv")
    except (pl.exceptions.PolarsError, pa.ArrowException, OSError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise StatsError(f"could not write {target}: {first}") from None


def _write_pieces(pieces: Sequence[pathlib.Path], tmp: str, *, csv: bool) -> None:
    """Parquet piece files, in order, as one table file (CSV or zstd Parquet) at ``tmp``,
    one piece in memory at a time (the streamed per-frame table, issue 38); columns a
    piece lacks are nulls, each column has its first piece's type."""
    schema: dict[str, pl.DataType] = {}
    for path in pieces:
        for name, dtype in pl.read_parquet_schema(path).items():
            schema.setdefault(name, dtype)
    writer: pq.ParquetWriter | None = None
    with open(tmp, "wb") as out:
        for k, path in enumerate(pieces):
            piece = pl.read_parquet(path)
            piece = piece.select(
                pl.col(c).cast(t) if c in piece.columns else pl.lit(None, dtype=t).alias(c)
                for c, t in schema.items()
            )
            if csv:
                piece.write_csv(out, include_header=k == 0)
                continue
            table = piece.to_arrow()
            if writer is None:
                writer = pq.ParquetWriter(out, table.schema, compression="zstd")
            writer.write_table(table)
        if writer is not None:
            writer.close()
        elif not pieces:
            empty = pl.DataFrame(schema=schema)
            empty.write_csv(out) if csv else empty.write_parquet(out)
