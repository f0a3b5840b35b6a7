"""The replay table as a polars DataFrame, and its file (the part of the table sink that
imports polars, about 0.3 s).

:class:`replay.core.tables.TableSink` collects numpy columns (:class:`replay.core.tables.TableColumns`);
:func:`dataframe` turns them into the table of ``replay.core.tables``' docstring, and
:func:`write_temp` writes it to a temporary file, in the replay's process or in the output
process (:mod:`outputs.process`) while the replay computes.
"""

from __future__ import annotations

import pathlib

import numpy as np
import polars as pl

from replay.core.table_columns import PLANNER_COLUMNS, TRUTH_COLUMNS, TableColumns
from replay.errors import ReplayError
from risk.frame import KIND_NAMES
from risk.hindsight import LABEL_POSITIVE, LABEL_UNKNOWN


def dataframe(columns: TableColumns) -> pl.DataFrame:
    """The table (the columns of ``replay.core.tables``' docstring, in that order)."""
    data, keys = columns.data, columns.keys
    df = pl.DataFrame({k: v for k, v in data.items() if k not in ("kind", "dropped_at", "tier")})
    df = df.with_columns(
        _names(data["kind"], list(KIND_NAMES), "kind"),
        _names(data["dropped_at"], list(columns.stage_names), "dropped_by"),
        _names(data["tier"], list(columns.tier_names), "tier"),
    )
    labels = np.array([None, False, True], dtype=object)[
        np.where(
            columns.truth_label == LABEL_UNKNOWN,
            0,
            np.where(columns.truth_label == LABEL_POSITIVE, 2, 1),
        )
    ]
    df = df.with_columns(
        pl.Series("truth_gap_m", columns.truth_gap_m).fill_nan(None),
        pl.Series("truth_pet_s", columns.truth_pet_s).fill_nan(None),
        pl.Series("truth_label", labels.tolist(), dtype=pl.Boolean),
    )
    planner = [k for k in PLANNER_COLUMNS if k in data]
    if planner:
        label = np.asarray(data["planner_label"], dtype=np.float64)
        df = df.with_columns(
            pl.Series(
                "planner_label",
                np.asarray(np.where(np.isnan(label), None, label == 1.0)).tolist(),
                dtype=pl.Boolean,
            ),
            pl.Series("planner_shift_m", np.asarray(data["planner_shift_m"])).fill_nan(None),
        )
    return df.select(
        [*keys[:5], *keys[5:-3], "dropped_by", "tier", "baseline", *TRUTH_COLUMNS, *planner]
    )


def write_temp(path: pathlib.Path, tmp: pathlib.Path, columns: TableColumns) -> None:
    """Write the table destined for ``path`` (Parquet, or CSV by its suffix) into the
    temporary file ``tmp``; the caller renames it into place, or removes it."""
    write_dataframe(dataframe(columns), tmp, path)


def write_dataframe(df: pl.DataFrame, tmp: str | pathlib.Path, path: str | pathlib.Path) -> None:
    """Write ``df`` to ``tmp`` as the table file ``path`` will be: CSV when ``path`` ends
    in .csv, else zstd Parquet. A polars error (e.g. a full disk) becomes a one-line
    ``ReplayError`` naming ``path``."""
    try:
        if pathlib.Path(path).suffix.lower() == ".csv":
            df.write_csv(tmp)
        else:
            df.write_parquet(tmp, compression="zstd")
    except pl.exceptions.PolarsError as exc:  # e.g. a full disk ("os error 28")
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ReplayError(f"could not write {path}: {first}") from None


def _names(codes: np.ndarray | list, names: list[str], column: str) -> pl.Series:
    """Integer codes as an Enum column; -1 (or any code outside ``names``) becomes null."""
    codes = np.asarray(codes, dtype=np.int64)
    labels = np.array([*names, None], dtype=object)
    idx = np.where((codes >= 0) & (codes < len(names)), codes, len(names))
    return pl.Series(column, labels[idx].tolist(), dtype=pl.Enum(names))
