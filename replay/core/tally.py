"""What ``replay run`` says about hindsight: how many agents really came close to the ego,
and how many of those the cascade dropped (the table and the recording carry the same
truth per row; this is their one-line total)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from outputs.sinks import FrameResult, SceneInfo
from risk.hindsight import LABEL_POSITIVE, HindsightSettings, truth_for_rows


@dataclass(frozen=True)
class HindsightCounts:
    """Distinct agents (and agent-frames) that came close, and those the cascade dropped."""

    came_close: int
    close_frames: int
    dropped: int  # of the agents that came close, dropped by a stage at least once
    dropped_frames: int
    settings: HindsightSettings


class HindsightTally:
    """A replay sink that counts, at its close, the hindsight positives of the replayed
    frames and the cascade's misses among them (:attr:`counts`; None when the scene
    has no recorded tracks)."""

    timing_name = "hindsight"

    def __init__(self, settings: HindsightSettings | None = None) -> None:
        self.settings = settings or HindsightSettings()
        self._info: SceneInfo | None = None
        self._rows: list[tuple[np.ndarray, ...]] = []
        self.counts: HindsightCounts | None = None

    def begin(self, info: SceneInfo) -> None:
        self._info = info

    def add(self, result: FrameResult) -> None:
        frame, cascade = result.frame, result.cascade
        others = np.flatnonzero(cascade.others)
        ids = frame.ids[others]
        self._rows.append(
            (
                np.full(ids.size, float(frame.t)),
                np.full(ids.size, int(frame.ids[frame.ego])),
                ids,
                cascade.dropped_at[others] >= 0,
            )
        )

    def close(self) -> None:
        if self._info is None or self._info.tracks is None or not self._rows:
            return
        t, ego, agent, dropped = (np.concatenate(c) for c in zip(*self._rows, strict=True))
        _, _, label = truth_for_rows(self._info.tracks(), t, ego, agent, settings=self.settings)
        close = label == LABEL_POSITIVE
        missed = close & dropped
        pairs = np.stack((ego, agent), axis=1)
        self.counts = HindsightCounts(
            came_close=len(np.unique(pairs[close], axis=0)),
            close_frames=int(close.sum()),
            dropped=len(np.unique(pairs[missed], axis=0)),
            dropped_frames=int(missed.sum()),
            settings=self.settings,
        )
        self._rows = []

    def abort(self) -> None:
        self._rows = []


def format_counts(c: HindsightCounts) -> str:
    """One line for the end of ``replay run``."""
    s = c.settings
    rule = f"a box gap of {s.gap_m:g} m or a PET of {s.pet_s:g} s within {s.horizon_s:g} s"
    if c.came_close == 0:
        return f"Hindsight: no agent really came close to the ego ({rule})"
    return (
        f"Hindsight: {c.came_close} agent(s) really came close to the ego ({rule}) in"
        f" {c.close_frames} agent-frames; the cascade dropped {c.dropped} of them"
        f" ({c.dropped_frames} agent-frames)"
    )
