"""The Rerun recording of a replay: a :class:`outputs.sinks.Sink` that writes one ``.rrd``.

``add()`` keeps only the arrays the recording needs (valid agents, the cascade outcome,
every model's risk, the paths to draw); ``close()`` adds the hindsight labels and writes
everything at once with :func:`recordings.writer.write_file` (batched, atomic: a
temporary file renamed at the end; ``abort()`` or any error leaves nothing behind).

This module does not import rerun. With ``background=True`` the writing runs in the
output process (:mod:`outputs.process`), started by ``begin()`` or earlier by the
command, which imports rerun (about 1 s) while the replay computes; ``close()`` hands it
the collected frames, waits for the temporary file and renames it into place. On one CPU,
or where processes cannot be forked (Windows, macOS), the recorder writes in its own
process.

What each entity shows is described in ``docs/recording.md``; paths, colours and the
blueprint live in :mod:`recordings.layout`, the Arrow batching in
:mod:`recordings.columns`, the summary text in :mod:`recordings.summary`.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
from dataclasses import replace
from typing import Any, Literal

import numpy as np

from outputs import process as output_process
from outputs.atomic import commit, temp_path_beside
from outputs.sinks import FrameResult, SceneInfo
from recordings.errors import RecordingError
from recordings.frames import (
    APPLICATION_ID,
    MAX_RECORDED_AGENTS,
    FrameRows,
    PackedFrames,
    WriteOptions,
    too_many_agents,
)
from risk.hindsight import LABEL_POSITIVE, LABEL_UNKNOWN, truth_for_rows

LabelMode = Literal["kept", "all", "none"]
LABEL_MODES: tuple[str, ...] = ("kept", "all", "none")
#: The module that writes the file (imports rerun).
WRITER = "recordings.writer"


class SceneRecorder:
    """Writes the replay of one scene to a Rerun ``.rrd`` file (a replay :class:`Sink`).

    ``output``: the ``.rrd`` path (its folder must exist). ``labels``: which agents carry
    their id as a label in the scene view: ``"kept"`` (the default: the ego, the tier
    agents and the misses, decluttered so that labels never overlap; every id shows on
    hover), ``"all"`` or ``"none"``. ``paths``: draw the deeper-tier survivors' forward
    path candidates. ``links``: draw the paper's Fig. 2 lines from the ego to every agent
    kept after each stage (off by default: in dense traffic they cover the agents).
    ``log10_decades``: a model's risk view plots
    log10(risk) when its positive values in the scene span more than this many decades
    (the raw values are always recorded under ``/risk``). ``background``: write in the
    output process, which imports rerun while the replay runs (see the module's text);
    ignored where that cannot help (one CPU) or cannot work (no ``fork``).
    """

    timing_name = "writing the recording"  # (named for the timing line, not the class)

    def __init__(
        self,
        output: str | os.PathLike[str],
        *,
        labels: LabelMode = "kept",
        paths: bool = True,
        links: bool = False,
        log10_decades: float = 4.0,
        application_id: str = APPLICATION_ID,
        background: bool = False,
    ) -> None:
        if labels not in LABEL_MODES:
            raise RecordingError(f"labels must be one of {', '.join(LABEL_MODES)}, got {labels!r}")
        self.output = pathlib.Path(output)
        self.labels = labels
        self.paths = paths
        self.links = links
        self.log10_decades = float(log10_decades)
        self.application_id = application_id
        self.background = bool(background) and output_process.available()
        self._info: SceneInfo | None = None
        self._frames: list[FrameRows] = []
        self._state = "new"  # new -> open -> closed | aborted
        self._tmp: pathlib.Path | None = None
        self._process: output_process.OutputProcess | None = None
        self._pending: output_process.Pending | None = None  # (start_close)

    # ------------------------------------------------------------------ Sink protocol
    def begin(self, info: SceneInfo) -> None:
        """Start a scene; fails early when the output cannot be written."""
        if self._state != "new":
            raise RecordingError(f"recorder for {self.output} was already started")
        folder = self.output.parent
        if not folder.is_dir():
            raise RecordingError(f"cannot write {self.output}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK):
            raise RecordingError(f"cannot write {self.output}: folder {folder} is not writable")
        if info.tracks is not None:  # refused before the replay, not after it
            n_others = info.tracks().n_agents - 1
            if n_others > MAX_RECORDED_AGENTS:
                raise too_many_agents(self.output, n_others)
        self._info = info
        self._state = "open"
        if self.background:  # the command's output process, or a new one
            self._process = output_process.acquire(preload=(WRITER,))

    def add(self, result: FrameResult) -> None:
        """Keep what the recording needs from one frame (nothing is written yet)."""
        if self._state != "open":
            raise RecordingError(f"add() on a recorder that is {self._state}; call begin() first")
        assert self._info is not None
        self._frames.append(_collect(result, self._info, keep_paths=self.paths))

    def start_close(self) -> None:
        """With the output process: send it the recording to write now, so that it
        writes while the other sinks close (:meth:`close` then waits for it). Does nothing
        otherwise, or when sent already."""
        if self._state != "open" or self._process is None or self._pending is not None:
            return
        assert self._info is not None
        self._tmp = temp_path_beside(self.output)
        try:
            frames = _with_hindsight(self._frames, self._info)
            # the tracks (a reader of the scene file) stay here: their labels are in frames
            info = replace(self._info, tracks=None)
            self._pending = self._process.submit(
                f"{WRITER}:write_temp", self.output, self._tmp, info, PackedFrames.pack(frames),
                self._options(),
            )  # fmt: skip
        except BaseException:
            self._discard()
            self._state = "aborted"
            raise

    def close(self) -> None:
        """Write the whole recording atomically (temp file, then rename) and finish."""
        if self._state != "open":
            raise RecordingError(f"close() on a recorder that is {self._state}")
        assert self._info is not None
        try:
            if self._process is not None:
                self.start_close()
                pending, self._pending = self._pending, None
                assert pending is not None
                pending.result()
            else:
                self._tmp = temp_path_beside(self.output)
                frames = _with_hindsight(self._frames, self._info)
                from recordings import writer  # rerun: about 1 s, only when writing

                writer.write_temp(self.output, self._tmp, self._info, frames, self._options())
            assert self._tmp is not None
            commit(self._tmp, self.output)
        except BaseException:
            self._discard()
            self._state = "aborted"
            raise
        self._tmp = None
        self._release()
        self._frames = []
        self._state = "closed"

    def abort(self) -> None:
        """Discard everything; no file is left behind. Safe to call at any time."""
        self._discard()
        self._frames = []
        self._state = "aborted"

    # ------------------------------------------------------------------ helpers
    def _options(self) -> WriteOptions:
        return WriteOptions(
            labels=self.labels,
            links=self.links,
            log10_decades=self.log10_decades,
            application_id=self.application_id,
        )

    def _release(self) -> None:
        output_process.release(self._process)
        self._process = None

    def _discard(self) -> None:
        try:
            if self._pending is not None:  # let the process finish its file first
                pending, self._pending = self._pending, None
                with contextlib.suppress(Exception):
                    pending.result()
        finally:  # (also on Ctrl-C: releasing a busy process ends it before the unlink)
            self._release()
            if self._tmp is not None:
                self._tmp.unlink(missing_ok=True)
                self._tmp = None


# ---------------------------------------------------------------------- collection
def _collect(result: FrameResult, info: SceneInfo, *, keep_paths: bool) -> FrameRows:
    """The arrays of one frame that the recording needs, valid agents only."""
    frame, casc = result.frame, result.cascade
    n = frame.n_agents
    stages = info.cascade.stage_names
    if casc.kept.shape != (len(stages), n):
        raise RecordingError(
            f"frame {result.index}: cascade reports {casc.kept.shape[0]} stages x "
            f"{casc.kept.shape[1]} agents, expected {len(stages)} x {n}"
        )
    missing = [m for m in info.model_names if m not in result.risks]
    if missing:
        raise RecordingError(f"frame {result.index}: no risk for model(s) {', '.join(missing)}")
    for m in info.model_names:
        if np.shape(result.risks[m]) != (n,):
            raise RecordingError(
                f"frame {result.index}: risk of {m} has shape {np.shape(result.risks[m])}, "
                f"expected ({n},)"
            )
    valid = np.asarray(frame.valid, dtype=bool)
    idx = np.flatnonzero(valid)
    is_ego = idx == frame.ego
    others = casc.others[idx]
    survivors = others & (casc.dropped_at[idx] < 0)
    ego_paths = frame.agent_paths(frame.ego) if keep_paths else []
    deep = survivors & (casc.tier[idx] >= 1)
    paths, path_risk = _survivor_paths(frame, casc.survival, idx[deep], keep_paths)
    return FrameRows(
        index=int(result.index),
        t=float(frame.t),
        ids=np.asarray(frame.ids[idx], dtype=np.int64),
        xy=np.asarray(frame.xy[idx]),
        heading=np.asarray(frame.heading[idx]),
        length=np.asarray(frame.length[idx]),
        width=np.asarray(frame.width[idx]),
        is_ego=is_ego,
        kept=np.asarray(casc.kept[:, idx], dtype=bool) & others[None, :],
        dropped_at=np.where(others, casc.dropped_at[idx], -1).astype(np.int64),
        tier=np.where(survivors, casc.tier[idx], -1).astype(np.int64),
        survival=np.where(survivors, casc.survival[idx], np.nan),
        baseline=np.asarray(casc.baseline[idx], dtype=bool) & others,
        truth=_truth(result, n)[idx],
        risks={m: np.asarray(result.risks[m][idx], dtype=np.float64) for m in info.model_names},
        false_negatives=np.asarray(casc.false_negatives, dtype=np.int64).reshape(len(stages)),
        stage_time_s=np.asarray(casc.stage_time_s, dtype=np.float64).reshape(len(stages)),
        sort_time_s=float(casc.sort_time_s),
        survival_all_time_s=float(casc.survival_all_time_s),
        ego_paths=ego_paths,
        survivor_paths=paths,
        survivor_path_risk=path_risk,
        survivor_path_owner=np.asarray(frame.ids, dtype=np.int64)[
            _path_owner_rows(frame, idx[deep], keep_paths)
        ],
        **_plans(result),
    )


def _plans(result: FrameResult) -> dict[str, Any]:
    """The planner's two plans of the frame, when one ran beside the replay."""
    out: dict[str, Any] = {}
    for key in ("plan_all", "plan_filtered"):
        plan = result.extras.get(key)
        if plan is None:
            continue
        ok = bool(getattr(plan, "ok", False))
        out[key] = np.asarray(plan.xy, dtype=np.float64) if ok else np.zeros((0, 2))
        out[f"{key}_ms"] = float(plan.plan_ms)
    return out


def _with_hindsight(frames: list[FrameRows], info: SceneInfo) -> list[FrameRows]:
    """Frames whose hindsight label the run did not give get it from the scene's recorded
    tracks, through the same rows function as the table's ``truth_label``
    (:func:`risk.hindsight.truth_for_rows`, default settings)."""
    need = [k for k, f in enumerate(frames) if np.isnan(f.truth).all()]
    if info.tracks is None or not need:
        return frames
    rows = [frames[k] for k in need]
    t_s = np.concatenate([np.full(f.ids.size, f.t) for f in rows])
    ego = np.concatenate([np.full(f.ids.size, f.ids[f.is_ego][0] if f.is_ego.any() else -1)
                          for f in rows])  # fmt: skip
    agent = np.concatenate([f.ids for f in rows])
    _, _, label = truth_for_rows(info.tracks(), t_s, ego, agent)
    value = np.where(label == LABEL_UNKNOWN, np.nan, (label == LABEL_POSITIVE).astype(float))
    out = list(frames)
    for k, part in zip(
        need, np.split(value, np.cumsum([f.ids.size for f in rows])[:-1]), strict=True
    ):
        out[k] = replace(frames[k], truth=np.where(frames[k].is_ego, np.nan, part))
    return out


def _truth(result: FrameResult, n: int) -> np.ndarray:
    """The hindsight label of every agent as float: 1 came close, 0 did not, NaN unknown.

    Read from ``result.truth_label`` when the run provides it (``(N,)`` of True / False /
    None-or-NaN for censored); all NaN otherwise.
    """
    labels = getattr(result, "truth_label", None)
    if labels is None:
        return np.full(n, np.nan)
    raw = np.asarray(labels, dtype=object).reshape(-1)
    if raw.size != n:
        raise RecordingError(
            f"frame {result.index}: truth_label has {raw.size} values, expected {n}"
        )
    unknown = np.array([v is None for v in raw.tolist()], dtype=bool)
    values = np.where(unknown, np.nan, raw).astype(np.float64)
    return np.where(np.isnan(values), np.nan, (values != 0).astype(np.float64))


def _path_owner_rows(frame, survivor_idx: np.ndarray, keep: bool) -> np.ndarray:
    """The agent index owning each row of :func:`_survivor_paths`' output."""
    if not keep or survivor_idx.size == 0:
        return np.zeros(0, dtype=np.int64)
    is_survivor = np.zeros(frame.n_agents, dtype=bool)
    is_survivor[survivor_idx] = True
    return np.asarray(frame.path_agent)[np.flatnonzero(is_survivor[frame.path_agent])]


def _survivor_paths(
    frame, survival: np.ndarray, survivor_idx: np.ndarray, keep: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The padded path candidates ``(R, P, 2)`` of the survivors and their owners' R_S."""
    if not keep or survivor_idx.size == 0:
        return np.zeros((0, 1, 2)), np.zeros(0)
    is_survivor = np.zeros(frame.n_agents, dtype=bool)
    is_survivor[survivor_idx] = True
    rows = np.flatnonzero(is_survivor[frame.path_agent])
    return np.asarray(frame.paths[rows]), np.asarray(survival[frame.path_agent[rows]])
