"""Labels and misses in a recording: which rows carry a label (decluttered per frame,
the agent directly ahead of the ego kept), their texts, and the misses list (one text
row per episode of an important agent dropped by the cascade).

Split from :mod:`recordings.writer`, which calls these while writing a scene.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pyarrow as pa

from outputs.sinks import SceneInfo
from recordings import columns as C
from recordings import layout as L
from recordings.frames import SceneRows
from recordings.timelines import timed_batch


# ---------------------------------------------------------------------- labels and misses
def _tier_tags(names: tuple[str, ...]) -> np.ndarray:
    """Short tier marks for labels: initials (B, I, C) when unique, else 1, 2, 3."""
    initials = [n[:1].upper() for n in names]
    tags = (
        initials if len(set(initials)) == len(initials) else [str(k + 1) for k in range(len(names))]
    )
    return np.array([*tags, ""])  # index -1 (no tier) -> ""


def _references(rows: dict[str, np.ndarray]) -> np.ndarray:
    """Which reference marks each row important: ``baseline``, ``hindsight``, both or ``""``."""
    b, h = rows["baseline"], rows["truth"] == 1.0
    return np.where(
        b & h, "baseline+hindsight", np.where(b, "baseline", np.where(h, "hindsight", ""))
    )


def label_texts(info: SceneInfo, scene: SceneRows, mode: str) -> np.ndarray:
    """The label of every row (``""``: none; the id still shows on hover).

    ``"kept"`` (default): the ego, the tier agents (``17 I``) and the misses
    (``17 MISS ✗2``), decluttered: per frame, a label gives way to a more important
    one within :data:`recordings.layout.LABEL_SPACING_M` (ego, then misses, then deeper
    tiers), so that no two labels overlap at the opening zoom. ``"all"``: every agent,
    not decluttered. ``"none"``: no labels.
    """
    r = scene.rows
    n = r["ids"].size
    if mode == "none":
        return np.full(n, "", dtype="<U1")
    if mode == "all":
        shown = np.ones(n, dtype=bool)
    else:
        survivor_tier = np.where(r["dropped_at"] < 0, r["tier"], -1)
        lead = lead_rows(scene)
        wanted = r["is_ego"] | r["miss"] | (survivor_tier >= 0) | lead
        priority = np.where(r["is_ego"], 1000, np.where(r["miss"], 100, survivor_tier + 1))
        # The agent directly ahead of the ego keeps its label over any other but the
        # ego's: de-cluttering hid it behind a tier agent beside it (issue 31).
        priority = np.where(lead & ~r["is_ego"], 500, priority)
        shown = declutter(scene, wanted, priority, L.LABEL_SPACING_M)
    # Texts only for the labelled rows (string operations are slow in numpy).
    rows = np.flatnonzero(shown)
    ids = r["ids"][rows].astype(str)
    tags = _tier_tags(tuple(t.name for t in info.cascade.tiers))
    stage = (r["dropped_at"][rows] + 1).astype(str)
    text = np.where(
        r["is_ego"][rows], np.char.add("ego ", ids),
        np.where(
            r["miss"][rows], np.char.add(np.char.add(ids, " MISS ✗"), stage),
            np.where(
                r["dropped_at"][rows] >= 0, np.char.add(np.char.add(ids, " ✗"), stage),
                np.where(
                    r["tier"][rows] >= 0,
                    np.char.rstrip(np.char.add(np.char.add(ids, " "), tags[r["tier"][rows]])),
                    ids,  # (kept below the first tier: labelled as the agent ahead)
                ),
            ),
        ),
    )  # fmt: skip
    out = np.full(n, "", dtype=text.dtype if text.size else "<U1")
    out[rows] = text
    return out


#: Half the width of the corridor in which an agent counts as directly ahead of the ego.
LEAD_HALF_WIDTH_M = 2.0


def lead_rows(scene: SceneRows) -> np.ndarray:
    """Per frame, the row of the nearest agent ahead of the ego: in front of it along
    its heading and within :data:`LEAD_HALF_WIDTH_M` of its centre line (vectorised
    over all rows)."""
    r = scene.rows
    n_frames = scene.times_s.size
    ego_row = np.full(n_frames, -1)
    ego_rows = np.flatnonzero(r["is_ego"])
    ego_row[scene.frame_of[ego_rows]] = ego_rows
    e = ego_row[scene.frame_of]
    has_ego = (e >= 0) & ~r["is_ego"]
    e = np.maximum(e, 0)
    d = r["xy"] - r["xy"][e]
    c, s_ = np.cos(r["heading"][e]), np.sin(r["heading"][e])
    lon = d[:, 0] * c + d[:, 1] * s_
    lat = -d[:, 0] * s_ + d[:, 1] * c
    ahead = has_ego & (lon > 0) & (np.abs(lat) < LEAD_HALF_WIDTH_M)
    key = np.where(ahead, lon, np.inf)
    best = np.full(n_frames, np.inf)
    np.minimum.at(best, scene.frame_of, key)
    return ahead & (key == best[scene.frame_of])


def declutter(
    scene: SceneRows, wanted: np.ndarray, priority: np.ndarray, spacing_m: float
) -> np.ndarray:
    """``wanted`` rows minus those within ``spacing_m`` of a more important wanted row.

    Per frame (a loop over frames, vectorised over agents): a row gives way to any wanted
    row of higher priority (ties: the earlier row) closer than ``spacing_m``. Of any two
    rows that keep their label, neither gives way, so they are at least ``spacing_m``
    apart.
    """
    shown = wanted.copy()
    rows = np.flatnonzero(wanted)
    bounds = np.searchsorted(scene.frame_of[rows], np.arange(scene.times_s.size + 1))
    for f in range(scene.times_s.size):
        idx = rows[bounds[f] : bounds[f + 1]]
        if idx.size < 2:
            continue
        xy, p = scene.rows["xy"][idx], priority[idx]
        near = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=-1) < spacing_m
        order = np.arange(idx.size)
        above = (p[None, :] > p[:, None]) | (
            (p[None, :] == p[:, None]) & (order[None, :] < order[:, None])
        )
        shown[idx[(near & above).any(axis=1)]] = False
    return shown


def miss_episodes(scene: SceneRows, info: SceneInfo) -> list[dict[str, Any]]:
    """The misses, one entry per episode: an agent dropped although important, over
    consecutive recorded frames with the same stage and reference.

    Each entry: ``agent``, ``stage`` (1-based), ``model``, ``reference``, ``first``
    and ``last`` (positions in the recorded frames), ``t_start_s``, ``t_end_s``.
    """
    r = scene.rows
    rows = np.flatnonzero(r["miss"])
    if rows.size == 0:
        return []
    ids, frame, stage = r["ids"][rows], scene.frame_of[rows], r["dropped_at"][rows]
    ref = _references(r)[rows]
    order = np.lexsort((frame, ids))
    ids, frame, stage, ref = ids[order], frame[order], stage[order], ref[order]
    new = np.ones(ids.size, dtype=bool)
    new[1:] = (
        (ids[1:] != ids[:-1]) | (frame[1:] != frame[:-1] + 1)
        | (stage[1:] != stage[:-1]) | (ref[1:] != ref[:-1])
    )  # fmt: skip
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], ids.size) - 1
    names = info.cascade.stage_names
    return [
        {
            "agent": int(ids[s]),
            "stage": int(stage[s]) + 1,
            "model": names[int(stage[s])],
            "reference": str(ref[s]),
            "first": int(frame[s]),
            "last": int(frame[e]),
            "t_start_s": float(scene.times_s[frame[s]]),
            "t_end_s": float(scene.times_s[frame[e]]),
        }
        for s, e in zip(starts, ends, strict=True)
    ]


def log_misses(rec, info: SceneInfo, scene: SceneRows) -> None:
    """The misses list: a text log row per episode on the agent's body entity.

    A row at the episode's first frame reads ``agent 17 · dropped by stage 2
    (trajectory_distance) · important by baseline · 1.2 s (12 frames)``; clicking it
    in the viewer selects ``/scene/agents/17/body`` (highlighted in the scene) and
    moves the time cursor to the row's time.
    """
    episodes = miss_episodes(scene, info)
    if not episodes:
        return
    n_frames = scene.times_s.size
    agents = sorted({int(e["agent"]) for e in episodes})
    slot = {a: i for i, a in enumerate(agents)}
    text = np.full(len(agents) * n_frames, "", dtype=object)
    missing = np.ones(len(agents) * n_frames, dtype=bool)
    for e in episodes:  # one per episode (a few), not per agent-frame
        cell = slot[int(e["agent"])] * n_frames + int(e["first"])
        frames = int(e["last"]) - int(e["first"]) + 1
        duration = float(e["t_end_s"]) - float(e["t_start_s"])
        text[cell] = (
            f"agent {e['agent']} · dropped by stage {e['stage']} ({e['model']}) · important by "
            f"{e['reference']} · {duration:.1f} s ({frames} frame{'s' if frames > 1 else ''})"
        )  # the row's time is the episode's start
        missing[cell] = False
    batch = timed_batch(scene)
    texts = C.one_per_row(text.tolist(), pa.utf8(), missing)
    levels = C.one_per_row(np.full(text.size, "WARN").tolist(), pa.utf8(), missing)
    colors = C.one_per_row(
        np.full(text.size, C.pack_colors(np.array([L.MISSED]))[0]), pa.uint32(), missing
    )
    for i, agent in enumerate(agents):
        path, start = L.body_path(agent), i * n_frames
        batch.add(path, C.LOG_TEXT, texts.slice(start, n_frames))
        batch.add(path, C.LOG_LEVEL, levels.slice(start, n_frames))
        batch.add(path, C.LOG_COLOR, colors.slice(start, n_frames))
    batch.send(rec)
