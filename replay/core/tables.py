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
- ``truth_complete`` (the window is recorded for both: not censored), ``truth_yielded``
  (the ego braked while the agent was ahead on its path), ``track_ok`` (false: the ego's
  or the agent's track is inconsistent in the window, and the truth is left unknown);
- ``distance_m``: the centre distance from the ego (m), for nearest-K and radius budgets;
- ``label_<name>``: the dataset's own labels of the scene (``/labels``), one column per
  list name: the agent is in it.
- with a planner beside the replay: ``planner_label`` (removing the agent alone changes
  the plan; null when unknown) and ``planner_shift_m`` (m), :mod:`replay.planning.truth`.

The file is written once, at ``close()``, to a temporary name in the target folder and
renamed into place, so a failed run never leaves a half-written table.
"""

from __future__ import annotations

import importlib
import os
import pathlib
from typing import TYPE_CHECKING, Any

import numpy as np

from outputs import process as background_process
from outputs.atomic import commit, target_kind, temp_path_beside
from outputs.sinks import FrameResult, SceneInfo
from replay.core.table_columns import LABEL_PREFIX, PLANNER_COLUMNS, TableColumns
from replay.errors import ReplayError
from risk.hindsight import HindsightSettings, RowTruth, rows_truth

if TYPE_CHECKING:
    import polars as pl

#: The module that builds and writes the table with polars (replay.core.table_file).
TABLE_WRITER = "replay.core.table_file"


SUFFIXES = (".parquet", ".csv")


class TableSink:
    """A :class:`replay.core.engine.Sink` that collects per-agent rows and writes one table.

    With ``path=None`` nothing is written: the rows stay in memory for :meth:`dataframe`
    (what ``replay stats`` uses). ``background``: write the file in the output process
    (:mod:`outputs.process`), which imports polars while the replay runs; ignored where
    that cannot help (one CPU) or cannot work (no ``fork``).
    """

    timing_name = "writing the table"  # (the run's timing line names stages, not classes)

    def __init__(
        self,
        path: str | os.PathLike[str] | None,
        *,
        hindsight: HindsightSettings | None = None,
        background: bool = False,
    ):
        self.hindsight = hindsight or HindsightSettings()
        self.background = bool(background)
        self._process: background_process.OutputProcess | None = None
        self._info: SceneInfo | None = None
        self._chunks: list[dict[str, np.ndarray]] = []
        self.path = None if path is None else pathlib.Path(path)
        if self.path is None:
            return
        if self.path.suffix.lower() not in SUFFIXES and target_kind(self.path) != "device":
            raise ReplayError(
                f"{self.path}: table files must end in .parquet or .csv, got "
                f"{self.path.suffix or 'no suffix'!r}"
            )
        if not self.path.parent.is_dir():
            raise ReplayError(f"{self.path}: the folder {self.path.parent} does not exist")

    def begin(self, info: SceneInfo) -> None:
        # Rows accumulate over begin() calls (one per ego with ``--ego all``) until close().
        self._info = info
        if self.background and self.path is not None and self._process is None:
            self._process = background_process.acquire(preload=(TABLE_WRITER,))

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
            "distance_m": np.hypot(*(frame.xy[rows] - frame.xy[frame.ego]).T),
        }
        for model in info.model_names:
            chunk[f"risk_{model}"] = result.risks[model][rows]
        for s, stage in enumerate(res.stage_names):
            chunk[f"kept_{stage}"] = res.kept[s, rows]
        chunk["dropped_at"] = res.dropped_at[rows]
        chunk["tier"] = res.tier[rows]
        chunk["baseline"] = res.baseline[rows]
        for name, ids in info.labels.items():  # the dataset's own labels
            chunk[LABEL_PREFIX + name] = np.isin(frame.ids[rows], np.asarray(ids, dtype=np.int64))
        for name in PLANNER_COLUMNS:  # a planner's labels, when one ran beside the replay
            if name in result.extras:
                chunk[name] = np.asarray(result.extras[name], dtype=np.float64)[rows]
        self._chunks.append(chunk)

    def columns(self) -> TableColumns:
        """Everything added so far as numpy columns, the hindsight truth included."""
        info = self._require_info()
        keys = self._columns(info)
        extra = list(dict.fromkeys(k for c in self._chunks for k in c if k not in keys))
        labels = [k for k in extra if k.startswith(LABEL_PREFIX)]
        planner = [k for k in PLANNER_COLUMNS if k in extra]
        data: dict[str, Any] = {
            k: np.concatenate([c[k] for c in self._chunks]) if self._chunks else []
            for k in (*keys, *planner)
        }
        for k in labels:  # an ego's run without the list (another scene's): False
            data[k] = np.concatenate(
                [c.get(k, np.zeros(c["frame"].size, bool)) for c in self._chunks]
            )
        truth = self._truth(data["t_s"], data["ego_id"], data["agent_id"])
        return TableColumns(
            keys=tuple([*keys, *labels]),
            data=data,
            stage_names=tuple(info.cascade.stage_names),
            tier_names=tuple(t.name for t in info.cascade.tiers),
            truth_gap_m=truth.gap_m,
            truth_pet_s=truth.pet_s,
            truth_label=truth.label,
            truth_complete=truth.complete,
            truth_yielded=truth.yielded,
            track_ok=truth.track_ok,
        )

    def dataframe(self) -> pl.DataFrame:
        """Everything added so far as one polars DataFrame (the columns of the module
        docstring)."""
        from replay.core import table_file  # polars: about 0.3 s, only when asked for

        return table_file.dataframe(self.columns())

    def _truth(self, t_s: np.ndarray, ego_id: np.ndarray, agent_id: np.ndarray) -> RowTruth:
        """The hindsight truth of rows (t_s, ego_id, agent_id), from the scene's tracks
        (unknown without them)."""
        get_tracks = self._require_info().tracks
        if len(t_s) and get_tracks is not None:
            return rows_truth(get_tracks(), t_s, ego_id, agent_id, settings=self.hindsight)
        n = len(t_s)
        return RowTruth(
            np.full(n, np.nan), np.full(n, np.nan), np.full(n, -1, dtype=np.int8),
            np.zeros(n, bool), np.zeros(n, bool), np.ones(n, bool),
        )  # fmt: skip

    def close(self) -> None:
        if self.path is None:
            return  # in memory: the rows stay available through dataframe()
        columns = self.columns()
        tmp = temp_path_beside(self.path)
        try:
            if self._process is not None:
                self._process.run(f"{TABLE_WRITER}:write_temp", self.path, tmp, columns)
            else:  # polars: about 0.3 s, only when writing
                importlib.import_module(TABLE_WRITER).write_temp(self.path, tmp, columns)
            commit(tmp, self.path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            self._release()
            raise
        self._release()
        self._chunks = []

    def abort(self) -> None:
        self._chunks = []  # nothing is on disk before close()
        self._release()

    def _release(self) -> None:
        background_process.release(self._process)
        self._process = None

    def _require_info(self) -> SceneInfo:
        if self._info is None:
            raise ReplayError("TableSink: begin() must be called before add()")
        return self._info

    @staticmethod
    def _columns(info: SceneInfo) -> list[str]:
        return [
            "frame", "t_s", "ego_id", "agent_id", "kind", "x_m", "y_m", "speed_mps", "distance_m",
            *(f"risk_{m}" for m in info.model_names),
            *(f"kept_{s}" for s in info.cascade.stage_names),
            "dropped_at", "tier", "baseline",
        ]  # fmt: skip
