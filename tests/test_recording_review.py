"""Reviewing a recording: the misses list, hindsight marks, decluttered labels, map layers,
the opening frame; read back from the ``.rrd`` with ``RrdReader``."""

from __future__ import annotations

import dataclasses
import pathlib
import re

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from test_recordings import TIMES, make_results, read_rrd, rgba

from outputs.sinks import FrameResult
from recordings import SceneRecorder
from recordings import layout as L
from recordings import writer as W
from recordings.labels import declutter
from replay.cli.app import main
from replay.core.tables import TableSink
from risk import MODELS
from risk.frame import MapLine

MISS_ROW = re.compile(
    r"agent (-?\d+) · dropped by stage (\d+) \((\w+)\) · important by ([\w+]+) · "
    r"([\d.]+) s \((\d+) frames?\)"
)


@dataclasses.dataclass(frozen=True, eq=False)
class WithTruth(FrameResult):
    """A frame result that carries the hindsight label, as the run will provide it."""

    truth_label: object = None


def record(tmp_path: pathlib.Path, info, results, **options) -> dict:
    out = tmp_path / "scene.rrd"
    rec, table = SceneRecorder(out, **options), TableSink(None)
    for sink in (rec, table):
        sink.begin(info)
        for r in results:
            sink.add(r)
    rec.close()
    return {"ents": read_rrd(out), "table": table.dataframe(), "out": out}


def misses_list(ents: dict, times: list[float]) -> set[tuple[int, int, int, str]]:
    """(frame position, agent, stage, reference) of every miss, from the text log rows:
    each row names an episode of consecutive recorded frames starting at its time."""
    got = set()
    for path, ent in ents.items():
        if not (path.startswith(L.AGENTS) and path.endswith("/" + L.BODY)):
            continue
        for t_ns, row in ent.rows:
            if "text" not in row:
                continue
            (text,) = row["text"]
            m = MISS_ROW.fullmatch(text)
            assert m, text
            agent, stage, _, reference, _, n = m.groups()
            assert path == L.body_path(int(agent))  # the row selects the agent's body
            assert row["level"] == ["WARN"]
            first = int(np.argmin(np.abs(np.array(times) - t_ns / 1e9)))
            got |= {(first + k, int(agent), int(stage), reference) for k in range(int(n))}
    return got


def table_misses(df: pl.DataFrame, stage_names) -> set[tuple[int, int, int, str]]:
    """The same from the table: dropped by a stage although the baseline (or, when the
    table has it, the hindsight truth) marks the agent important."""
    truth = pl.col("truth_label").fill_null(False) if "truth_label" in df.columns else pl.lit(False)
    rows = df.filter(pl.col("dropped_by").is_not_null() & (pl.col("baseline") | truth))
    out = set()
    for r in rows.with_columns(truth.alias("_truth")).iter_rows(named=True):
        ref = "+".join(
            n for n, on in (("baseline", r["baseline"]), ("hindsight", r["_truth"])) if on
        )
        out.add((r["frame"], r["agent_id"], stage_names.index(r["dropped_by"]) + 1, ref))
    return out


def test_misses_list_equals_the_tables_misses(tmp_path):
    info, results = make_results()
    rec = record(tmp_path, info, results)
    got = misses_list(rec["ents"], list(TIMES))
    # Frame 0: agent 3 dropped by stage 1 and agent 2 by stage 2, both baseline-important.
    assert got == {(0, 3, 1, "baseline"), (0, 2, 2, "baseline")}
    assert got == table_misses(rec["table"], list(info.cascade.stage_names))


def with_truth(results, labels: dict[int, list]) -> list[FrameResult]:
    """``labels``: frame -> one hindsight label per agent (True, False or None)."""
    return [
        WithTruth(r.index, r.frame, r.risks, r.cascade, truth_label=labels.get(r.index))
        for r in results
    ]


def test_hindsight_labels_mark_misses_and_positives(tmp_path):
    info, results = make_results()
    # Agents [ego, 1, 2, 3, 4]. Frame 0: agent 2 (baseline miss) also came close.
    # Frame 2: agent 4 (dropped, not baseline-important) came close: a hindsight-only
    # miss; agent 1 (kept) came close: a hindsight positive; agent 3 censored (None).
    labels = {0: [None, False, True, False, None], 2: [None, True, False, None, True]}
    rec = record(tmp_path, info, with_truth(results, labels))
    ents = rec["ents"]
    got = misses_list(ents, list(TIMES))
    assert got == {
        (0, 3, 1, "baseline"),
        (0, 2, 2, "baseline+hindsight"),
        (2, 4, 2, "hindsight"),
    }
    # The table will carry truth_label (hindsight branch); built here from the same labels.
    df = rec["table"].with_columns(
        pl.Series("truth_label", [bool(v) if v is not None else None for v in
                                  [labels.get(r.index, [None] * 5)[i] for r in results
                                   for i in np.flatnonzero(r.cascade.others)]]),
    )  # fmt: skip
    assert got == table_misses(df, list(info.cascade.stage_names))

    def body(agent: int, frame: int):
        ent = ents[L.body_path(agent)]
        strips = ent.column("strips", rows_with="strips")[frame]
        colors = ent.column("colors", rows_with="strips")[frame]
        return [len(s) for s in strips], [rgba(c)[:3] for c in colors]

    # Agent 4 in frame 2: yellow capsule and ring, like any miss.
    counts, colors = body(4, 2)
    assert counts == [2, 2, 17] and colors[0] == L.MISSED and colors[2] == L.MISSED
    # Agent 1 in frame 2, kept and came close: tier outline plus an orange ring.
    counts, colors = body(1, 2)
    assert counts == [2, 2, 5, 17] and colors[3] == L.HINDSIGHT
    # Censored (None) marks nothing: agent 3 in frame 2 is a plain dropped agent.
    assert body(3, 2) == ([2, 2], [L.DROPPED, L.NOSE])


def test_truth_label_of_the_wrong_length_is_refused(tmp_path):
    info, results = make_results()
    rec = SceneRecorder(tmp_path / "x.rrd")
    rec.begin(info)
    with pytest.raises(W.RecordingError, match="truth_label has 2 values, expected 5"):
        rec.add(with_truth(results, {0: [True, False]})[0])


def toy_scene(xy: np.ndarray, frame_of: np.ndarray) -> W.SceneRows:
    n_frames = int(frame_of.max()) + 1
    scene = W.SceneRows(
        times_s=np.arange(n_frames, dtype=float), frame_index=np.arange(n_frames),
        frame_of=frame_of, false_negatives=np.zeros((n_frames, 1), int),
        stage_time_ms=np.zeros((n_frames, 1)), sort_time_ms=np.zeros(n_frames),
        survival_all_time_ms=np.zeros(n_frames),
    )  # fmt: skip
    scene.rows["xy"] = xy
    return scene


def test_declutter_by_hand():
    # Frame 0: A (priority 5) at 0, B (1) 3 m away, C (1) 4 m from B but 7 m from A,
    # D (100, a miss) 20 m away. B gives way to A; C gives way to B (a tie, earlier wins)
    # although B itself is hidden: the rule is "nobody more important nearby".
    # Frame 1: the same B alone keeps its label.
    xy = np.array([[0, 0], [3, 0], [7, 0], [20, 0], [3, 0]], dtype=float)
    frame_of = np.array([0, 0, 0, 0, 1])
    wanted = np.array([True, True, True, True, True])
    priority = np.array([5, 1, 1, 100, 1])
    shown = declutter(toy_scene(xy, frame_of), wanted, priority, 4.5)
    assert shown.tolist() == [True, False, False, True, True]
    # Unwanted rows never show, and do not push others away.
    shown = declutter(toy_scene(xy, frame_of), np.array([False, True, True, True, True]),
                         priority, 4.5)  # fmt: skip
    assert shown.tolist() == [False, True, False, True, True]


def test_shown_labels_keep_their_distance():
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 60, size=(400, 2))
    frame_of = np.repeat(np.arange(4), 100)
    priority = rng.integers(0, 4, size=400)
    shown = declutter(toy_scene(xy, frame_of), np.ones(400, bool), priority, 7.0)
    for f in range(4):
        pts = xy[shown & (frame_of == f)]
        d = np.linalg.norm(pts[:, None] - pts[None, :], axis=-1) + np.eye(len(pts)) * 1e9
        assert d.min() >= 7.0
        assert len(pts) > 10  # and it does not hide everything


def test_map_layers_below_the_agents(tmp_path):
    info, results = make_results()
    lines = (
        MapLine(1, "lane_boundary", np.array([[0.0, 2.0], [50.0, 2.0]]), style="dashed"),
        MapLine(2, "lane_boundary", np.array([[0.0, -2.0], [50.0, -2.0]])),
        MapLine(3, "road_edge", np.array([[0.0, 6.0], [50.0, 6.0]])),
        MapLine(4, "crosswalk", np.array([[5.0, -3], [8.0, -3], [8.0, 3], [5.0, 3]]), closed=True),
    )
    info = dataclasses.replace(info, map=dataclasses.replace(info.map, lines=lines))
    ents = record(tmp_path, info, results)["ents"]
    counts = {}
    for kind, path in L.MAP_LINES.items():
        if path in ents:
            ent = ents[path]
            assert not ent.rows  # static
            counts[kind] = len(ent.static["strips"])
            assert rgba(ent.static["colors"][0])[:3] == L.MAP_LINE_COLORS[kind]
            assert ent.static["draw_order"][0] < ents[L.MAP_LANES].static["draw_order"][0]
    assert counts == {"lane_boundary": 2, "road_edge": 1, "crosswalk": 1}
    crosswalk = np.array(ents[L.MAP_LINES["crosswalk"]].static["strips"][0])
    assert crosswalk.shape == (5, 2)
    np.testing.assert_allclose(crosswalk[0], crosswalk[-1])  # closed


def test_view_opens_120_m_around_the_ego():
    ego = np.array([[100.0, 50.0], [110.0, 50.0]])
    (x0, x1), (y0, y1) = L.ego_bounds(ego, aspect=1.5)
    assert (x1 - x0) == pytest.approx(120.0) and (y1 - y0) == pytest.approx(80.0)
    assert ((x0 + x1) / 2, -(y0 + y1) / 2) == pytest.approx((105.0, 50.0))  # y flipped
    # An ego that drives further: its whole drive plus 20 m on either side.
    (x0, x1), (y0, y1) = L.ego_bounds(np.array([[0.0, 0.0], [300.0, 0.0]]), aspect=1.0)
    assert (x0, x1) == pytest.approx((-20.0, 320.0)) and (y1 - y0) == pytest.approx(340.0)
    (x0, x1), (y0, y1) = L.ego_bounds(np.array([[0.0, 0.0], [0.0, 100.0]]), aspect=2.0)
    assert (-y1, -y0) == pytest.approx((-20.0, 120.0)) and (x1 - x0) == pytest.approx(280.0)


# ---------------------------------------------------------------------- real data
@pytest.mark.realdata
def test_waymo_recording_review(shared_data, tmp_path):
    """The Waymo sample end to end: per-agent layout, misses = the table's misses,
    labels per frame (ego + tiers + misses, decluttered), the map's layers."""
    runner = CliRunner()
    scene = tmp_path / "w.mcap"
    tfrecord = next((shared_data / "waymo").glob("*.tfrecord"))
    res = runner.invoke(main, ["convert", "waymo", str(tfrecord), "-o", str(scene)])
    assert res.exit_code == 0, res.output
    rrd, table = tmp_path / "w.rrd", tmp_path / "w.parquet"
    res = runner.invoke(
        main, ["run", str(scene), "-o", str(rrd), "--table", str(table), "--no-progress"]
    )
    assert res.exit_code == 0, res.output
    ents, df = read_rrd(rrd), pl.read_parquet(table)
    times = sorted(df["t_s"].unique().to_list())
    stage_names = [c[len("kept_") :] for c in df.columns if c.startswith("kept_")]
    # Per-agent layout: every agent of the table has its body and nine risk timelines.
    for agent in df["agent_id"].unique().to_list():
        assert L.body_path(agent) in ents
        for model in MODELS:
            assert L.risk_path(model, agent) in ents
    # The misses list is the table's misses.
    frame_pos = {f: k for k, f in enumerate(sorted(df["frame"].unique().to_list()))}
    want = {(frame_pos[f], a, s, r) for f, a, s, r in table_misses(df, stage_names)}
    assert misses_list(ents, times) == want
    # Labels: the ego in every frame, then tier agents and misses, never closer than
    # LABEL_SPACING_M; and far fewer than agents.
    labelled = np.zeros(len(times), int)
    positions: dict[int, list] = {}
    for path, ent in ents.items():
        if path != L.EGO_BODY and not (path.startswith(L.AGENTS) and path.endswith("/body")):
            continue
        strips = ent.column("strips", rows_with="strips")
        for f, labels in enumerate(ent.column("labels", rows_with="strips")):
            if labels and any(labels):
                labelled[f] += 1
                positions.setdefault(f, []).append(np.mean(strips[f][0], axis=0))
    n_agents = df.group_by("frame").len().sort("frame")["len"].to_numpy()
    assert labelled.min() >= 1 and (labelled < n_agents / 2).all()
    for pts in positions.values():
        pts = np.array(pts)
        d = np.linalg.norm(pts[:, None] - pts[None, :], axis=-1) + np.eye(len(pts)) * 1e9
        assert d.min() >= L.LABEL_SPACING_M - 0.01
    # The map: lanes plus the sample's 58 road lines, 28 road edges and 4 crosswalks.
    sizes = {k: len(ents[p].static["strips"]) for k, p in L.MAP_LINES.items() if p in ents}
    assert sizes == {"lane_boundary": 58, "road_edge": 28, "crosswalk": 4}


@pytest.mark.realdata
def test_recorded_scene_marks_the_tables_hindsight_positives(shared_data, tmp_path):
    """A highD scene end to end: the recording computes the hindsight truth from the same
    recorded tracks (one rows function) as the table, so every kept agent whose
    ``truth_label`` is true carries the orange ring in its frame, and no other does.
    (highD: its 7.5 s scenes have complete 5 s windows with positives; SinD's, whose
    positions move faster than their recorded speeds, are mostly track-flagged.)"""
    src = sorted((shared_data / "recorded" / "highd").glob("*.xml"))[0]
    scene, rrd, table = tmp_path / "s.mcap", tmp_path / "s.rrd", tmp_path / "s.parquet"
    runner = CliRunner()
    assert runner.invoke(main, ["convert", "commonroad", str(src), "-o", str(scene)]).exit_code == 0
    res = runner.invoke(
        main, ["run", str(scene), "-o", str(rrd), "--table", str(table), "--no-progress"]
    )
    assert res.exit_code == 0, res.output
    ents, df = read_rrd(rrd), pl.read_parquet(table)
    kept = df.filter(pl.col("dropped_by").is_null())
    positives = kept.filter(pl.col("truth_label").fill_null(False))
    assert positives.height > 0, "this scene has agents that came close"
    pos = {f: k for k, f in enumerate(sorted(df["frame"].unique().to_list()))}
    for r in kept.iter_rows(named=True):
        ent = ents[L.body_path(r["agent_id"])]
        per_frame = ent.column("colors", rows_with="strips")
        assert len(per_frame) == len(pos)  # one row of the body per recorded frame
        colors = [rgba(c)[:3] for c in per_frame[pos[r["frame"]]]]
        assert (L.HINDSIGHT in colors) == bool(r["truth_label"]), r
