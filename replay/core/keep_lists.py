"""The keep-list sink: the cascade's answer for every frame, by agent id, for a planner
stack to read.

One row per frame (and ego, with ``--ego all``): ``frame``, ``t_s``, ``ego_id``,
``kept`` (ids, most important first), one list of ids per planner tier (``tier_<name>``),
``dropped`` (``{"id": "stage"}`` in JSON Lines; ``dropped_ids`` and ``dropped_by`` lists
in Parquet) and ``filter_ms`` (the cascade's own compute time). The answer is
:func:`risk.filtering.cascade_answer`, the same one :func:`risk.filter_frame` returns.

JSON Lines (``.jsonl``) or Parquet (``.parquet``), by suffix; written once at
``close()`` to a temporary file beside the target and renamed into place.
"""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any

from outputs.atomic import atomic_write, write_text
from outputs.sinks import FrameResult, SceneInfo
from replay.errors import ReplayError
from risk.filtering import cascade_answer

SUFFIXES = (".jsonl", ".parquet")


class KeepListSink:
    """A sink that writes the cascade's per-frame keep-lists (see the module docstring)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = pathlib.Path(path)
        if self.path.suffix not in SUFFIXES:
            raise ReplayError(
                f"{self.path}: a keep-list file ends in .jsonl (JSON Lines) or .parquet, "
                f"not {self.path.suffix or 'no suffix'!r}"
            )
        self.rows: list[dict[str, Any]] = []
        self.info: SceneInfo | None = None
        self.outputs: tuple[pathlib.Path, ...] = ()

    def begin(self, info: SceneInfo) -> None:
        self.info = info

    def add(self, result: FrameResult) -> None:
        assert self.info is not None, "begin() first"
        config = self.info.cascade
        answer = cascade_answer(result.frame, result.cascade, config)
        row: dict[str, Any] = {
            "frame": result.index,
            "t_s": answer.t_s,
            "ego_id": answer.ego_id,
            "n_others": answer.n_others,
            "kept": [int(i) for i in answer.kept_ids],
        }
        for name, ids in answer.tiers.items():
            row[f"tier_{name}"] = list(ids)
        row["dropped"] = {str(k): v for k, v in answer.dropped.items()}
        row["filter_ms"] = answer.time_ms
        self.rows.append(row)

    def close(self) -> None:
        if self.path.suffix == ".jsonl":
            text = "".join(json.dumps(row, separators=(",", ":")) + "\n" for row in self.rows)
            write_text(self.path, text)
        else:
            import polars as pl  # polars: 0.3 s to import, only for a Parquet keep-list

            rows = [
                {
                    **{k: v for k, v in row.items() if k != "dropped"},
                    "dropped_ids": [int(k) for k in row["dropped"]],
                    "dropped_by": list(row["dropped"].values()),
                }
                for row in self.rows
            ]
            schema = {
                "kept": pl.List(pl.Int64),
                "dropped_ids": pl.List(pl.Int64),
                "dropped_by": pl.List(pl.String),
            }
            frame = pl.DataFrame(rows, schema_overrides=schema, infer_schema_length=None)
            atomic_write(self.path, frame.write_parquet)
        self.outputs = (self.path,)

    def abort(self) -> None:
        self.rows = []
