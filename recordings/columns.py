"""Arrow record batches in Rerun's column layout, built from numpy without per-row Python.

``rr.send_columns`` converts its inputs in Python and sends one entity per call; for a
scene of a hundred agents that means thousands of calls (about 0.2 ms each) and a slow
conversion of line strips. Rerun 0.41 also accepts a plain Arrow record batch whose
columns carry ``rerun:*`` metadata (entity path, component, archetype;
``rerun.chunk.Chunk.from_record_batch``): one ``send_record_batch`` then logs many
entities at once. This module builds such batches: index columns for the timelines,
and component columns partitioned by row (each row one frame, holding that frame's
instances).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa


@dataclass(frozen=True)
class Component:
    """What a component column is: its name, Rerun component type, archetype, item type."""

    name: str  # "LineStrips2D:strips"
    component_type: str  # "rerun.components.LineStrip2D"
    archetype: str  # "rerun.archetypes.LineStrips2D"
    item: pa.DataType

    @functools.cached_property
    def list_type(self) -> pa.DataType:
        """The column type: a list of ``item`` per row."""
        return pa.list_(self.item)

    @functools.cached_property
    def metadata(self) -> dict[str, str]:
        """The column metadata Rerun reads, except the entity path."""
        return {
            "rerun:component": self.name,
            "rerun:component_type": self.component_type,
            "rerun:archetype": self.archetype,
            "rerun:kind": "data",
        }


_POINT2D = pa.list_(pa.field("item", pa.float32(), nullable=False), 2)
_STRIP2D = pa.list_(pa.field("item", _POINT2D, nullable=False))

STRIPS = Component(
    "LineStrips2D:strips", "rerun.components.LineStrip2D", "rerun.archetypes.LineStrips2D", _STRIP2D
)
STRIP_COLORS = Component(
    "LineStrips2D:colors", "rerun.components.Color", "rerun.archetypes.LineStrips2D", pa.uint32()
)
STRIP_RADII = Component(
    "LineStrips2D:radii", "rerun.components.Radius", "rerun.archetypes.LineStrips2D", pa.float32()
)
STRIP_LABELS = Component(
    "LineStrips2D:labels", "rerun.components.Text", "rerun.archetypes.LineStrips2D", pa.utf8()
)
SCALARS = Component(
    "Scalars:scalars", "rerun.components.Scalar", "rerun.archetypes.Scalars", pa.float64()
)
SERIES_COLORS = Component(
    "SeriesLines:colors", "rerun.components.Color", "rerun.archetypes.SeriesLines", pa.uint32()
)
SERIES_WIDTHS = Component(
    "SeriesLines:widths", "rerun.components.StrokeWidth", "rerun.archetypes.SeriesLines",
    pa.float32(),
)  # fmt: skip
SERIES_NAMES = Component(
    "SeriesLines:names", "rerun.components.Name", "rerun.archetypes.SeriesLines", pa.utf8()
)
DRAW_ORDER = Component(
    "LineStrips2D:draw_order", "rerun.components.DrawOrder", "rerun.archetypes.LineStrips2D",
    pa.float32(),
)  # fmt: skip
SHOW_LABELS = Component(
    "LineStrips2D:show_labels", "rerun.components.ShowLabels", "rerun.archetypes.LineStrips2D",
    pa.bool_(),
)  # fmt: skip
LOG_TEXT = Component("TextLog:text", "rerun.components.Text", "rerun.archetypes.TextLog", pa.utf8())
LOG_LEVEL = Component(
    "TextLog:level", "rerun.components.TextLogLevel", "rerun.archetypes.TextLog", pa.utf8()
)
LOG_COLOR = Component(
    "TextLog:color", "rerun.components.Color", "rerun.archetypes.TextLog", pa.uint32()
)


def pack_colors(rgb: np.ndarray) -> np.ndarray:
    """``(K, 3)`` RGB or ``(K, 4)`` RGBA uint8 -> ``(K,)`` uint32 ``0xRRGGBBAA`` (Rerun's Color)."""
    c = np.asarray(rgb, dtype=np.uint32)
    alpha = c[:, 3] if c.shape[1] == 4 else np.uint32(0xFF)
    return (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | alpha


def strips(points: np.ndarray, points_per_strip: np.ndarray) -> pa.Array:
    """Line strips from flat points: ``(T, 2)`` m and ``(K,)`` counts summing to ``T``."""
    flat = pa.array(np.ascontiguousarray(points, dtype=np.float32).reshape(-1), pa.float32())
    xy = pa.FixedSizeListArray.from_arrays(flat, type=_POINT2D)
    offsets = np.concatenate([[0], np.cumsum(points_per_strip)]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), xy, type=_STRIP2D)


def uniform_strips(polylines: np.ndarray) -> pa.Array:
    """Line strips of equal length: ``(K, P, 2)`` m."""
    k, p = polylines.shape[:2]
    return strips(polylines.reshape(-1, 2), np.full(k, p))


def rows(values: pa.Array | np.ndarray, lengths: np.ndarray, item: pa.DataType) -> pa.ListArray:
    """A column whose row ``f`` holds the next ``lengths[f]`` values (0: an empty batch)."""
    if not isinstance(values, pa.Array):
        values = pa.array(values, item)
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), values)


def one_per_row(values, item: pa.DataType, missing: np.ndarray | None = None) -> pa.Array:
    """A column of one value per row; rows where ``missing`` is True hold nothing (null).

    Built from buffers (validity bitmap + offsets): ``ListArray.from_arrays(mask=...)``
    would pull in ``pyarrow.compute``, a third of a second to import.
    """
    values = values if isinstance(values, pa.Array) else pa.array(values, item)
    n = len(values)
    offsets = pa.py_buffer(np.arange(n + 1, dtype=np.int32).tobytes())
    validity = None
    if missing is not None:
        valid = ~np.asarray(missing, dtype=bool)
        validity = pa.py_buffer(np.packbits(valid, bitorder="little").tobytes())
    return pa.Array.from_buffers(
        pa.list_(item), n, [validity, offsets], children=[values],
        null_count=-1 if missing is not None else 0,
    )  # fmt: skip


@dataclass
class Batch:
    """Columns for many entities over shared timelines, sent as one record batch.

    ``indexes``: ``{timeline name: (values, arrow type)}``; empty for static data.
    """

    indexes: dict[str, tuple[np.ndarray, pa.DataType]] = field(default_factory=dict)
    _fields: list[pa.Field] = field(default_factory=list)
    _arrays: list[pa.Array] = field(default_factory=list)

    def add(self, entity: str, component: Component, column: pa.Array) -> None:
        target = component.list_type
        if column.type != target:
            raise TypeError(f"{entity}:{component.name}: column type {column.type} is not {target}")
        meta = {"rerun:entity_path": entity, **component.metadata}
        self._fields.append(pa.field(f"{entity}:{component.name}", target, metadata=meta))
        self._arrays.append(column)

    def __len__(self) -> int:
        return len(self._arrays)

    def send(self, rec) -> None:
        """Log every column (a no-op when there is none)."""
        if not self._arrays:
            return
        fields, arrays = [], []
        for name, (values, dtype) in self.indexes.items():
            fields.append(
                pa.field(name, dtype, metadata={"rerun:kind": "index", "rerun:index_name": name})
            )
            arrays.append(pa.array(values, dtype))
        batch = pa.RecordBatch.from_arrays(
            arrays + self._arrays, schema=pa.schema(fields + self._fields)
        )
        rec.send_record_batch(batch, index=None if not self.indexes else list(self.indexes))
