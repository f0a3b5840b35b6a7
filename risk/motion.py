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


def track_extents(xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(N,)`` travel extent in m of ``N`` tracks over ``T`` steps.

    ``xy``: ``(T, N, 2)`` centres (m), ``valid``: ``(T, N)`` bool; 0 for a track seen at
    most once or never.
    """
    xy = np.asarray(xy, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    if valid.size == 0:
        return np.zeros(valid.shape[1] if valid.ndim == 2 else 0)
    first = np.argmax(valid, axis=0)  # (N,) first valid step (0 when never valid)
    start = xy[first, np.arange(valid.shape[1])]  # (N, 2)
    dist = np.hypot(*(xy - start[None]).transpose(2, 0, 1))  # (T, N)
    return np.where(valid, dist, 0.0).max(axis=0)


def travel_extents(frames: Iterable[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """``(ids (A,), extent_m (A,))`` of every agent valid in at least one frame, ids
    ascending (see :func:`track_extents`)."""
    frames = list(frames)
    seen = [f.ids[f.valid] for f in frames]
    if not any(s.size for s in seen):
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    ids = np.unique(np.concatenate(seen))
    xy = np.zeros((len(frames), ids.size, 2))
    valid = np.zeros((len(frames), ids.size), dtype=bool)
    for k, (frame, frame_ids) in enumerate(zip(frames, seen, strict=True)):
        rows = np.searchsorted(ids, frame_ids)  # ids are unique within a frame
        xy[k, rows] = frame.xy[frame.valid]
        valid[k, rows] = True
    return ids, track_extents(xy, valid)


def moving_agent_ids(frames: Iterable[Frame], min_travel_m: float = MIN_TRAVEL_M) -> np.ndarray:
    """Ids (ascending) of the agents whose travel extent is at least ``min_travel_m``."""
    if not (np.isfinite(min_travel_m) and min_travel_m >= 0):
        raise ValueError(f"min_travel_m must be a finite number >= 0, got {min_travel_m!r}")
    ids, extent = travel_extents(frames)
    return ids[extent >= min_travel_m]
