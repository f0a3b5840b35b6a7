"""The Rerun recording of a replay: a :class:`base.sinks.Sink` that writes one ``.rrd``.

``add()`` keeps only the arrays the recording needs (valid agents, the cascade outcome,
every model's risk, the paths to draw); ``close()`` writes everything at once, batched:
one ``send_columns`` call per scene layer for the whole scene (all agents of all frames,
partitioned by frame) and one per timeline entity. Measured with rerun-sdk 0.41 (see
``docs/recording.md``, "Writing: batched, atomic"), this is 20-60x faster than one ``log`` call per agent or
frame. The file appears atomically: it is written to a temporary file beside the output
and renamed at the end; ``abort()`` (or any error) leaves nothing behind.

What each entity shows is described in ``docs/recording.md``; paths, colours and the
blueprint live in :mod:`recordings.layout`, the Arrow batching in
:mod:`recordings.columns`, the summary text in :mod:`recordings.summary`.
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pyarrow as pa
import rerun as rr

from base.atomic import commit, temp_path_beside
from base.guard import run_with_stall_timeout
from base.sinks import FrameResult, SceneInfo
from recordings import columns as C
from recordings import layout as L
from recordings.errors import RecordingError
from recordings.summary import recording_name, summary_markdown
from risk.cascade import SURVIVAL_MODEL
from risk.registry import MODELS

LabelMode = Literal["kept", "all", "none"]
LABEL_MODES: tuple[str, ...] = ("kept", "all", "none")
APPLICATION_ID = "riskreplay"


@dataclass
class _FrameRows:
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
    risks: dict[str, np.ndarray]  # model -> (n,)
    false_negatives: np.ndarray  # (S,) int
    stage_time_s: np.ndarray  # (S,) s
    sort_time_s: float
    survival_all_time_s: float
    ego_paths: list[np.ndarray]  # the ego's path candidates, each (P, 2) m
    survivor_paths: np.ndarray  # (R, P, 2) m, survivors' candidates (padded)
    survivor_path_risk: np.ndarray  # (R,) R_S of each candidate's owner (colour)


@dataclass
class _Scene:
    """All frames concatenated: ``K`` agent rows in total, ``F`` frames."""

    times_s: np.ndarray  # (F,) s
    frame_index: np.ndarray  # (F,) int
    frame_of: np.ndarray  # (K,) row -> position in the frame list
    false_negatives: np.ndarray  # (F, S) int, cumulative per stage
    stage_time_ms: np.ndarray  # (F, S) ms
    sort_time_ms: np.ndarray  # (F,) ms
    survival_all_time_ms: np.ndarray  # (F,) ms
    rows: dict[str, np.ndarray] = field(default_factory=dict)  # name -> (K, ...) or (S, K)


class SceneRecorder:
    """Writes the replay of one scene to a Rerun ``.rrd`` file (a replay :class:`Sink`).

    ``output``: the ``.rrd`` path (its folder must exist). ``labels``: which agents carry
    their id as a label in the scene view: ``"kept"`` (survivors and false negatives, the
    default: readable with 100 agents), ``"all"`` or ``"none"``. ``paths``: draw the
    survivors' forward path candidates. ``log10_decades``: a model's risk view plots
    log10(risk) when its positive values in the scene span more than this many decades
    (the raw values are always recorded under ``/risk``).
    """

    def __init__(
        self,
        output: str | os.PathLike[str],
        *,
        labels: LabelMode = "kept",
        paths: bool = True,
        log10_decades: float = 4.0,
        application_id: str = APPLICATION_ID,
    ) -> None:
        if labels not in LABEL_MODES:
            raise RecordingError(f"labels must be one of {', '.join(LABEL_MODES)}, got {labels!r}")
        self.output = pathlib.Path(output)
        self.labels = labels
        self.paths = paths
        self.log10_decades = float(log10_decades)
        self.application_id = application_id
        self._info: SceneInfo | None = None
        self._frames: list[_FrameRows] = []
        self._state = "new"  # new -> open -> closed | aborted
        self._tmp: pathlib.Path | None = None

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
        self._info = info
        self._state = "open"

    def add(self, result: FrameResult) -> None:
        """Keep what the recording needs from one frame (nothing is written yet)."""
        if self._state != "open":
            raise RecordingError(f"add() on a recorder that is {self._state}; call begin() first")
        assert self._info is not None
        self._frames.append(_collect(result, self._info, keep_paths=self.paths))

    def close(self) -> None:
        """Write the whole recording atomically (temp file, then rename) and finish."""
        if self._state != "open":
            raise RecordingError(f"close() on a recorder that is {self._state}")
        assert self._info is not None
        self._tmp = temp_path_beside(self.output)
        try:
            tmp = self._tmp
            # A save that stops making progress (full disk) fails instead of hanging.
            run_with_stall_timeout(lambda: self._write(tmp), watch=tmp, target=self.output)
            commit(self._tmp, self.output)
        except BaseException:
            self._discard()
            self._state = "aborted"
            raise
        self._tmp = None
        self._frames = []
        self._state = "closed"

    def abort(self) -> None:
        """Discard everything; no file is left behind. Safe to call at any time."""
        self._discard()
        self._frames = []
        self._state = "aborted"

    # ------------------------------------------------------------------ writing
    def _discard(self) -> None:
        if self._tmp is not None:
            self._tmp.unlink(missing_ok=True)
            self._tmp = None

    def _write(self, path: pathlib.Path) -> None:
        assert self._info is not None
        info, frames = self._info, self._frames
        scene = _concatenate(frames, info)
        models = tuple(info.model_names)
        log10_ranges = {
            m: _log10_range(scene.rows[f"risk:{m}"])
            for m in models
            if _decades(scene.rows[f"risk:{m}"]) > self.log10_decades
        }
        bp = L.blueprint(
            model_names=models,
            log10_ranges=log10_ranges,
            stage_models=info.cascade.stage_names,
            units=_units(models),
            active_model=_baseline_model(models),
            bounds=L.scene_bounds(*_focus_points(scene, info)),
        )
        rec = rr.RecordingStream(application_id=self.application_id)
        try:
            rec.save(path, default_blueprint=bp)
            rec.send_recording_name(recording_name(info))
            _log_static(rec, info, scene)
            if frames:
                _log_scene_layers(rec, info, scene, frames, labels=self.labels)
                _log_timelines(rec, info, scene, set(log10_ranges))
                _log_cascade_series(rec, info, scene)
            rec.flush()
        except (OSError, RuntimeError) as exc:  # I/O and rerun's native errors; bugs propagate
            raise RecordingError(f"could not write {self.output}: {exc}") from exc
        finally:
            rec.disconnect()
        if not path.is_file() or path.stat().st_size == 0:
            raise RecordingError(
                f"rerun wrote nothing to {self.output} (is logging disabled, e.g. RERUN=off?)"
            )


# ---------------------------------------------------------------------- collection
def _collect(result: FrameResult, info: SceneInfo, *, keep_paths: bool) -> _FrameRows:
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
    paths, path_risk = _survivor_paths(frame, casc.survival, idx[survivors], keep_paths)
    return _FrameRows(
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
        risks={m: np.asarray(result.risks[m][idx], dtype=np.float64) for m in info.model_names},
        false_negatives=np.asarray(casc.false_negatives, dtype=np.int64).reshape(len(stages)),
        stage_time_s=np.asarray(casc.stage_time_s, dtype=np.float64).reshape(len(stages)),
        sort_time_s=float(casc.sort_time_s),
        survival_all_time_s=float(casc.survival_all_time_s),
        ego_paths=ego_paths,
        survivor_paths=paths,
        survivor_path_risk=path_risk,
    )


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


def _concatenate(frames: Sequence[_FrameRows], info: SceneInfo) -> _Scene:
    """Stack all frames' rows: one flat array per field, ``frame_of`` maps rows to frames."""
    n_stages = len(info.cascade.stages)
    scene = _Scene(
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
    dtypes = {"ids": np.int64, "xy": np.float64, "heading": np.float64, "length": np.float64}
    dtypes |= {"width": np.float64, "is_ego": bool, "dropped_at": np.int64, "tier": np.int64}
    dtypes |= {"survival": np.float64, "baseline": bool}
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
    return scene


# ---------------------------------------------------------------------- static entities
def _log_static(rec: rr.RecordingStream, info: SceneInfo, scene: _Scene) -> None:
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
    rec.log(
        L.SUMMARY,
        rr.TextDocument(summary_markdown(info, scene), media_type="text/markdown"),
        static=True,
        strict=True,
    )


# ---------------------------------------------------------------------- scene layers
def _time_columns(scene: _Scene) -> list[rr.TimeColumn]:
    return [
        rr.TimeColumn(L.TIMELINE, duration=scene.times_s),
        rr.TimeColumn(L.FRAME_TIMELINE, sequence=scene.frame_index),
    ]


def _timed_batch(scene: _Scene) -> C.Batch:
    """An empty batch over the scene's two timelines (one row per recorded frame)."""
    ns = np.rint(scene.times_s * 1e9).astype(np.int64)
    return C.Batch(
        indexes={
            L.TIMELINE: (ns, pa.duration("ns")),
            L.FRAME_TIMELINE: (scene.frame_index, pa.int64()),
        }
    )


def _counts(scene: _Scene, mask: np.ndarray) -> np.ndarray:
    """Rows of ``mask`` per frame: the partition lengths of a layer, ``(F,)``."""
    return np.bincount(scene.frame_of[mask], minlength=scene.times_s.size)


def _add_layer(
    rec,
    batch: C.Batch,
    path: str,
    lengths: np.ndarray,
    order: float,
    *,
    strips: pa.Array,
    colors: np.ndarray,
    radii: np.ndarray,
    labels: np.ndarray | None = None,
    show_labels: bool | None = None,
) -> None:
    """One line-strip layer for the whole scene: frame ``f``'s instances in row ``f``.

    ``lengths``: ``(F,)`` instances per frame (0 clears the layer in that frame); the
    other arguments hold the instances of all frames, concatenated: ``colors (K, 3|4)``
    uint8, ``radii (K,)`` (m; negative: UI points), ``labels (K,)``. The draw order and
    the label switch hold for the whole layer, so they are logged once, static.
    """
    rec.log(
        path,
        rr.LineStrips2D.from_fields(draw_order=order, show_labels=show_labels),
        static=True,
        strict=True,
    )
    batch.add(path, C.STRIPS, C.rows(strips, lengths, C.STRIPS.item))
    batch.add(path, C.STRIP_COLORS, C.rows(C.pack_colors(colors), lengths, pa.uint32()))
    batch.add(path, C.STRIP_RADII, C.rows(np.asarray(radii, np.float32), lengths, pa.float32()))
    if labels is not None:
        batch.add(path, C.STRIP_LABELS, C.rows(pa.array(labels, pa.utf8()), lengths, pa.utf8()))


def _tile(color: tuple[int, ...], k: int) -> np.ndarray:
    return np.tile(np.array(color, dtype=np.uint8), (k, 1))


def _log_scene_layers(rec, info: SceneInfo, scene: _Scene, frames, *, labels: str) -> None:
    """Every layer of the scene view, all frames, in one record batch."""
    batch = _timed_batch(scene)
    _add_bodies(rec, batch, info, scene, labels)
    _add_outlines(rec, batch, info, scene)
    _add_links(rec, batch, info, scene)
    _add_paths(rec, batch, info, scene, frames)
    batch.send(rec)


def _add_bodies(rec, batch: C.Batch, info: SceneInfo, scene: _Scene, labels: str) -> None:
    """Capsules: the ego (green), survivors (red by survival risk), dropped (grey)."""
    r = scene.rows
    survivors = ~r["is_ego"] & (r["dropped_at"] < 0)
    dropped = r["dropped_at"] >= 0
    missed = dropped & r["baseline"]
    ids = r["ids"].astype(str)
    tags = _tier_tags(tuple(t.name for t in info.cascade.tiers))
    for path, mask, order, text in (
        (L.EGO_BODY, r["is_ego"], L.ORDER_EGO, np.char.add("ego ", ids)),
        (L.KEPT_BODIES, survivors, L.ORDER_KEPT, _survivor_labels(ids, r["tier"], tags)),
        (L.DROPPED_BODIES, dropped, L.ORDER_DROPPED, _dropped_labels(ids, r, missed)),
    ):
        k = int(mask.sum())
        caps, radii = L.capsules(
            r["xy"][mask], r["heading"][mask], r["length"][mask], r["width"][mask]
        )
        if path == L.KEPT_BODIES:
            rgb = L.risk_colors(r["survival"][mask], info.cascade.baseline_threshold)
        else:
            rgb = _tile(L.EGO if path == L.EGO_BODY else L.DROPPED, k)
        show = _label_mask(labels, path, missed[mask])
        _add_layer(
            rec, batch, path, _counts(scene, mask), order,
            strips=C.uniform_strips(caps), colors=rgb, radii=radii,
            labels=np.where(show, text[mask], ""), show_labels=labels != "none",
        )  # fmt: skip
    everyone = np.ones(r["ids"].size, dtype=bool)
    _add_layer(
        rec, batch, L.HEADINGS, _counts(scene, everyone), L.ORDER_HEADINGS,
        strips=C.uniform_strips(L.noses(r["xy"], r["heading"], r["length"])),
        colors=_tile((20, 20, 20), everyone.size), radii=np.full(everyone.size, -1.5),
    )  # fmt: skip


def _add_outlines(rec, batch: C.Batch, info: SceneInfo, scene: _Scene) -> None:
    """Tier outlines around survivors that reached a tier; yellow ones around FNs."""
    r = scene.rows
    tiered = ~r["is_ego"] & (r["dropped_at"] < 0) & (r["tier"] >= 0)
    missed = (r["dropped_at"] >= 0) & r["baseline"]
    n_tiers = max(len(info.cascade.tiers), 1)
    tier_rgb = np.array([L.tier_color(k) for k in range(n_tiers)], np.uint8)
    tiers = r["tier"][tiered]
    for path, mask, rgb, width, margin in (
        (L.TIER_OUTLINES, tiered, tier_rgb[tiers], L.outline_width_ui(tiers), 0.35),
        (L.MISSED_OUTLINES, missed, _tile(L.MISSED, int(missed.sum())), np.full(int(missed.sum()), 2.0), 0.5),
    ):  # fmt: skip
        boxes = L.outlines(
            r["xy"][mask], r["heading"][mask], r["length"][mask], r["width"][mask], margin
        )
        _add_layer(
            rec, batch, path, _counts(scene, mask), L.ORDER_OUTLINES,
            strips=C.uniform_strips(boxes), colors=rgb, radii=-width,
        )  # fmt: skip


def _add_links(rec, batch: C.Batch, info: SceneInfo, scene: _Scene) -> None:
    """Fig. 2 overlay: per stage, a line from the ego to every agent kept after it."""
    r = scene.rows
    ego_xy = np.zeros((scene.times_s.size, 2))
    ego_xy[scene.frame_of[r["is_ego"]]] = r["xy"][r["is_ego"]]
    for s, stage in enumerate(info.cascade.stages):
        mask = r["kept"][s]
        k = int(mask.sum())
        lines = np.stack([ego_xy[scene.frame_of[mask]], r["xy"][mask]], axis=1)
        _add_layer(
            rec, batch, L.link_path(s, stage.model), _counts(scene, mask), L.ORDER_LINKS + 0.1 * s,
            strips=C.uniform_strips(lines), radii=np.full(k, -L.link_width_ui(s)),
            colors=_tile((*L.stage_color(s), L.LINK_ALPHA), k),
        )  # fmt: skip


def _add_paths(rec, batch: C.Batch, info: SceneInfo, scene: _Scene, frames) -> None:
    """The ego's path candidates and the deeper-tier survivors' forward paths."""
    ego = [p for f in frames for p in f.ego_paths]
    if ego:
        n = len(ego)
        _add_layer(
            rec, batch, L.EGO_PATH, np.array([len(f.ego_paths) for f in frames]), L.ORDER_PATHS,
            strips=C.strips(np.concatenate(ego), np.array([len(p) for p in ego])),
            radii=np.full(n, -L.PATH_WIDTH_UI * 1.5), colors=_tile((*L.EGO, 200), n),
        )  # fmt: skip
    lengths = np.array([f.survivor_paths.shape[0] for f in frames])
    if lengths.sum() == 0:
        return
    points = np.concatenate([f.survivor_paths.reshape(-1, 2) for f in frames])
    per_strip = np.repeat([f.survivor_paths.shape[1] for f in frames], lengths)
    risk = np.concatenate([f.survivor_path_risk for f in frames])
    rgb = L.risk_colors(risk, info.cascade.baseline_threshold)
    rgba = np.concatenate([rgb, np.full((rgb.shape[0], 1), L.PATH_ALPHA, np.uint8)], axis=1)
    _add_layer(
        rec, batch, L.PREDICTED_PATHS, lengths, L.ORDER_PATHS,
        strips=C.strips(points, per_strip), radii=np.full(risk.size, -L.PATH_WIDTH_UI), colors=rgba,
    )  # fmt: skip


def _label_mask(mode: str, path: str, missed: np.ndarray) -> np.ndarray:
    """Which instances of a body layer show their label (``missed``: (k,) FN flags)."""
    if mode == "all":
        return np.ones(missed.size, dtype=bool)
    if mode == "none":
        return np.zeros(missed.size, dtype=bool)
    if path == L.DROPPED_BODIES:
        return missed  # "kept": a dropped agent is labelled only when it is a false negative
    return np.ones(missed.size, dtype=bool)


def _tier_tags(names: tuple[str, ...]) -> np.ndarray:
    """Short tier marks for labels: initials (B, I, C) when unique, else 1, 2, 3."""
    initials = [n[:1].upper() for n in names]
    tags = (
        initials if len(set(initials)) == len(initials) else [str(k + 1) for k in range(len(names))]
    )
    return np.array([*tags, ""])  # index -1 (no tier) -> ""


def _survivor_labels(ids: np.ndarray, tier: np.ndarray, tags: np.ndarray) -> np.ndarray:
    return np.char.rstrip(np.char.add(np.char.add(ids, " "), tags[tier]))


def _dropped_labels(ids: np.ndarray, rows: dict[str, np.ndarray], missed: np.ndarray) -> np.ndarray:
    """``"17 ✗2"``: dropped by stage 2; ``"17 FN ✗2"`` when it was baseline-important."""
    stage = (rows["dropped_at"] + 1).astype(str)
    mark = np.where(missed, " FN ✗", " ✗")
    return np.char.add(np.char.add(ids, mark), stage)


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


def _agent_grid(scene: _Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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


def _log_timelines(rec, info: SceneInfo, scene: _Scene, log10_models: set[str]) -> None:
    """``/risk/<model>/<id>``: each agent's risk from its first to its last frame.

    Frames in between where the agent is absent (or invalid) hold NaN, which the viewer
    draws as a gap. Agents the cascade kept to the end in some frame carry their own
    colour; the others take the view's default, a quiet grey, so that the agents that
    matter stand out among a hundred. Each model is one record batch with a column per
    agent (null outside the agent's span), not one ``send_columns`` call per agent.
    """
    r = scene.rows
    agent_ids, column, first, last = _agent_grid(scene)
    n_frames, others = scene.times_s.size, column >= 0
    ever_kept = np.zeros(agent_ids.size, dtype=bool)
    ever_kept[column[others & (r["dropped_at"] < 0)]] = True
    frame_pos = np.arange(n_frames)
    outside = (frame_pos[None, :] < first[:, None]) | (frame_pos[None, :] > last[:, None])
    colors = C.pack_colors(L.agent_series_colors(agent_ids))
    thresholds = {s.model: s.threshold for s in info.cascade.stages}
    for model in info.model_names:
        grid = np.full((agent_ids.size, n_frames), np.nan)  # (A, F): one row per agent
        grid[column[others], scene.frame_of[others]] = r[f"risk:{model}"][others]
        variants = [(False, grid)]
        if model in log10_models:
            with np.errstate(divide="ignore", invalid="ignore"):
                variants.append((True, np.where(grid > 0, np.log10(grid), np.nan)))
        for is_log, values in variants:
            batch = _timed_batch(scene)
            # All agents' cells in one array; each agent's column is a zero-copy slice.
            cells = C.one_per_row(values.reshape(-1), pa.float64(), outside.reshape(-1))
            own = C.one_per_row(np.repeat(colors, n_frames), pa.uint32(), outside.reshape(-1))
            for a, agent in enumerate(agent_ids):
                path = L.risk_path(model, int(agent), log10=is_log)
                batch.add(path, C.SCALARS, cells.slice(a * n_frames, n_frames))
                if ever_kept[a]:
                    batch.add(path, C.SERIES_COLORS, own.slice(a * n_frames, n_frames))
            batch.send(rec)
            if model in thresholds:
                _log_threshold(rec, scene, model, thresholds[model], is_log)


def _log_threshold(rec, scene: _Scene, model: str, threshold: float, is_log: bool) -> None:
    """The stage threshold as a flat line in the model's risk view."""
    if is_log and threshold <= 0:
        return
    value = math.log10(threshold) if is_log else threshold
    path = f"{L.risk_root(model, log10=is_log)}/{L.THRESHOLD_SERIES}"
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
def _log_cascade_series(rec, info: SceneInfo, scene: _Scene) -> None:
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
    series += [
        (f"{L.TIMING}/sort", "sort into tiers", L.tier_color(1), scene.sort_time_ms),
        (f"{L.TIMING}/cascade_total", "cascade total", L.OTHERS_SERIES, total_ms),
        (f"{L.TIMING}/survival_all", "survival (all)", L.MISSED, scene.survival_all_time_ms),
    ]
    for path, name, color, values in series:
        style = rr.SeriesLines(colors=color, names=name, widths=2.0)
        rec.log(path, style, static=True, strict=True)
        rec.send_columns(
            path,
            indexes=_time_columns(scene),
            columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64)),
            strict=True,
        )


# ---------------------------------------------------------------------- helpers
def _baseline_model(models: Sequence[str]) -> str | None:
    """The model whose tab opens first: the survival baseline the cascade is judged by."""
    return SURVIVAL_MODEL if SURVIVAL_MODEL in models else (models[0] if models else None)


def _units(models: Sequence[str]) -> dict[str, str]:
    """Each model's unit from the registry ("" when dimensionless or not registered)."""
    return {m: MODELS[m].unit for m in models if m in MODELS}


def _focus_points(scene: _Scene, info: SceneInfo) -> tuple[np.ndarray, np.ndarray | None]:
    """Points the scene view frames, and its anchor: the ego and the final survivors.

    Agents a stage dropped are usually far away; framing them would shrink the action.
    Without frames, the whole map.
    """
    r = scene.rows
    if r["ids"].size:
        near = r["is_ego"] | (r["dropped_at"] < 0)
        return r["xy"][near], r["xy"][r["is_ego"]]
    lanes = [
        np.asarray(lane.centerline, dtype=np.float64).reshape(-1, 2) for lane in info.map.lanes
    ]
    return (np.concatenate(lanes) if lanes else np.zeros((1, 2))), None
