"""Writing a recorded replay into a Rerun ``.rrd`` file (the part that imports rerun).

:class:`recordings.recorder.SceneRecorder` collects each frame's arrays during the replay;
:func:`write_temp` writes them at the end, all at once and batched: one ``send_columns``
call per scene layer for the whole scene (all agents of all frames, partitioned by frame)
and one per timeline entity. Measured with rerun-sdk 0.41 (see ``docs/recording.md``,
"Writing: batched, atomic"), this is 20-60x faster than one ``log`` call per agent or
frame. The recorder renames the temporary file into place when it is complete.

This module is kept apart from the recorder so that the recorder can run it in the output
process (:mod:`outputs.process`; importing rerun takes about 1 s) while the replay
computes; see ``SceneRecorder(background=True)``.
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

# rerun's native log: its I/O errors (a full disk) also reach us as exceptions, which the
# CLI reports in one line; without this they print two more lines of Rust log first.
# Set RUST_LOG to see them.
os.environ.setdefault("RUST_LOG", "off")

import numpy as np
import numpy.ma  # (rerun's blueprint code needs it: 40 ms, here while idle)
import pyarrow as pa
import rerun as rr

from outputs.sinks import SceneInfo
from outputs.transaction import run_with_stall_timeout
from recordings import columns as C
from recordings import layout as L
from recordings.errors import RecordingError
from recordings.frames import (
    MAX_RECORDED_AGENTS,
    FrameRows,
    PackedFrames,
    SceneRows,
    WriteOptions,
    too_many_agents,
)
from recordings.summary import recording_name, summary_markdown
from risk.cascade import SURVIVAL_MODEL
from risk.registry import MODELS


def write_temp(
    output: pathlib.Path,
    tmp: pathlib.Path,
    info: SceneInfo,
    frames: Sequence[FrameRows] | PackedFrames,
    options: WriteOptions,
) -> None:
    """Write the recording of ``frames`` (destined for ``output``) into the temporary file
    ``tmp``; the caller renames it into place, or removes it.

    A save that stops making progress (a full disk) fails instead of hanging.
    ``frames`` may come packed (the output process gets them so)."""
    if isinstance(frames, PackedFrames):
        frames = frames.unpack()
    run_with_stall_timeout(
        lambda: _write(output, tmp, info, frames, options), watch=tmp, target=output
    )


def _write(
    output: pathlib.Path,
    path: pathlib.Path,
    info: SceneInfo,
    frames: Sequence[FrameRows],
    options: WriteOptions,
) -> None:
    scene = _concatenate(frames, info)
    n_agents = _agent_grid(scene)[0].size
    if n_agents > MAX_RECORDED_AGENTS:
        raise too_many_agents(output, n_agents)
    models = tuple(info.model_names)
    log10_ranges = {
        m: _log10_range(scene.rows[f"risk:{m}"])
        for m in models
        if _decades(scene.rows[f"risk:{m}"]) > options.log10_decades
    }
    focus = focus_agents(scene)
    reach = _plan_reach_m(frames, scene)
    bp = L.blueprint(
        model_names=models,
        log10_ranges=log10_ranges,
        stage_models=info.cascade.stage_names,
        units=_units(models),
        active_model=_baseline_model(models),
        bounds=L.ego_bounds(_ego_points(scene, info)),
        focus_agents=focus,
        has_misses=bool(scene.rows["miss"].any()),
        ego_view=None if reach is None else L.ego_view_bounds(reach),
    )
    rec = rr.RecordingStream(application_id=options.application_id)
    try:
        rec.save(path, default_blueprint=bp)
        rec.send_recording_name(recording_name(info))
        _log_static(rec, info, scene)
        if frames:
            _log_scene_layers(rec, info, scene, frames, options=options)
            if reach is not None:
                _log_ego_frame(rec, scene)
            _log_timelines(rec, info, scene, set(log10_ranges), focus)
            _log_cascade_series(rec, info, scene, frames)
        rec.flush()
    except (OSError, RuntimeError) as exc:  # I/O and rerun's native errors; bugs propagate
        raise RecordingError(f"could not write {output}: {exc}") from exc
    finally:
        rec.disconnect()
    if not path.is_file() or path.stat().st_size == 0:
        raise RecordingError(
            f"rerun wrote nothing to {output} (is logging disabled, e.g. RERUN=off?)"
        )


def _concatenate(frames: Sequence[FrameRows], info: SceneInfo) -> SceneRows:
    """Stack all frames' rows: one flat array per field, ``frame_of`` maps rows to frames."""
    n_stages = len(info.cascade.stages)
    scene = SceneRows(
        times_s=np.array([f.t for f in frames], dtype=np.float64),
        frame_index=np.array([f.index for f in frames], dtype=np.int64),
        frame_of=np.repeat(np.arange(len(frames)), [f.ids.size for f in frames]).astype(np.int64),
        false_negatives=np.array([f.false_negatives for f in frames], np.int64).reshape(
            -1, n_stages
        ),
        stage_time_ms=np.array([f.stage_time_s for f in frames]).reshape(-1, n_stages) * 1e3,
        sort_time_ms=np.array([f.sort_time_s for f in frames], dtype=np.float64) * 1e3,
        survival_all_time_ms=np.array([f.survival_all_time_s for f in frames]) * 1e3,
    )
    dtypes: dict[str, type] = {
        "ids": np.int64,
        "xy": np.float64,
        "heading": np.float64,
        "length": np.float64,
    }
    dtypes |= {"width": np.float64, "is_ego": bool, "dropped_at": np.int64, "tier": np.int64}
    dtypes |= {"survival": np.float64, "baseline": bool, "truth": np.float64}
    for name, dtype in dtypes.items():
        parts = [getattr(f, name) for f in frames]
        shape = (0, 2) if name == "xy" else (0,)
        scene.rows[name] = np.concatenate(parts) if parts else np.zeros(shape, dtype=dtype)
    scene.rows["kept"] = (
        np.concatenate([f.kept for f in frames], axis=1)
        if frames
        else np.zeros((n_stages, 0), dtype=bool)
    )
    for m in info.model_names:
        parts = [f.risks[m] for f in frames]
        scene.rows[f"risk:{m}"] = np.concatenate(parts) if parts else np.zeros(0)
    r = scene.rows
    r["miss"] = (r["dropped_at"] >= 0) & (r["baseline"] | (r["truth"] == 1.0))
    return scene


# ---------------------------------------------------------------------- static entities
def _log_static(rec: rr.RecordingStream, info: SceneInfo, scene: SceneRows) -> None:
    rec.log(L.SCENE, rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True, strict=True)
    lanes = [np.asarray(lane.centerline, dtype=np.float64) for lane in info.map.lanes]
    lanes = [c for c in lanes if c.ndim == 2 and c.shape[0] >= 2]
    if lanes:
        colors = [
            L.LANE if lane.kind == "vehicle" else L.LANE_OTHER
            for lane in info.map.lanes
            if np.asarray(lane.centerline).ndim == 2 and len(lane.centerline) >= 2
        ]
        rec.log(
            L.MAP_LANES,
            rr.LineStrips2D(lanes, colors=colors, radii=-L.LANE_WIDTH_UI, draw_order=L.ORDER_MAP),
            static=True,
            strict=True,
        )
    _log_map_lines(rec, info)
    rec.log(
        L.SUMMARY,
        rr.TextDocument(summary_markdown(info, scene), media_type="text/markdown"),
        static=True,
        strict=True,
    )


def _log_map_lines(rec: rr.RecordingStream, info: SceneInfo) -> None:
    """Lane boundaries, road edges, crosswalks, ...: one static entity per kind, muted,
    below the lanes (format version 2 maps; older scenes have none)."""
    lines = [ln for ln in info.map.lines if len(ln.points) >= 2]
    for kind, path in L.MAP_LINES.items():
        strips = [
            np.vstack([ln.points, ln.points[:1]]) if ln.closed else np.asarray(ln.points)
            for ln in lines
            if ln.kind == kind
        ]
        if not strips:
            continue
        rec.log(
            path,
            rr.LineStrips2D(
                strips, colors=L.MAP_LINE_COLORS[kind], radii=-L.MAP_LINE_WIDTHS_UI[kind],
                draw_order=L.ORDER_MAP_LINES,
            ),
            static=True,
            strict=True,
        )  # fmt: skip


# ---------------------------------------------------------------------- scene layers
def _time_columns(scene: SceneRows) -> list[rr.TimeColumn]:
    return [
        rr.TimeColumn(L.TIMELINE, duration=scene.times_s),
        rr.TimeColumn(L.FRAME_TIMELINE, sequence=scene.frame_index),
    ]


def _timed_batch(scene: SceneRows) -> C.Batch:
    """An empty batch over the scene's two timelines (one row per recorded frame)."""
    ns = np.rint(scene.times_s * 1e9).astype(np.int64)
    return C.Batch(
        indexes={
            L.TIMELINE: (ns, pa.duration("ns")),
            L.FRAME_TIMELINE: (scene.frame_index, pa.int64()),
        }
    )


def _tile(color: tuple[int, ...], k: int) -> np.ndarray:
    return np.tile(np.array(color, dtype=np.uint8), (k, 1))


@dataclass
class _Parts:
    """Line strips of many cells (a cell = one entity in one frame), built part by part.

    Each :meth:`add` is one strip per member: ``cell (m,)``, ``points (m, P, 2)`` m,
    ``colors (m, 3|4)`` uint8, ``radii (m,)`` and optional ``labels (m,)``.
    :meth:`columns` orders the strips by cell, then by part (the order within an
    entity), and returns list columns with one row per cell: entity ``e``'s column over
    ``F`` frames is then the zero-copy slice ``[e * F, (e + 1) * F)``.
    """

    cells: list[np.ndarray] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)
    colors: list[np.ndarray] = field(default_factory=list)
    radii: list[np.ndarray] = field(default_factory=list)
    labels: list[np.ndarray] = field(default_factory=list)

    def add(self, cell, points, colors, radii, labels=None) -> None:
        m = int(cell.size)
        if m == 0:
            return
        colors = np.asarray(colors, dtype=np.uint8)
        if colors.shape[1] == 3:
            colors = np.column_stack([colors, np.full(m, 255, np.uint8)])
        self.cells.append(np.asarray(cell, dtype=np.int64))
        self.points.append(np.asarray(points, dtype=np.float64))
        self.colors.append(colors)
        self.radii.append(np.asarray(radii, dtype=np.float32))
        self.labels.append(
            np.full(m, "", dtype="<U1") if labels is None else np.asarray(labels, str)
        )

    def columns(self, n_cells: int) -> tuple[pa.Array, pa.Array, pa.Array, pa.Array]:
        if not self.cells:
            cell = np.zeros(0, np.int64)
            points, n_points = np.zeros((0, 2)), np.zeros(0, np.int64)
            colors, radii, labels = (
                np.zeros(0, np.uint32),
                np.zeros(0, np.float32),
                np.zeros(0, str),
            )
            order = np.zeros(0, np.int64)
        else:
            cell = np.concatenate(self.cells)
            part = np.repeat(np.arange(len(self.cells)), [c.size for c in self.cells])
            order = np.lexsort((part, cell))
            n_points = np.concatenate(
                [np.full(c.size, p.shape[1]) for c, p in zip(self.cells, self.points, strict=True)]
            )
            # Reorder points strip by strip: each point goes where its strip went.
            strip_of_point = np.repeat(np.arange(n_points.size), n_points)
            rank = np.empty(n_points.size, dtype=np.int64)
            rank[order] = np.arange(n_points.size)
            flat = np.concatenate([p.reshape(-1, 2) for p in self.points])
            points = flat[np.argsort(rank[strip_of_point], kind="stable")]
            n_points = n_points[order]
            colors = C.pack_colors(np.concatenate(self.colors)[order])
            radii = np.concatenate(self.radii)[order]
            labels = np.concatenate(self.labels)[order]
        lengths = np.bincount(cell, minlength=n_cells)
        return (
            C.rows(C.strips(points, n_points), lengths, C.STRIPS.item),
            C.rows(colors, lengths, pa.uint32()),
            C.rows(radii, lengths, pa.float32()),
            C.rows(pa.array(labels, pa.utf8()), lengths, pa.utf8()),
        )


def _add_entities(
    batch: C.Batch,
    static: C.Batch,
    paths: Sequence[str],
    n_frames: int,
    columns: tuple[pa.Array, pa.Array, pa.Array, pa.Array],
    order: float | None,
    *,
    labels: bool,
) -> None:
    """Line-strip entities ``paths[e]`` whose frame-``f`` instances are row ``e*F + f``.

    ``order``: the entities' draw order, logged static with ``show_labels``; None leaves
    both to the scene view's defaults (the agents' bodies: one entity each, so per-entity
    static values would cost two columns per agent for the same value).
    """
    strips, colors, radii, texts = columns
    for e, path in enumerate(paths):
        start = e * n_frames
        if order is not None:
            static.add(path, C.DRAW_ORDER, C.one_per_row(np.array([order]), pa.float32()))
        batch.add(path, C.STRIPS, strips.slice(start, n_frames))
        batch.add(path, C.STRIP_COLORS, colors.slice(start, n_frames))
        batch.add(path, C.STRIP_RADII, radii.slice(start, n_frames))
        if labels:
            if order is not None:
                static.add(path, C.SHOW_LABELS, C.one_per_row(np.array([True]), pa.bool_()))
            batch.add(path, C.STRIP_LABELS, texts.slice(start, n_frames))


def _log_scene_layers(
    rec, info: SceneInfo, scene: SceneRows, frames, *, options: WriteOptions
) -> None:
    """Every layer of the scene view, all frames: one timed and one static record batch."""
    batch, static = _timed_batch(scene), C.Batch()
    labels = _label_texts(info, scene, options.labels)
    _add_ego(batch, static, scene, labels)
    _add_agents(batch, static, info, scene, labels, show=options.labels != "none")
    if options.links:
        _add_links(batch, static, info, scene)
    _add_paths(batch, static, info, scene, frames)
    _add_plans(batch, static, scene, frames)
    static.send(rec)
    batch.send(rec)
    _log_misses(rec, info, scene)


def _add_ego(batch: C.Batch, static: C.Batch, scene: SceneRows, labels: np.ndarray) -> None:
    """The ego: a green capsule with a dark heading nose and the label ``ego <id>``."""
    r = scene.rows
    ego = r["is_ego"]
    cell, k = scene.frame_of[ego], int(ego.sum())
    parts = _Parts()
    caps, radius = L.capsules(r["xy"][ego], r["heading"][ego], r["length"][ego], r["width"][ego])
    parts.add(cell, caps, _tile(L.EGO, k), radius, labels[ego])
    parts.add(
        cell, L.noses(r["xy"][ego], r["heading"][ego], r["length"][ego]), _tile(L.NOSE, k),
        np.full(k, -L.NOSE_WIDTH_UI),
    )  # fmt: skip
    columns = parts.columns(scene.times_s.size)
    _add_entities(
        batch, static, [L.EGO_BODY], scene.times_s.size, columns, L.ORDER_EGO, labels=True
    )


def _add_agents(
    batch: C.Batch,
    static: C.Batch,
    info: SceneInfo,
    scene: SceneRows,
    labels: np.ndarray,
    *,
    show: bool,
) -> None:
    """``/scene/agents/<id>/body`` for every other agent: capsule, nose and marker.

    The capsule is red by survival risk for a survivor, grey when dropped, and yellow
    when dropped although the baseline or hindsight marks it important (a miss). The
    marker: a survivor's tier outline, a yellow ring around a miss, an orange ring
    around a kept agent that really came close (hindsight positive).
    """
    r = scene.rows
    agent_ids, column, _, _ = _agent_grid(scene)
    n_frames = scene.times_s.size
    others = column >= 0
    cell = column[others] * n_frames + scene.frame_of[others]
    xy, heading = r["xy"][others], r["heading"][others]
    length, width = r["length"][others], r["width"][others]
    dropped, tier, miss = r["dropped_at"][others] >= 0, r["tier"][others], r["miss"][others]
    came_close_kept = ~dropped & (r["truth"][others] == 1.0)
    rgb = L.risk_colors(r["survival"][others], info.cascade.baseline_threshold)
    rgb[dropped] = L.DROPPED
    rgb[miss] = L.MISSED
    # A label takes the colour of the strip it sits on: it goes on the agent's marker
    # (white / cyan / magenta tier outline, yellow miss ring, orange hindsight ring) when
    # it has one, so that the text never reads red on a red body.
    text = labels[others]
    tiered = ~dropped & (tier >= 0)
    ringed = came_close_kept & ~tiered
    parts = _Parts()
    caps, radius = L.capsules(xy, heading, length, width)
    parts.add(cell, caps, rgb, radius, np.where(tiered | miss | ringed, "", text))
    parts.add(
        cell, L.noses(xy, heading, length), _tile(L.NOSE, cell.size),
        np.full(cell.size, -L.NOSE_WIDTH_UI),
    )  # fmt: skip
    tier_rgb = np.array([L.tier_color(k) for k in range(max(len(info.cascade.tiers), 1))], np.uint8)
    parts.add(
        cell[tiered], L.outlines(xy[tiered], heading[tiered], length[tiered], width[tiered], 0.35),
        tier_rgb[tier[tiered]], -L.outline_width_ui(tier[tiered]), text[tiered],
    )  # fmt: skip
    for mask, label_mask, color, ui, margin in (
        (miss, miss, L.MISSED, 2.5, 1.2),
        (came_close_kept, ringed, L.HINDSIGHT, 1.5, 0.8),
    ):
        k = int(mask.sum())
        parts.add(
            cell[mask], L.rings(xy[mask], length[mask], width[mask], margin), _tile(color, k),
            np.full(k, -ui), np.where(label_mask, text, "")[mask],
        )  # fmt: skip
    paths = [L.body_path(int(a)) for a in agent_ids]
    columns = parts.columns(agent_ids.size * n_frames)
    # Draw order and show_labels: the scene view's defaults (layout.blueprint).
    _add_entities(batch, static, paths, n_frames, columns, None, labels=show)


def _add_links(batch: C.Batch, static: C.Batch, info: SceneInfo, scene: SceneRows) -> None:
    """Fig. 2 overlay (option ``links``): per stage, ego -> every agent kept after it."""
    r, n_frames = scene.rows, scene.times_s.size
    ego_xy = np.zeros((n_frames, 2))
    ego_xy[scene.frame_of[r["is_ego"]]] = r["xy"][r["is_ego"]]
    for s, stage in enumerate(info.cascade.stages):
        mask = r["kept"][s]
        k = int(mask.sum())
        parts = _Parts()
        parts.add(
            scene.frame_of[mask], np.stack([ego_xy[scene.frame_of[mask]], r["xy"][mask]], axis=1),
            _tile((*L.stage_color(s), L.LINK_ALPHA), k), np.full(k, -L.link_width_ui(s)),
        )  # fmt: skip
        path = L.link_path(s, stage.model)
        _add_entities(
            batch, static, [path], n_frames, parts.columns(n_frames), L.ORDER_LINKS + 0.1 * s,
            labels=False,
        )  # fmt: skip


def _add_paths(batch: C.Batch, static: C.Batch, info: SceneInfo, scene: SceneRows, frames) -> None:
    """The ego's path candidates; each deeper-tier survivor's under its own subtree."""
    n_frames = scene.times_s.size
    ego = [p for f in frames for p in f.ego_paths]
    if ego:
        parts = _Parts()
        cell = np.repeat(np.arange(n_frames), [len(f.ego_paths) for f in frames])
        for p_len in sorted({len(p) for p in ego}):  # strips of equal length, one part each
            same = np.array([len(p) == p_len for p in ego])
            pts = np.stack([p for p in ego if len(p) == p_len])
            k = int(same.sum())
            parts.add(cell[same], pts, _tile((*L.EGO, 200), k), np.full(k, -L.PATH_WIDTH_UI * 1.5))
        cols = parts.columns(n_frames)
        _add_entities(batch, static, [L.EGO_PATH], n_frames, cols, L.ORDER_PATHS, labels=False)
    owners = np.concatenate([f.survivor_path_owner for f in frames]) if frames else np.zeros(0)
    if owners.size == 0:
        return
    agent_ids, _, _, _ = _agent_grid(scene)
    frame_of = np.repeat(np.arange(n_frames), [f.survivor_paths.shape[0] for f in frames])
    col = np.searchsorted(agent_ids, owners)
    with_paths = np.unique(col)
    # Only agents that ever have a path get an entity: cells index into that subset.
    sub = np.searchsorted(with_paths, col)
    risk = np.concatenate([f.survivor_path_risk for f in frames])
    rgb = L.risk_colors(risk, info.cascade.baseline_threshold)
    rgba = np.column_stack([rgb, np.full(risk.size, L.PATH_ALPHA, np.uint8)])
    parts = _Parts()
    for f, frame in enumerate(frames):  # frames, not agents: one part per frame
        rows = frame_of == f
        if rows.any():
            parts.add(
                sub[rows] * n_frames + f, frame.survivor_paths, rgba[rows],
                np.full(int(rows.sum()), -L.PATH_WIDTH_UI),
            )  # fmt: skip
    paths = [L.agent_paths_path(int(agent_ids[c])) for c in with_paths]
    cols = parts.columns(with_paths.size * n_frames)
    _add_entities(batch, static, paths, n_frames, cols, L.ORDER_PATHS, labels=False)


def _add_plans(batch: C.Batch, static: C.Batch, scene: SceneRows, frames) -> None:
    """A planner's two plans per frame (replay run --planner): white with every agent,
    orange with the cascade's agents (drawn thinner, on top, so both show where equal)."""
    n_frames = scene.times_s.size
    for path, key, color, width in (
        (L.PLAN_ALL, "plan_all", L.PLAN_ALL_COLOR, 2.2),
        (L.PLAN_FILTERED, "plan_filtered", L.PLAN_FILTERED_COLOR, 1.2),
    ):
        plans = [getattr(f, key) for f in frames]
        if not any(len(p) >= 2 for p in plans):
            continue
        parts = _Parts()
        for f, plan in enumerate(plans):
            if len(plan) >= 2:
                parts.add(
                    np.array([f]), plan[None], _tile((*color, 230), 1),
                    np.full(1, -L.PATH_WIDTH_UI * width),
                )  # fmt: skip
        cols = parts.columns(n_frames)
        _add_entities(batch, static, [path], n_frames, cols, L.ORDER_PATHS + 1.0, labels=False)


def _plan_reach_m(frames: Sequence[FrameRows], scene: SceneRows) -> float | None:
    """How far ahead of the ego its plans reach (m, the 90th percentile over frames of the
    farthest plan point); None when no frame has a plan (no ego view then)."""
    r = scene.rows
    ego_xy = np.full((len(frames), 2), np.nan)
    ego_xy[scene.frame_of[r["is_ego"]]] = r["xy"][r["is_ego"]]
    reach = [
        float(np.hypot(*(np.asarray(plan) - ego_xy[f]).T).max())
        for f, frame in enumerate(frames)
        for plan in (frame.plan_all, frame.plan_filtered)
        if len(plan) >= 2 and np.isfinite(ego_xy[f]).all()
    ]
    return float(np.percentile(reach, 90)) if reach else None


def _log_ego_frame(rec: rr.RecordingStream, scene: SceneRows) -> None:
    """The ego's pose per frame at EGO_FRAME (see recordings.layout): its position and
    :func:`recordings.layout.ego_frame_matrices`, so that the view with this origin shows
    the ego driving up, its left to the left."""
    r = scene.rows
    ego = r["is_ego"]
    rows = np.flatnonzero(ego)
    frame = scene.frame_of[rows]
    xyz = np.column_stack([r["xy"][rows], np.zeros(rows.size)])
    times = [
        rr.TimeColumn(L.TIMELINE, duration=scene.times_s[frame]),
        rr.TimeColumn(L.FRAME_TIMELINE, sequence=scene.frame_index[frame]),
    ]
    rec.send_columns(
        L.EGO_FRAME,
        indexes=times,
        columns=rr.Transform3D.columns(
            translation=xyz,
            mat3x3=L.ego_frame_matrices(r["heading"][rows]),
        ),
        strict=True,
    )


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


def _label_texts(info: SceneInfo, scene: SceneRows, mode: str) -> np.ndarray:
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
        lead = _lead_rows(scene)
        wanted = r["is_ego"] | r["miss"] | (survivor_tier >= 0) | lead
        priority = np.where(r["is_ego"], 1000, np.where(r["miss"], 100, survivor_tier + 1))
        # The agent directly ahead of the ego keeps its label over any other but the
        # ego's: de-cluttering hid it behind a tier agent beside it (issue 31).
        priority = np.where(lead & ~r["is_ego"], 500, priority)
        shown = _declutter(scene, wanted, priority, L.LABEL_SPACING_M)
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


def _lead_rows(scene: SceneRows) -> np.ndarray:
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


def _declutter(
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


def _log_misses(rec, info: SceneInfo, scene: SceneRows) -> None:
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
    batch = _timed_batch(scene)
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


# ---------------------------------------------------------------------- timelines
def _decades(values: np.ndarray) -> float:
    """How many decades the positive finite ``values`` span (0 when fewer than two)."""
    pos = values[np.isfinite(values) & (values > 0)]
    if pos.size < 2:
        return 0.0
    return float(np.log10(pos.max()) - np.log10(pos.min()))


def _log10_range(values: np.ndarray, window_decades: float = 30.0) -> tuple[float, float]:
    """The y range of a log10 risk view: from the top value down ``window_decades`` at most.

    Survival risk reaches 1e-300 for agents that never come near; a full-range axis would
    squash the risks that matter (around the 1e-25 baseline and above) into a line.
    """
    pos = values[np.isfinite(values) & (values > 0)]
    top, bottom = float(np.log10(pos.max())), float(np.log10(pos.min()))
    return max(bottom, top - window_decades) - 0.5, top + 0.5


def _agent_grid(scene: SceneRows) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def _log_timelines(
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
    agent_ids, column, first, last = _agent_grid(scene)
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
    static, batch = C.Batch(), _timed_batch(scene)  # every model in one record batch
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
        indexes=_time_columns(scene),
        columns=rr.Scalars.columns(scalars=np.full(scene.times_s.size, value)),
        strict=True,
    )


# ---------------------------------------------------------------------- cascade series
def _log_cascade_series(rec, info: SceneInfo, scene: SceneRows, frames=()) -> None:
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
    static, batch = C.Batch(), _timed_batch(scene)
    colors = C.pack_colors(np.array([c for _, _, c, _ in series], dtype=np.uint8))
    for k, (path, name, _, values) in enumerate(series):
        static.add(path, C.SERIES_COLORS, C.one_per_row(colors[k : k + 1], pa.uint32()))
        static.add(path, C.SERIES_NAMES, C.one_per_row([name], pa.utf8()))
        static.add(path, C.SERIES_WIDTHS, C.one_per_row(np.array([2.0]), pa.float32()))
        batch.add(path, C.SCALARS, C.one_per_row(np.asarray(values, np.float64), pa.float64()))
    static.send(rec)
    batch.send(rec)


# ---------------------------------------------------------------------- helpers
def _baseline_model(models: Sequence[str]) -> str | None:
    """The model whose tab opens first: the survival baseline the cascade is judged by."""
    return SURVIVAL_MODEL if SURVIVAL_MODEL in models else (models[0] if models else None)


def _units(models: Sequence[str]) -> dict[str, str]:
    """Each model's unit from the registry ("" when dimensionless or not registered)."""
    return {m: MODELS[m].unit for m in models if m in MODELS}


def _ego_points(scene: SceneRows, info: SceneInfo) -> np.ndarray:
    """Where the scene view opens: the ego's positions (without frames, the map)."""
    r = scene.rows
    if r["is_ego"].any():
        return r["xy"][r["is_ego"]]
    lanes = [
        np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2) for lane in info.map.lanes
    ]
    return np.concatenate(lanes) if lanes else np.zeros((1, 2))


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
    agent_ids, column, _, _ = _agent_grid(scene)
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
