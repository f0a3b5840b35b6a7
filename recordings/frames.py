"""The arrays a recording is made of, handed from the recorder (:mod:`recordings.recorder`,
in the replay's process) to the writer (:mod:`recordings.writer`, which imports rerun,
often in the output process). numpy only: both sides import it, neither imports the
other's module for its types.
"""

from __future__ import annotations

import pathlib
from dataclasses import dataclass, field, fields

import numpy as np

from recordings.errors import RecordingError

APPLICATION_ID = "riskreplay"

#: Agents (other than the ego) a recording draws at most: rerun encodes each as its own
#: entity, about 1 ms each (20,000 agents in one frame: 23 s measured, and minutes before
#: the risk timelines were bounded too). Checked before the replay when the scene's
#: tracks are known, else when writing.
MAX_RECORDED_AGENTS = 5000


@dataclass(frozen=True)
class WriteOptions:
    """How to draw the recording (see :class:`SceneRecorder`)."""

    labels: str = "kept"
    links: bool = False
    log10_decades: float = 4.0
    application_id: str = APPLICATION_ID


@dataclass
class FrameRows:
    """One frame, restricted to its valid agents (ego included). ``n`` valid agents."""

    index: int
    t: float
    ids: np.ndarray  # (n,) int64
    xy: np.ndarray  # (n, 2) m
    heading: np.ndarray  # (n,) rad
    length: np.ndarray  # (n,) m
    width: np.ndarray  # (n,) m
    is_ego: np.ndarray  # (n,) bool
    kept: np.ndarray  # (S, n) bool, kept after stage s
    dropped_at: np.ndarray  # (n,) int, stage that dropped the agent, -1 otherwise
    tier: np.ndarray  # (n,) int, deepest tier, -1 none
    survival: np.ndarray  # (n,) R_S of the survivors, NaN otherwise
    baseline: np.ndarray  # (n,) bool, baseline-important (others only)
    truth: np.ndarray  # (n,) float, hindsight label: 1 came close, 0 did not, NaN unknown
    risks: dict[str, np.ndarray]  # model -> (n,)
    false_negatives: np.ndarray  # (S,) int
    stage_time_s: np.ndarray  # (S,) s
    sort_time_s: float
    survival_all_time_s: float
    ego_paths: list[np.ndarray]  # the ego's path candidates, each (P, 2) m
    survivor_paths: np.ndarray  # (R, P, 2) m, deeper-tier survivors' candidates (padded)
    survivor_path_risk: np.ndarray  # (R,) R_S of each candidate's owner (colour)
    survivor_path_owner: np.ndarray  # (R,) id of each candidate's owner
    # With a planner beside the replay (replay run --planner): the plans with all agents
    # and with the cascade's agents, (T, 2) m ((0, 2) without a plan), and their times.
    plan_all: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    plan_filtered: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    plan_all_ms: float = float("nan")
    plan_filtered_ms: float = float("nan")


@dataclass(frozen=True)
class PackedFrames:
    """A list of :class:`FrameRows` as a few large arrays, to hand to the output process:
    pickling the demo's 100 frames (about 3,000 small arrays) took 36 ms and unpickling
    18 ms, this form about 2 ms each. :meth:`unpack` gives the frames back, equal field
    by field (their arrays are views of the large ones)."""

    n_frames: int
    scalars: dict[str, np.ndarray]  # field -> (F,) values
    #: (field, key) -> (values of all items raveled, their shapes (I, ndim)); the key is
    #: the dict key of ``risks``, else "". One item per frame, or a list's items.
    arrays: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]
    list_lengths: dict[str, np.ndarray]  # list field -> (F,) items per frame

    @classmethod
    def pack(cls, frames: list[FrameRows]) -> PackedFrames:
        scalars: dict[str, np.ndarray] = {}
        arrays: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]] = {}
        lengths: dict[str, np.ndarray] = {}
        for f in fields(FrameRows):
            values = [getattr(fr, f.name) for fr in frames]
            if f.type in ("int", "float"):
                scalars[f.name] = np.array(values, dtype=f.type)
            elif f.type.startswith("dict"):
                for key in values[0] if values else ():
                    arrays[f.name, key] = _stack([v[key] for v in values])
            elif f.type.startswith("list"):
                lengths[f.name] = np.array([len(v) for v in values], dtype=np.int64)
                arrays[f.name, ""] = _stack([a for v in values for a in v])
            else:
                arrays[f.name, ""] = _stack(values)
        return cls(len(frames), scalars, arrays, lengths)

    def unpack(self) -> list[FrameRows]:
        items = {k: _unstack(*v) for k, v in self.arrays.items()}
        out: list[dict[str, object]] = [{} for _ in range(self.n_frames)]
        for name, values in self.scalars.items():
            for row, v in zip(out, values.tolist(), strict=True):
                row[name] = v
        for f in fields(FrameRows):
            if f.type.startswith("dict"):
                keys = [k for (name, k) in items if name == f.name]
                for i, row in enumerate(out):
                    row[f.name] = {k: items[f.name, k][i] for k in keys}
            elif f.type.startswith("list"):
                ends = np.cumsum(self.list_lengths[f.name]).tolist()
                for row, start, end in zip(out, [0, *ends], ends, strict=False):
                    row[f.name] = items[f.name, ""][start:end]
            elif f.name not in self.scalars:
                for i, row in enumerate(out):
                    row[f.name] = items[f.name, ""][i]
        return [FrameRows(**row) for row in out]  # type: ignore[arg-type]


def _stack(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Arrays of one dtype and rank as (their values raveled and joined, their shapes)."""
    if not arrays:
        return np.zeros(0), np.zeros((0, 1), dtype=np.int64)
    flat = np.concatenate([np.ravel(a) for a in arrays])
    return flat, np.array([a.shape for a in arrays], dtype=np.int64).reshape(len(arrays), -1)


def _unstack(flat: np.ndarray, shapes: np.ndarray) -> list[np.ndarray]:
    ends = np.cumsum(np.prod(shapes, axis=1)).tolist()
    starts = [0, *ends][:-1]
    return [flat[a:b].reshape(sh) for a, b, sh in zip(starts, ends, shapes.tolist(), strict=True)]


@dataclass
class SceneRows:
    """All frames of a recording concatenated (:func:`recordings.writer` builds it): ``K`` agent rows in total, ``F`` frames."""

    times_s: np.ndarray  # (F,) s
    frame_index: np.ndarray  # (F,) int
    frame_of: np.ndarray  # (K,) row -> position in the frame list
    false_negatives: np.ndarray  # (F, S) int, cumulative per stage
    stage_time_ms: np.ndarray  # (F, S) ms
    sort_time_ms: np.ndarray  # (F,) ms
    survival_all_time_ms: np.ndarray  # (F,) ms
    rows: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (K, ...) or (S, K)
    #: _agent_grid's result, computed once: agent ids, column of each row, first and last frame
    grid: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


def too_many_agents(output: pathlib.Path, n_agents: int) -> RecordingError:
    """The error for a scene of more than :data:`MAX_RECORDED_AGENTS` other agents."""
    return RecordingError(
        f"could not write {output}: the scene has {n_agents} agents besides the ego, more"
        f" than the {MAX_RECORDED_AGENTS} a recording draws (each is its own entity in"
        " the viewer, and encoding them takes minutes); write a table instead (--no-rrd"
        " --table FILE)"
    )
