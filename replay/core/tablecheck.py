"""Checks of an agents table read back from disk (``replay run --table``), so that a
damaged or foreign table is reported instead of feeding impossible values into the
statistics: no rows, non-numeric risk columns, or a risk outside its model's range.

Ranges: each model's ``risk_range`` in the registry (:data:`risk.MODELS`; docs/models.md):
``[0, 1]`` for all but ``gaussian`` (``[0, inf)``, unit 1/m^2). NaN is allowed (the ego and
invalid agents have no risk). A column of a model the registry does not know is held to
``[0, 1]``.
"""

from __future__ import annotations

import os

import polars as pl

from replay.errors import ReplayError
from risk.registry import MODELS

RISK_PREFIX = "risk_"
DEFAULT_RANGE = (0.0, 1.0)
RANGES: dict[str, tuple[float, float]] = {name: spec.risk_range for name, spec in MODELS.items()}
TOLERANCE = 1e-9  # float noise at the ends of a range


class TableError(ReplayError):
    """A table file holds values no ``replay run --table`` could have written."""


def check_agents_table(df: pl.DataFrame, path: str | os.PathLike[str]) -> None:
    """Raise :class:`TableError` naming ``path`` when the table is empty, a risk column
    is not numeric, or a risk value is outside its model's range."""
    if df.height == 0:
        raise TableError(f"{path}: the table has no rows; replay the scene again")
    check_column_types(df, path)
    for column in (c for c in df.columns if c.startswith(RISK_PREFIX)):
        dtype = df.schema[column]
        if not (dtype.is_numeric() or dtype == pl.Null):
            raise TableError(
                f"{path}: column {column} holds {dtype} values, not numbers; the table is"
                " damaged or not from 'replay run --table'"
            )
        model = column.removeprefix(RISK_PREFIX)
        lo, hi = RANGES.get(model, DEFAULT_RANGE)
        values = pl.col(column).cast(pl.Float64)
        bad = df.select(
            (values.is_infinite() | (values < lo - TOLERANCE) | (values > hi + TOLERANCE)).sum()
        ).item()
        if bad:
            first = df.filter(
                values.is_infinite() | (values < lo - TOLERANCE) | (values > hi + TOLERANCE)
            )[column][0]
            raise TableError(
                f"{path}: {bad} value(s) of {column} lie outside the model's range"
                f" [{lo:g}, {hi:g}] (e.g. {first:g}); the table is damaged, replay the scene"
                " again"
            )


#: Columns of an agents table that hold integers (ids, frame numbers) or numbers.
INTEGER_COLUMNS = ("frame", "agent_id", "ego_id")
NUMBER_COLUMNS = ("t_s",)
FLAG_PREFIXES = ("baseline", "kept_", "truth_label")
#: Reference label columns: booleans, or null where unknown (issue 36: words, lists, a 2
#: or a NaN there gave a polars traceback or silently counted as true).
LABEL_PREFIXES = ("planner_label", "label_")


def check_column_types(df: pl.DataFrame, path: str | os.PathLike[str]) -> None:
    """Raise :class:`TableError` when an id or frame column is not integers, ``t_s`` not
    numbers, or a flag column (``baseline``, ``kept_*``) anything but booleans or the
    words true/false (a CSV stores them so): a table of the wrong types would otherwise
    fail deep inside the statistics, or count a ``maybe`` as false."""

    def wrong(column: str, what: str, dtype: object) -> TableError:
        return TableError(
            f"{path}: column {column} holds {dtype} values, not {what}; the table is damaged"
            " or not from 'replay run --table'"
        )

    for column in INTEGER_COLUMNS:
        if column in df.columns and not (df.schema[column].is_integer()):
            raise wrong(column, "integers", df.schema[column])
    for column in NUMBER_COLUMNS:
        if column in df.columns and not df.schema[column].is_numeric():
            raise wrong(column, "numbers", df.schema[column])
    for column in df.columns:
        if not column.startswith(FLAG_PREFIXES + LABEL_PREFIXES):
            continue
        dtype = df.schema[column]
        if dtype == pl.Boolean or (dtype == pl.Null and column.startswith(LABEL_PREFIXES)):
            continue
        if dtype != pl.String:
            raise wrong(column, "true/false", dtype)
        words = df[column].drop_nulls().str.to_lowercase()
        bad = words.filter(~words.is_in(["true", "false"]))
        if bad.len():
            raise TableError(
                f"{path}: column {column} holds {bad[0]!r}, not true/false; the table is"
                " damaged or not from 'replay run --table'"
            )
