"""The table sink: one row per frame and agent, written as Parquet or CSV (polars).

Rows: every valid agent other than the ego, in every processed frame (the agents that get
a risk value). Columns, in order:

- ``frame`` (frame index in the scene), ``t_s`` (s), ``ego_id``, ``agent_id``, ``kind``;
- ``x_m``, ``y_m``, ``speed_mps``: the agent's state;
- ``risk_<model>``: every model's risk on all agents (units per model, see
  ``docs/models.md`` or ``replay models``);
- ``kept_<model>``: kept after that cascade stage (stages in cascade order);
- ``dropped_by``: the stage model that dropped the agent, null if it survived;
- ``tier``: deepest planner tier reached, by name, null if none;
- ``baseline``: survival baseline (``R_S >= baseline_threshold``) on all agents;
- ``truth_gap_m``, ``truth_pet_s``, ``truth_label``: the hindsight truth from the scene's
  recorded future (:mod:`risk.hindsight`, ``docs/hindsight.md``): least box clearance at
  equal times within the horizon (m), post-encroachment time (s; null when the footprints
  do not meet), and whether the agent really came close (true / false, null when the
  window is censored). All null when the engine cannot give the recorded tracks.

The file is written once, at ``close()``, to a temporary name in the target folder and
renamed into place, so a failed run never leaves a half-written table.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np
import polars as pl

from base.atomic import atomic_output
from base.sinks import FrameResult, SceneInfo
from replay.errors import ReplayError
from risk.frame import KIND_NAMES
from risk.hindsight import LABEL_POSITIVE, LABEL_UNKNOWN, HindsightSettings, truth_for_rows

TRUTH_COLUMNS = ("truth_gap_m", "truth_pet_s", "truth_label")

SUFFIXES = (".parquet", ".csv")


class TableSink:
    """A :class:`replay.engine.Sink` that collects per-agent rows and writes one table.

    With ``path=None`` nothing is written: the rows stay in memory for :meth:`dataframe`
    (what ``replay stats`` uses).
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | None,
        *,
        hindsight: HindsightSettings | None = None,
    ):
        self.hindsight = hindsight or HindsightSettings()
        self._info: SceneInfo | None = None
        self._chunks: list[dict[str, np.ndarray]] = []
        self.path = None if path is None else pathlib.Path(path)
        if self.path is None:
            return
        if self.path.suffix.lower() not in SUFFIXES:
            raise ReplayError(
                f"{self.path}: table files must end in .parquet or .csv, got "
                f"{self.path.suffix or 'no suffix'!r}"
            )
        if not self.path.parent.is_dir():
            raise ReplayError(f"{self.path}: the folder {self.path.parent} does not exist")

    def begin(self, info: SceneInfo) -> None:
        # Rows accumulate over begin() calls (one per ego with ``--ego all``) until close().
        self._info = info

    def add(self, result: FrameResult) -> None:
        info = self._require_info()
        frame, res = result.frame, result.cascade
        rows = np.flatnonzero(res.others)
        n = rows.size
        chunk: dict[str, np.ndarray] = {
            "frame": np.full(n, result.index, dtype=np.int32),
            "t_s": np.full(n, frame.t),
            "ego_id": np.full(n, frame.ego_id, dtype=np.int64),
            "agent_id": frame.ids[rows],
            "kind": frame.kinds[rows],
            "x_m": frame.xy[rows, 0],
            "y_m": frame.xy[rows, 1],
            "speed_mps": frame.speed[rows],
        }
        for model in info.model_names:
            chunk[f"risk_{model}"] = result.risks[model][rows]
        for s, stage in enumerate(res.stage_names):
            chunk[f"kept_{stage}"] = res.kept[s, rows]
        chunk["dropped_at"] = res.dropped_at[rows]
        chunk["tier"] = res.tier[rows]
        chunk["baseline"] = res.baseline[rows]
        self._chunks.append(chunk)

    def dataframe(self) -> pl.DataFrame:
        """Everything added so far as one DataFrame (the columns of the module docstring)."""
        info = self._require_info()
        keys = self._columns(info)
        data = {
            k: np.concatenate([c[k] for c in self._chunks]) if self._chunks else [] for k in keys
        }
        df = pl.DataFrame(
            {k: v for k, v in data.items() if k not in ("kind", "dropped_at", "tier")}
        )
        stage_names = list(info.cascade.stage_names)
        tier_names = [t.name for t in info.cascade.tiers]
        df = df.with_columns(
            _names(data["kind"], list(KIND_NAMES), "kind"),
            _names(data["dropped_at"], stage_names, "dropped_by"),
            _names(data["tier"], tier_names, "tier"),
        )
        df = df.with_columns(self._truth(data["t_s"], data["ego_id"], data["agent_id"]))
        return df.select([*keys[:5], *keys[5:-3], "dropped_by", "tier", "baseline", *TRUTH_COLUMNS])

    def _truth(self, t_s: np.ndarray, ego_id: np.ndarray, agent_id: np.ndarray) -> list[pl.Series]:
        """The hindsight columns for rows (t_s, ego_id, agent_id), from the scene's tracks."""
        n = len(t_s)
        gap, pet = np.full(n, np.nan), np.full(n, np.nan)
        label = np.full(n, LABEL_UNKNOWN, dtype=np.int8)
        get_tracks = self._require_info().tracks
        if n and get_tracks is not None:
            gap, pet, label = truth_for_rows(
                get_tracks(), t_s, ego_id, agent_id, settings=self.hindsight
            )
        labels = np.array([None, False, True], dtype=object)[
            np.where(label == LABEL_UNKNOWN, 0, np.where(label == LABEL_POSITIVE, 2, 1))
        ]
        return [
            pl.Series("truth_gap_m", gap).fill_nan(None),
            pl.Series("truth_pet_s", pet).fill_nan(None),
            pl.Series("truth_label", labels.tolist(), dtype=pl.Boolean),
        ]

    def close(self) -> None:
        if self.path is None:
            return  # in memory: the rows stay available through dataframe()
        df = self.dataframe()
        try:
            with atomic_output(self.path) as tmp:
                if self.path.suffix.lower() == ".csv":
                    df.write_csv(tmp)
                else:
                    df.write_parquet(tmp, compression="zstd")
        except pl.exceptions.PolarsError as exc:  # e.g. a full disk ("os error 28")
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise ReplayError(f"could not write {self.path}: {first}") from None
        self._chunks = []

    def abort(self) -> None:
        self._chunks = []  # nothing is on disk before close()

    def _require_info(self) -> SceneInfo:
        if self._info is None:
            raise ReplayError("TableSink: begin() must be called before add()")
        return self._info

    @staticmethod
    def _columns(info: SceneInfo) -> list[str]:
        return [
            "frame", "t_s", "ego_id", "agent_id", "kind", "x_m", "y_m", "speed_mps",
            *(f"risk_{m}" for m in info.model_names),
            *(f"kept_{s}" for s in info.cascade.stage_names),
            "dropped_at", "tier", "baseline",
        ]  # fmt: skip


def _names(codes: np.ndarray | list, names: list[str], column: str) -> pl.Series:
    """Integer codes as an Enum column; -1 (or any code outside ``names``) becomes null."""
    codes = np.asarray(codes, dtype=np.int64)
    labels = np.array([*names, None], dtype=object)
    idx = np.where((codes >= 0) & (codes < len(names)), codes, len(names))
    return pl.Series(column, labels[idx].tolist(), dtype=pl.Enum(names))
