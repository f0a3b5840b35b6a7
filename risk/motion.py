"""How far each agent of a scene moves: the rule behind "a moving agent" and the default ego.

Drone and camera recordings have no ego vehicle, so any agent that moves can serve as one.
"Moves" is measured as the **travel extent**: the largest distance of the agent's recorded
centre from its first recorded centre. Unlike the summed frame-to-frame path length, the
extent does not grow with position jitter: a parked car tracked at 25 Hz with a few
centimetres of noise keeps an extent well under a metre, while its summed path length
reaches metres over a long recording.

Pure numpy over arrays; one pass over frames, no loop over agents.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from risk.frame import Frame

#: An agent whose travel extent over the scene reaches this is "moving" (``--ego all``).
MIN_TRAVEL_M = 5.0


def travel_extents(frames: Iterable[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """``(ids (A,), extent_m (A,))`` of every agent valid in at least one frame.

    ``extent_m[a]`` is ``max_t |xy_a(t) - xy_a(t0)|`` over the frames where agent ``a`` is
    valid, ``t0`` its first such frame (0 for an agent seen once). Ids ascend.
    """
    frames = list(frames)
    seen = [f.ids[f.valid] for f in frames]
    if not seen or not any(s.size for s in seen):
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    ids = np.unique(np.concatenate(seen))
    start = np.full((ids.size, 2), np.nan)
    extent = np.zeros(ids.size)
    for frame, frame_ids in zip(frames, seen, strict=True):
        rows = np.searchsorted(ids, frame_ids)  # ids are unique within a frame
        xy = frame.xy[frame.valid]
        first = np.isnan(start[rows, 0])
        start[rows[first]] = xy[first]
        extent[rows] = np.maximum(extent[rows], np.hypot(*(xy - start[rows]).T))
    return ids, extent


def moving_agent_ids(frames: Iterable[Frame], min_travel_m: float = MIN_TRAVEL_M) -> np.ndarray:
    """Ids (ascending) of the agents whose travel extent is at least ``min_travel_m``."""
    if not (np.isfinite(min_travel_m) and min_travel_m >= 0):
        raise ValueError(f"min_travel_m must be a finite number >= 0, got {min_travel_m!r}")
    ids, extent = travel_extents(frames)
    return ids[extent >= min_travel_m]
