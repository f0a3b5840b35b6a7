"""The timed parts of a recording: the two timelines, each agent's risk over time, the
stage thresholds and the cascade's per-frame series (funnel, false negatives, compute
times), and which agents the risk views open on.

Split from :mod:`recordings.writer`, which calls these while writing a scene (and which
sets ``RUST_LOG`` before rerun is imported).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pyarrow as pa
import rerun as rr

from outputs.sinks import SceneInfo
from recordings import columns as C
from recordings import layout as L
from recordings.frames import SceneRows


# ---------------------------------------------------------------------- time axes
def time_columns(scene: SceneRows) -> list[rr.TimeColumn]:
    return [
        rr.TimeColumn(L.TIMELINE, duration=scene.times_s),
        rr.TimeColumn(L.FRAME_TIMELINE, sequence=scene.frame_index),
    ]


def timed_batch(scene: SceneRows) -> C.Batch:
    """An empty batch over the scene's two timelines (one row per recorded frame)."""
    ns = np.rint(scene.times_s * 1e9).astype(np.int64)
    return C.Batch(
        indexes={
            L.TIMELINE: (ns, pa.duration("ns")),
            L.FRAME_TIMELINE: (scene.frame_index, pa.int64()),
        }
    )


# ---------------------------------------------------------------------- timelines
def decades(values: np.ndarray) -> float:
    """How many decades the positive finite ``values`` span (0 when fewer than two)."""
    pos = values[np.isfinite(values) & (values > 0)]
    if pos.size < 2:
        return 0.0
    return float(np.log10(pos.max()) - np.log10(pos.min()))


def log10_range(values: np.ndarray, window_decades: float = 30.0) -> tuple[float, float]:
    """The y range of a log10 risk view: from the top value down ``window_decades`` at most.

    Survival risk reaches 1e-300 for agents that never come near; a full-range axis would
    squash the risks that matter (around the 1e-25 baseline and above) into a line.
    """
    pos = values[np.isfinite(values) & (values > 0)]
    top, bottom = float(np.log10(pos.max())), float(np.log10(pos.min()))
    return max(bottom, top - window_decades) - 0.5, top + 0.5


def agent_grid(scene: SceneRows) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if scene.grid is None:
        scene.grid = _compute_agent_grid(scene)
    return scene.grid


def _compute_agent_grid(scene: SceneRows) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The other agents as columns of a frame x agent grid.

    Returns ``agent_ids (A,)``, ``column (K,)`` (-1 for the ego rows), and each agent's
    first and last frame ``(A,)``.
    """
    r = scene.rows
    others = ~r["is_ego"]
    agent_ids, col = np.unique(r["ids"][others], return_inverse=True)
    column = np.full(r["ids"].size, -1, dtype=np.int64)
    column[others] = col
    first = np.full(agent_ids.size, np.iinfo(np.int64).max)
    last = np.full(agent_ids.size, -1)
    np.minimum.at(first, col, scene.frame_of[others])
    np.maximum.at(last, col, scene.frame_of[others])
    return agent_ids, column, first, last


#: Agents with their own risk timelines in one recording (the most important first; see
#: :func:`focus_agents`). The scene view still draws every agent.
MAX_TIMELINE_AGENTS = 1000


def log_timelines(
    rec, info: SceneInfo, scene: SceneRows, log10_models: set[str], focus: Sequence[int]
) -> None:
    """``/scene/agents/<id>/risk/<model>``: each agent's risk from its first to its last
    frame, in the agent's own subtree (beside its body and path).

    Frames in between where the agent is absent (or invalid) hold NaN, which the viewer
    draws as a gap. Every agent has its own colour and its id as the series name (static);
    the model views start on the agents that matter (:func:`focus_agents`). Each model is
    one record batch with a column per agent (null outside the agent's span), not one
    ``send_columns`` call per agent.
    """
    r = scene.rows
    agent_ids, column, first, last = agent_grid(scene)
    if agent_ids.size > MAX_TIMELINE_AGENTS:
        # Every timeline is a column of one record batch, and rerun's encoding of a
        # batch grows faster than its columns: 20,000 agents took minutes (seen as a
        # stalled save). The views keep the agents that matter most, as they open on.
        keep = np.isin(
            agent_ids,
            focus_agents(scene, MAX_TIMELINE_AGENTS, only_important=False),
        )
        remap = np.where(keep, np.cumsum(keep) - 1, -1)
        column = np.where(column >= 0, remap[np.maximum(column, 0)], -1)
        agent_ids, first, last = agent_ids[keep], first[keep], last[keep]
    n_frames, others = scene.times_s.size, column >= 0
    frame_pos = np.arange(n_frames)
    outside = (frame_pos[None, :] < first[:, None]) | (frame_pos[None, :] > last[:, None])
    colors = C.one_per_row(C.pack_colors(L.agent_series_colors(agent_ids)), pa.uint32())
    # Own colours (the same in every model's view) for the agents the views open on; an
    # agent added in the viewer takes the view's quiet grey. The series name is the
    # entity path, which holds the agent id.
    coloured = np.isin(agent_ids, np.asarray(focus, dtype=np.int64))
    names = C.one_per_row([f"agent {int(a)}" for a in agent_ids], pa.utf8())
    static, batch = C.Batch(), timed_batch(scene)  # every model in one record batch
    thresholds = {s.model: s.threshold for s in info.cascade.stages}
    for model in info.model_names:
        grid = np.full((agent_ids.size, n_frames), np.nan)  # (A, F): one row per agent
        grid[column[others], scene.frame_of[others]] = r[f"risk:{model}"][others]
        variants = [(False, grid)]
        if model in log10_models:
            with np.errstate(divide="ignore", invalid="ignore"):
                variants.append((True, np.where(grid > 0, np.log10(grid), np.nan)))
        for is_log, values in variants:
            # All agents' cells in one array; each agent's column is a zero-copy slice.
            cells = C.one_per_row(values.reshape(-1), pa.float64(), outside.reshape(-1))
            for a, agent in enumerate(agent_ids):
                path = L.risk_path(model, int(agent), log10=is_log)
                batch.add(path, C.SCALARS, cells.slice(a * n_frames, n_frames))
                if coloured[a]:
                    static.add(path, C.SERIES_COLORS, colors.slice(a, 1))
                    # the tab's legend names the agent (else: its entity path)
                    static.add(path, C.SERIES_NAMES, names.slice(a, 1))
            if model in thresholds:
                _log_threshold(rec, scene, model, thresholds[model], is_log)
    batch.send(rec)
    static.send(rec)


def _log_threshold(rec, scene: SceneRows, model: str, threshold: float, is_log: bool) -> None:
    """The stage threshold as a flat line in the model's risk view."""
    if is_log and threshold <= 0:
        return
    value = math.log10(threshold) if is_log else threshold
    path = L.threshold_path(model, log10=is_log)
    rec.log(
        path,
        rr.SeriesLines(colors=(255, 255, 255), widths=2.5, names="stage threshold"),
        static=True,
        strict=True,
    )
    rec.send_columns(
        path,
        indexes=time_columns(scene),
        columns=rr.Scalars.columns(scalars=np.full(scene.times_s.size, value)),
        strict=True,
    )


# ---------------------------------------------------------------------- cascade series
def log_cascade_series(rec, info: SceneInfo, scene: SceneRows, frames=()) -> None:
    """Funnel counts, cumulative false negatives and compute times, one value per frame."""
    r, n_frames = scene.rows, scene.times_s.size
    per_frame = lambda mask: np.bincount(scene.frame_of[mask], minlength=n_frames)  # noqa: E731
    series: list[tuple[str, str, tuple[int, int, int], np.ndarray]] = [
        (f"{L.FUNNEL}/0_others", "others", L.OTHERS_SERIES, per_frame(~r["is_ego"])),
        (f"{L.FUNNEL}/baseline", "baseline", L.MISSED, per_frame(r["baseline"])),
    ]
    for s, stage in enumerate(info.cascade.stages):
        key, color, label = L.stage_key(s, stage.model), L.stage_color(s), f"{s + 1}: {stage.model}"
        series += [
            (f"{L.FUNNEL}/{key}", label, color, per_frame(r["kept"][s])),
            (f"{L.FALSE_NEGATIVES}/{key}", label, color, scene.false_negatives[:, s]),
            (f"{L.TIMING}/{key}", label, color, scene.stage_time_ms[:, s]),
        ]
    for k, tier in enumerate(info.cascade.tiers):
        path = f"{L.FUNNEL}/tier_{k + 1}_{tier.name}"
        series.append((path, tier.name, L.tier_color(k), per_frame(r["tier"] >= k)))
    total_ms = scene.stage_time_ms.sum(axis=1) + scene.sort_time_ms
    plan_ms = {
        key: np.array([getattr(f, key) for f in frames], dtype=np.float64)
        for key in ("plan_all_ms", "plan_filtered_ms")
    }
    if np.isfinite(plan_ms["plan_all_ms"]).any():
        series += [
            (f"{L.TIMING}/plan_all_agents", "plan, all agents", L.PLAN_ALL_COLOR,
             plan_ms["plan_all_ms"]),
            (f"{L.TIMING}/plan_filtered", "plan, cascade's agents", L.PLAN_FILTERED_COLOR,
             plan_ms["plan_filtered_ms"]),
        ]  # fmt: skip
    series += [
        (f"{L.TIMING}/sort", "sort into tiers", L.tier_color(1), scene.sort_time_ms),
        (f"{L.TIMING}/cascade_total", "cascade total", L.OTHERS_SERIES, total_ms),
        (f"{L.TIMING}/survival_all", "survival (all)", L.MISSED, scene.survival_all_time_ms),
    ]
    # Two record batches (styles, static; values, one row per frame) for all series.
    static, batch = C.Batch(), timed_batch(scene)
    colors = C.pack_colors(np.array([c for _, _, c, _ in series], dtype=np.uint8))
    for k, (path, name, _, values) in enumerate(series):
        static.add(path, C.SERIES_COLORS, C.one_per_row(colors[k : k + 1], pa.uint32()))
        static.add(path, C.SERIES_NAMES, C.one_per_row([name], pa.utf8()))
        static.add(path, C.SERIES_WIDTHS, C.one_per_row(np.array([2.0]), pa.float32()))
        batch.add(path, C.SCALARS, C.one_per_row(np.asarray(values, np.float64), pa.float64()))
    static.send(rec)
    batch.send(rec)


def focus_agents(
    scene: SceneRows, limit: int = L.FOCUS_AGENTS_MAX, *, only_important: bool = True
) -> list[int]:
    """The agents the risk views open on: misses, hindsight positives and tier agents
    (``only_important=False``: any agent, in the same order).

    Ordered by importance (missed at least once, then came close, then the deepest tier
    reached, then the highest survival risk), at most ``limit``; the others are one
    click away in the viewer (each agent's subtree holds all nine timelines).
    """
    r = scene.rows
    agent_ids, column, _, _ = agent_grid(scene)
    if agent_ids.size == 0:
        return []
    others = column >= 0
    col = column[others]

    def per_agent(values: np.ndarray, fill: float) -> np.ndarray:
        out = np.full(agent_ids.size, fill)
        np.maximum.at(out, col, values[others])
        return out

    missed = per_agent(r["miss"].astype(float), 0.0)
    close = per_agent((r["truth"] == 1.0).astype(float), 0.0)
    tier = per_agent(np.where(r["dropped_at"] < 0, r["tier"], -1).astype(float), -1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        risk = per_agent(np.nan_to_num(np.log10(r["survival"]), nan=-np.inf), -np.inf)
    matter = (missed > 0) | (close > 0) | (tier >= 0)
    order = np.lexsort((-risk, -tier, -close, -missed))
    if not only_important:
        return [int(a) for a in agent_ids[order[:limit]]]
    return [int(agent_ids[a]) for a in order if matter[a]][:limit]
