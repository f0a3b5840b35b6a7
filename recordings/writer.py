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

import os
import pathlib
from collections.abc import Sequence
from dataclasses import dataclass, field

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
from recordings.labels import label_texts, log_misses
from recordings.summary import recording_name, summary_markdown
from recordings.timelines import (
    agent_grid,
    decades,
    focus_agents,
    log10_range,
    log_cascade_series,
    log_timelines,
    timed_batch,
)
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
    n_agents = agent_grid(scene)[0].size
    if n_agents > MAX_RECORDED_AGENTS:
        raise too_many_agents(output, n_agents)
    models = tuple(info.model_names)
    log10_ranges = {
        m: log10_range(scene.rows[f"risk:{m}"])
        for m in models
        if decades(scene.rows[f"risk:{m}"]) > options.log10_decades
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
            log_timelines(rec, info, scene, set(log10_ranges), focus)
            log_cascade_series(rec, info, scene, frames)
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
    batch, static = timed_batch(scene), C.Batch()
    labels = label_texts(info, scene, options.labels)
    _add_ego(batch, static, scene, labels)
    _add_agents(batch, static, info, scene, labels, show=options.labels != "none")
    if options.links:
        _add_links(batch, static, info, scene)
    _add_paths(batch, static, info, scene, frames)
    _add_plans(batch, static, scene, frames)
    static.send(rec)
    batch.send(rec)
    log_misses(rec, info, scene)


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
    agent_ids, column, _, _ = agent_grid(scene)
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
    agent_ids, _, _, _ = agent_grid(scene)
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
