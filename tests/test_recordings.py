"""The Rerun recording of a replay: written from hand-built results, read back, checked."""

from __future__ import annotations

import math
import pathlib
import shutil
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recordings import SceneRecorder
from recordings import layout as L
from recordings.errors import RecordingError
from replay.core.engine import FrameResult, SceneInfo, Sink
from risk.cascade import CascadeConfig, CascadeResult, Stage, Tier
from risk.frame import Frame, Lane, LaneMap

rr_chunk = pytest.importorskip("rerun.chunk")

MODELS = ("near", "wide", "survival")  # fake models: the recorder must not care about names
EGO_ID = 100
GREEN = L.EGO


# ---------------------------------------------------------------------- hand-built results
def cascade_config() -> CascadeConfig:
    return CascadeConfig(
        stages=(Stage("near", 0.2), Stage("wide", 1e-6)),
        tiers=(Tier("behavior", 1e-25), Tier("interactive", 1e-3), Tier("cooperative", 0.1, 1)),
        baseline_threshold=1e-25,
        provenance="hand-made for the recorder tests",
    )


def scene_info(n_frames: int, cfg: CascadeConfig | None = None) -> SceneInfo:
    lanes = LaneMap(
        (
            Lane(1, np.array([[0.0, -50.0], [0.0, 50.0]]), (2,)),
            Lane(2, np.array([[-50.0, 0.0], [50.0, 0.0]]), kind="crosswalk"),
        )
    )
    return SceneInfo(
        map=lanes,
        metadata={"dataset": "hand-made", "scenario_id": "rec-test"},
        labels={"focal": (1,)},
        frame_period_s=0.5,
        ego_id=EGO_ID,
        cascade=cfg or cascade_config(),
        model_names=MODELS,
        source=None,
        n_frames=n_frames,
    )


# Four other agents (ids 1..4); per frame, each model's risk is set by hand.
# Agent 3 is invalid in frame 1 (a gap in its timelines); agent 4 appears in frame 2.
NEAR = np.array([[0.9, 0.5, 0.1, np.nan], [0.8, 0.3, np.nan, np.nan], [0.7, 0.25, 0.05, 0.6]])
WIDE = np.array([[1e-2, 1e-9, 1e-3, np.nan], [1e-2, 1e-5, np.nan, np.nan], [0.5, 1e-4, 1e-7, 1e-8]])
SURV = np.array(
    [[0.5, 1e-20, 1e-10, np.nan], [0.2, 1e-4, np.nan, np.nan], [0.05, 1e-2, 0.0, 1e-30]]
)
TIMES = (0.0, 0.5, 1.0)


def make_frame(k: int) -> Frame:
    n = 5  # ego + 4
    xy = np.array([[0.0, -20.0 + 4.0 * k], [6.0, 5.0], [-12.0, 0.0], [30.0, 20.0], [3.0, -3.0]])
    heading = np.array([math.pi / 2, math.pi, 0.0, -math.pi / 2, 0.3])
    valid = np.array([True, True, True, k != 1, k == 2])
    paths = [
        np.array([p, p + 20.0 * np.array([math.cos(h), math.sin(h)])])
        for p, h in zip(xy, heading, strict=True)
    ]
    return Frame.from_arrays(
        xy, heading, np.full(n, 5.0), np.full(n, 4.0), np.full(n, 2.0), paths, ego=0,
        ids=[EGO_ID, 1, 2, 3, 4], valid=valid, t=TIMES[k],
    )  # fmt: skip


def run_cascade(frame: Frame, risks: dict[str, np.ndarray], cfg: CascadeConfig) -> CascadeResult:
    """A straightforward cascade over the hand-made risks (the recorder only draws it)."""
    others, n = frame.others, frame.n_agents
    kept = np.zeros((len(cfg.stages), n), dtype=bool)
    dropped = np.full(n, -1, dtype=np.int8)
    alive = others.copy()
    for s, stage in enumerate(cfg.stages):
        keep = alive & (risks[stage.model] >= stage.threshold)
        dropped[alive & ~keep] = s
        kept[s], alive = keep, keep
    surv = risks["survival"]
    tier = np.full(n, -1, dtype=np.int8)
    for k, t in enumerate(cfg.tiers):
        ok = alive & (tier == k - 1) & (surv >= t.min_survival_risk)
        if t.max_agents is not None:
            top = np.argsort(-np.where(ok, surv, -np.inf), kind="stable")[: t.max_agents]
            ok &= np.isin(np.arange(n), top)
        tier[ok] = k
    baseline = others & (surv >= cfg.baseline_threshold)
    fn = np.array(
        [(baseline & (dropped >= 0) & (dropped <= s)).sum() for s in range(len(cfg.stages))]
    )
    return CascadeResult(
        stage_names=cfg.stage_names, kept=kept, dropped_at=dropped, tier=tier,
        survival=np.where(alive, surv, np.nan), baseline=baseline, false_negatives=fn,
        stage_time_s=np.array([1e-3, 2e-3]), sort_time_s=4e-4, survival_all_time_s=9e-3,
        others=others, survival_all=np.where(others, surv, np.nan),
    )  # fmt: skip


def make_results(cfg: CascadeConfig | None = None) -> tuple[SceneInfo, list[FrameResult]]:
    cfg = cfg or cascade_config()
    results = []
    for k in range(3):
        frame = make_frame(k)
        risks = {
            name: np.concatenate([[np.nan], table[k]])
            for name, table in zip(MODELS, (NEAR, WIDE, SURV), strict=True)
        }
        risks = {m: np.where(frame.others, r, np.nan) for m, r in risks.items()}
        results.append(
            FrameResult(index=k, frame=frame, risks=risks, cascade=run_cascade(frame, risks, cfg))
        )
    return scene_info(3, cfg), results


def write(tmp_path: pathlib.Path, **options) -> tuple[pathlib.Path, list[FrameResult]]:
    info, results = make_results()
    out = tmp_path / "scene.rrd"
    rec = SceneRecorder(out, **options)
    rec.begin(info)
    for r in results:
        rec.add(r)
    rec.close()
    return out, results


# ---------------------------------------------------------------------- reading back
class Entity:
    """One entity read back: static components and time-indexed rows (sorted by time)."""

    def __init__(self) -> None:
        self.static: dict[str, list] = {}
        self.rows: list[tuple[int, dict[str, list]]] = []  # (time ns, component -> values)

    def column(self, component: str, *, rows_with: str | None = None) -> list:
        """``component`` per row in time order (None where absent); ``rows_with``: only
        the rows that hold that component (e.g. the line strips of an entity that also
        holds text log rows)."""
        return [
            values.get(component)
            for _, values in sorted(self.rows, key=lambda r: r[0])
            if rows_with is None or rows_with in values
        ]

    def times_s(self) -> list[float]:
        return [t / 1e9 for t, _ in sorted(self.rows, key=lambda r: r[0])]


def read_rrd(path: pathlib.Path) -> dict[str, Entity]:
    out: dict[str, Entity] = {}
    for chunk in rr_chunk.RrdReader(path).stream().to_chunks():
        ent = out.setdefault(chunk.entity_path, Entity())
        batch = chunk.to_record_batch()
        comps = [n for n in batch.schema.names if ":" in n]
        data = {n: batch.column(n).to_pylist() for n in comps}
        if chunk.is_static:
            for n in comps:
                ent.static[n.split(":", 1)[1]] = data[n][-1]
            continue
        times = batch.column(L.TIMELINE).cast("int64").to_pylist()
        for i, t in enumerate(times):
            row = {n.split(":", 1)[1]: data[n][i] for n in comps if data[n][i] is not None}
            if row:  # a null cell means "nothing logged at this time"
                ent.rows.append((t, row))
    return out


def rgba(packed: int) -> tuple[int, int, int, int]:
    return tuple(int(packed) >> s & 0xFF for s in (24, 16, 8, 0))  # type: ignore[return-value]


def scalars(ent: Entity) -> np.ndarray:
    return np.array([v[0] for v in ent.column("scalars")], dtype=np.float64)


# ---------------------------------------------------------------------- the recording
@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[pathlib.Path, dict[str, Entity], list[FrameResult]]:
    out, results = write(tmp_path_factory.mktemp("rec"))
    return out, read_rrd(out), results


def test_recorder_is_a_sink(tmp_path):
    assert isinstance(SceneRecorder(tmp_path / "x.rrd"), Sink)


def test_entities_present(recording):
    _, ents, _ = recording
    for path in (L.SCENE, L.MAP_LANES, L.EGO_BODY, L.EGO_PATH, L.SUMMARY):
        assert path in ents, path
    for agent in (1, 2, 3, 4):  # one subtree per agent: body and nine (here three) risks
        assert L.body_path(agent) in ents
        for model in MODELS:
            assert L.risk_path(model, agent) in ents
    for model in MODELS:
        assert L.risk_path(model, EGO_ID) not in ents  # the ego has no risk against itself
    assert not any(p.startswith(L.LINKS) for p in ents)  # links are an option, off


def test_per_agent_subtree_layout(recording):
    """Everything of agent k lives under /scene/agents/k, and only there."""
    _, ents, _ = recording
    agent_paths = sorted(p for p in ents if p.startswith(L.AGENTS + "/"))
    by_agent: dict[str, set[str]] = {}
    for p in agent_paths:
        agent, *rest = p[len(L.AGENTS) + 1 :].split("/")
        by_agent.setdefault(agent, set()).add("/".join(rest))
    assert set(by_agent) == {"1", "2", "3", "4"}
    risks = {f"{L.RISK}/{m}" for m in MODELS} | {
        f"{L.RISK_LOG10}/{m}" for m in ("wide", "survival")
    }
    assert by_agent["2"] == {L.BODY, L.PATH} | risks  # agent 2 reaches a deeper tier
    assert by_agent["3"] == {L.BODY} | risks  # never beyond the first stage: no path


def test_scene_is_flipped_for_display(recording):
    _, ents, _ = recording
    assert ents[L.SCENE].static["scale"] == [pytest.approx([1.0, -1.0, 1.0])]


def test_risk_timeline_equals_input_with_gap(recording):
    _, ents, _ = recording
    # Agent 3: present in frames 0 and 2, invalid in frame 1 -> NaN there (a gap).
    ent = ents[L.risk_path("near", 3)]
    assert ent.times_s() == pytest.approx(TIMES)
    np.testing.assert_array_equal(scalars(ent), [0.1, np.nan, 0.05])
    # Agent 4 appears only in the last frame: one row, nothing before it.
    ent = ents[L.risk_path("wide", 4)]
    assert ent.times_s() == pytest.approx([1.0])
    np.testing.assert_array_equal(scalars(ent), [1e-8])
    # Agent 1 in every frame, raw values in the model's units.
    np.testing.assert_array_equal(scalars(ents[L.risk_path("survival", 1)]), SURV[:, 0])
    # The agents the views open on have their own colour (the same in every view); the
    # others take the view's quiet default.
    own = tuple(int(c) for c in L.agent_series_colors(np.array([1]))[0])
    for model in MODELS:
        assert rgba(ents[L.risk_path(model, 1)].static["colors"][0])[:3] == own
    assert "colors" not in ents[L.risk_path("survival", 4)].static  # agent 4 never matters


def test_frame_timeline_is_logged(recording):
    out, _, _ = recording
    chunk = next(
        c
        for c in rr_chunk.RrdReader(out).stream().to_chunks()
        if c.entity_path == L.EGO_BODY and not c.is_static
    )
    assert chunk.to_record_batch().column(L.FRAME_TIMELINE).to_pylist() == [0, 1, 2]


def test_wide_range_models_get_a_log10_view(recording):
    _, ents, _ = recording
    # "wide" spans 1e-9..0.5 and "survival" 1e-30..0.5: both beyond 4 decades; "near" is not.
    assert L.risk_path("near", 1, log10=True) not in ents
    np.testing.assert_allclose(
        scalars(ents[L.risk_path("wide", 2, log10=True)]), [-9.0, -5.0, -4.0]
    )
    # Zero risk has no logarithm: a gap, not -inf.
    np.testing.assert_array_equal(
        scalars(ents[L.risk_path("survival", 3, log10=True)])[[1, 2]], [np.nan, np.nan]
    )


def test_funnel_counts(recording):
    _, ents, results = recording
    # Frame 0: others 1,2,3. near >= 0.2 keeps 1,2; wide >= 1e-6 keeps 1 (2 has 1e-9).
    # Frame 1: others 1,2. near keeps 1,2; wide keeps 1,2.
    # Frame 2: others 1..4. near keeps 1,2,4; wide keeps 1,2 (4 has 1e-8).
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/0_others"]), [3, 2, 4])
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/1_near"]), [2, 2, 3])
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/2_wide"]), [1, 2, 2])
    # Tiers: behavior = every survivor with R_S >= 1e-25 (frame 2: agent 4 has 1e-30).
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/tier_1_behavior"]), [1, 2, 2])
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/tier_2_interactive"]), [1, 1, 2])
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/tier_3_cooperative"]), [1, 1, 0])
    # Baseline: R_S >= 1e-25 among the others; frame 2: agent 3 has 0, agent 4 1e-30.
    np.testing.assert_array_equal(scalars(ents[f"{L.FUNNEL}/baseline"]), [3, 2, 2])
    # False negatives: frame 0 drops 3 (baseline) at stage 1 and 2 (baseline) at stage 2.
    np.testing.assert_array_equal(scalars(ents[f"{L.FALSE_NEGATIVES}/1_near"]), [1, 0, 0])
    np.testing.assert_array_equal(scalars(ents[f"{L.FALSE_NEGATIVES}/2_wide"]), [2, 0, 0])
    expected = [r.cascade.n_kept.tolist() for r in results]
    assert expected == [[2, 1], [2, 2], [3, 2]]


def test_timing_in_milliseconds(recording):
    _, ents, _ = recording
    np.testing.assert_allclose(scalars(ents[f"{L.TIMING}/1_near"]), [1.0] * 3)
    np.testing.assert_allclose(scalars(ents[f"{L.TIMING}/cascade_total"]), [3.4] * 3)
    np.testing.assert_allclose(scalars(ents[f"{L.TIMING}/survival_all"]), [9.0] * 3)


def test_ego_body_is_green_capsule_at_ego(recording):
    _, ents, _ = recording
    ego = ents[L.EGO_BODY]
    for k, (colors, strips, radii) in enumerate(
        zip(ego.column("colors"), ego.column("strips"), ego.column("radii"), strict=True)
    ):
        assert [rgba(c)[:3] for c in colors] == [GREEN, L.NOSE]  # capsule, heading nose
        centre = np.mean(np.array(strips[0]), axis=0)
        np.testing.assert_allclose(centre, [0.0, -20.0 + 4.0 * k], atol=1e-5)
        assert radii[0] == pytest.approx(1.0)  # half the 2 m width
    assert ego.column("labels") == [["ego 100", ""]] * 3


def body(ents, agent: int, frame: int) -> tuple[list, list, list]:
    """(strip point counts, RGB colours, labels) of an agent's body entity in a frame."""
    ent = ents[L.body_path(agent)]
    strips = ent.column("strips", rows_with="strips")[frame]
    return (
        [len(s) for s in strips],
        [rgba(c)[:3] for c in ent.column("colors", rows_with="strips")[frame]],
        ent.column("labels", rows_with="strips")[frame],
    )


def test_bodies_markers_and_colours(recording):
    _, ents, _ = recording
    # Frame 0: agent 1 kept to the cooperative tier: red capsule, nose, tier outline.
    counts, colors, labels = body(ents, 1, 0)
    assert counts == [2, 2, 5]
    assert colors[0][0] > 200 and colors[0][0] > colors[0][1]  # red by survival risk
    assert colors[2] == L.tier_color(2)
    assert labels == ["", "", "1 C"]  # on the outline: white/cyan/magenta text, not red
    # Agents 2 and 3 were dropped although baseline-important: yellow capsule and ring.
    for agent, stage in ((2, 2), (3, 1)):
        counts, colors, labels = body(ents, agent, 0)
        assert counts == [2, 2, 17] and colors[0] == L.MISSED and colors[2] == L.MISSED
        assert labels == ["", "", f"{agent} MISS ✗{stage}"]  # on the yellow ring
    # Frame 2: agents 3 and 4 dropped, not important: grey, no marker, no label.
    for agent in (3, 4):
        counts, colors, labels = body(ents, agent, 2)
        assert counts == [2, 2] and colors[0] == L.DROPPED and labels == ["", ""]
    # The riskier survivor is redder (less green): frame 1 has R_S 0.2 (agent 1), 1e-4 (2).
    assert body(ents, 1, 1)[1][0][1] < body(ents, 2, 1)[1][0][1]
    # Agent 4 is absent in frames 0 and 1: empty rows (nothing drawn), present in frame 2.
    assert [len(s) for s in ents[L.body_path(4)].column("strips", rows_with="strips")] == [0, 0, 2]


def test_label_counts_per_frame(recording):
    """Default labels: the ego, the tier agents and the misses (frame 2: agents 3 and 4
    are dropped but not important, so only the ego and agents 1, 2 are labelled)."""
    _, ents, _ = recording
    per_frame = [0, 0, 0]
    for path, ent in ents.items():
        if path == L.EGO_BODY or (path.startswith(L.AGENTS) and path.endswith("/" + L.BODY)):
            for f, labels in enumerate(ent.column("labels", rows_with="strips")):
                per_frame[f] += sum(bool(x) for x in labels or [])
    assert per_frame == [4, 3, 3]


@pytest.mark.parametrize(
    ("mode", "frame2"), [("all", [["3 ✗1", ""], ["4 ✗2", ""]]), ("none", [None, None])]
)
def test_label_modes(tmp_path, mode, frame2):
    out, _ = write(tmp_path, labels=mode)
    ents = read_rrd(out)
    got = [ents[L.body_path(a)].column("labels", rows_with="strips")[2] for a in (3, 4)]
    assert got == frame2


def test_links_are_an_option_and_start_at_the_ego(tmp_path):
    out, _ = write(tmp_path, links=True)
    ents = read_rrd(out)
    for s, model in enumerate(("near", "wide")):
        strips = ents[L.link_path(s, model)].column("strips")
        assert [len(x) for x in strips] == [[2, 2, 3], [1, 2, 2]][s]
        for k, frame_strips in enumerate(strips):
            for strip in frame_strips:
                np.testing.assert_allclose(strip[0], [0.0, -20.0 + 4.0 * k], atol=1e-5)


def test_threshold_lines_in_stage_views(recording):
    _, ents, _ = recording
    np.testing.assert_allclose(scalars(ents[L.threshold_path("near")]), [0.2] * 3)
    log_thr = ents[L.threshold_path("wide", log10=True)]
    np.testing.assert_allclose(scalars(log_thr), [-6.0] * 3)


def test_map_lanes_static(recording):
    _, ents, _ = recording
    lanes = ents[L.MAP_LANES]
    assert not lanes.rows
    assert len(lanes.static["strips"]) == 2
    assert [rgba(c)[:3] for c in lanes.static["colors"]] == [L.LANE, L.LANE_OTHER]
    assert not any(p in ents for p in L.MAP_LINES.values())  # this map has no lines


def test_summary_text(recording):
    _, ents, _ = recording
    doc = ents[L.SUMMARY].static
    assert doc["media_type"] == ["text/markdown"]
    text = doc["text"][0]
    for needle in ("rec-test", "hand-made for the recorder tests", "| 1 (blue) | near | 0.2", "cooperative",
                   "1e-25", "ego id | 100", "frames recorded | 3 of 3",
                   "keeps **1.7** of 3.0 other agents per frame", "**2** false negatives"):  # fmt: skip
        assert needle in text, needle


def blueprint_views(out: pathlib.Path) -> dict[str, tuple[str, str, list[str]]]:
    """View name -> (class, origin, contents) of the recording's default blueprint."""
    reader = rr_chunk.RrdReader(out)
    assert len(reader.blueprints()) == 1
    views = {}
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        if "ViewBlueprint:class_identifier" in batch.schema.names:
            kind = batch.column("ViewBlueprint:class_identifier").to_pylist()[0][0]
            origin = batch.column("ViewBlueprint:space_origin").to_pylist()[0][0]
            name = batch.column("ViewBlueprint:display_name").to_pylist()[0][0]
            views[chunk.entity_path] = (name, kind, origin)
    contents = {}
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        col = next((n for n in batch.schema.names if n.endswith("query")), None)
        if col is not None:
            contents[chunk.entity_path.rsplit("/", 1)[0]] = batch.column(col).to_pylist()[0]
    return {
        name: (kind, origin, contents.get(path, [])) for path, (name, kind, origin) in views.items()
    }


def test_blueprint_lays_out_views(recording):
    out, _, _ = recording
    views = blueprint_views(out)
    assert views["Scene (top-down, y north)"][:2] == ("2D", "/")
    assert views["Summary"][:2] == ("TextDocument", L.SUMMARY)
    assert views["Misses (click a row: select the agent)"][:2] == ("TextLog", L.AGENTS)
    for name in ("Funnel: agents left", "Compute time (ms)", "False negatives per frame (up to stage k)",
                 "near · stage", "log10 wide · stage", "log10 survival"):  # fmt: skip
        assert views[name][0] == "TimeSeries", name
    # The risk views open on the agents that matter: misses (2, 3) first, then tiers (1).
    contents = views["log10 survival"][2]
    assert contents == [f"+ {L.risk_path('survival', a, log10=True)}" for a in (2, 3, 1)]


def test_rerun_verify_passes(recording):
    out, _, _ = recording
    exe = pathlib.Path(sys.executable).with_name("rerun")
    if not exe.exists():
        exe = shutil.which("rerun")
        if exe is None:
            pytest.skip("the rerun binary is not installed")
    proc = subprocess.run(
        [str(exe), "rrd", "verify", str(out)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr


# ---------------------------------------------------------------------- lifecycle and errors
def test_output_mode_follows_umask(recording):
    import os
    import stat

    out, _, _ = recording
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o666 & ~umask  # not mkstemp's 0600


def test_abort_leaves_nothing(tmp_path):
    info, results = make_results()
    rec = SceneRecorder(tmp_path / "a.rrd")
    rec.begin(info)
    rec.add(results[0])
    rec.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RecordingError):
        rec.add(results[1])


def test_failed_close_keeps_old_file_and_no_temp(tmp_path, monkeypatch):
    out = tmp_path / "b.rrd"
    out.write_bytes(b"previous")
    info, results = make_results()
    rec = SceneRecorder(out)
    rec.begin(info)
    for r in results:
        rec.add(r)

    def boom(*args, **kwargs):
        raise OSError("simulated disk failure")

    monkeypatch.setattr("rerun.RecordingStream.send_columns", boom)
    with pytest.raises(RecordingError, match="simulated disk failure"):
        rec.close()
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.rrd"]


def test_missing_folder_fails_at_begin(tmp_path):
    rec = SceneRecorder(tmp_path / "nope" / "c.rrd")
    with pytest.raises(RecordingError, match="does not exist"):
        rec.begin(scene_info(0))


def test_add_before_begin_and_bad_shapes(tmp_path):
    info, results = make_results()
    rec = SceneRecorder(tmp_path / "d.rrd")
    with pytest.raises(RecordingError, match="begin"):
        rec.add(results[0])
    rec.begin(info)
    bad = FrameResult(
        index=0, frame=results[0].frame, risks={"near": np.zeros(2)}, cascade=results[0].cascade
    )
    with pytest.raises(RecordingError, match="no risk for model"):
        rec.add(bad)
    risks = dict(results[0].risks, wide=np.zeros(3))
    with pytest.raises(RecordingError, match="risk of wide has shape"):
        rec.add(
            FrameResult(index=0, frame=results[0].frame, risks=risks, cascade=results[0].cascade)
        )


def test_bad_label_mode():
    with pytest.raises(RecordingError, match="labels must be one of"):
        SceneRecorder("x.rrd", labels="some")  # type: ignore[arg-type]


def test_scene_without_frames_still_opens(tmp_path):
    out = tmp_path / "empty.rrd"
    rec = SceneRecorder(out)
    rec.begin(scene_info(4))
    rec.close()
    ents = read_rrd(out)
    assert L.MAP_LANES in ents and L.SUMMARY in ents
    assert "frames recorded | 0 of 4 (skipped: 4)" in ents[L.SUMMARY].static["text"][0]


# ---------------------------------------------------------------------- layout maths
def test_capsule_geometry_by_hand():
    strips, radii = L.capsules(
        np.array([[1.0, 2.0]]), np.array([0.0]), np.array([4.5]), np.array([1.8])
    )
    # Segment length L - W = 2.7 m, radius W / 2: the stadium is exactly 4.5 x 1.8 m.
    np.testing.assert_allclose(strips[0], [[-0.35, 2.0], [2.35, 2.0]])
    np.testing.assert_allclose(radii, [0.9])
    strips, radii = L.capsules(
        np.zeros((1, 2)), np.array([math.pi / 2]), np.array([0.5]), np.array([0.6])
    )
    assert np.linalg.norm(strips[0, 1] - strips[0, 0]) == pytest.approx(2e-3)  # a disc
    np.testing.assert_allclose(radii, [0.3])


def test_outline_corners_by_hand():
    box = L.outlines(
        np.array([[10.0, 0.0]]), np.array([math.pi / 2]), np.array([4.0]), np.array([2.0]), 0.5
    )
    # Heading north: the 5 m long side runs along y, the 3 m side along x.
    np.testing.assert_allclose(
        box[0, :4], [[8.5, 2.5], [8.5, -2.5], [11.5, -2.5], [11.5, 2.5]], atol=1e-12
    )


def test_scene_bounds_flip_y_and_have_a_minimum_size():
    x, y = L.scene_bounds(
        np.array([[0.0, 100.0], [10.0, 110.0]]), margin_m=0.0, min_size_m=60.0, aspect=1.0
    )
    assert x == pytest.approx((-25.0, 35.0))
    assert y == pytest.approx((-135.0, -75.0))  # view space: y = -north
    x, y = L.scene_bounds(
        np.array([[0.0, 100.0], [10.0, 110.0]]), margin_m=0.0, min_size_m=60.0, aspect=2.0
    )
    assert x == pytest.approx((-55.0, 65.0))  # widened to the view's aspect
    assert y == pytest.approx((-135.0, -75.0))


def test_scene_bounds_stay_near_the_ego_when_survivors_spread():
    pts = np.array([[-200.0, 0.0], [200.0, 0.0], [0.0, 5.0]])
    ego = np.array([[0.0, -10.0], [0.0, 10.0]])
    x, y = L.scene_bounds(pts, ego, margin_m=0.0, min_size_m=10.0, max_size_m=100.0, aspect=1.0)
    assert x == pytest.approx((-50.0, 50.0))
    assert y == pytest.approx((-52.5, 47.5))  # y was narrow: its own centre, widened


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(min_value=-40, max_value=3, allow_nan=False), min_size=2, max_size=20),
)
def test_risk_colors_monotone_in_survival(log_r):
    r = np.sort(10.0 ** np.array(log_r))
    colors = L.risk_colors(r, 1e-25).astype(int)
    # Riskier -> more saturated red: green and blue never rise, red never rises either
    # (RISK_HIGH is a darker, deeper red than the pale RISK_LOW).
    assert np.all(np.diff(colors[:, 1]) <= 0) and np.all(np.diff(colors[:, 2]) <= 0)
    assert np.all(colors[:, 0] >= colors[:, 1])
    assert np.all(colors[r <= 1e-25] == L.RISK_LOW)
    assert np.all(colors[r >= 1.0] == L.RISK_HIGH)


def test_series_colors_stable_per_id():
    a = L.agent_series_colors(np.array([1, 2, 3, 1]))
    np.testing.assert_array_equal(a[0], a[3])
    assert not np.array_equal(a[0], a[1])
    assert a.dtype == np.uint8 and a.shape == (4, 3)


# ---------------------------------------------------------------------- a real replay
class _Keep:
    """A sink that keeps the engine's results, to compare with what was recorded."""

    def __init__(self) -> None:
        self.results: list[FrameResult] = []

    def begin(self, info) -> None:
        self.info = info

    def add(self, result) -> None:
        self.results.append(result)

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


def test_synthetic_replay_round_trip(tmp_path):
    """The engine on a small synthetic intersection: every timeline value comes back."""
    from converters.synthetic import SyntheticSettings, generate_scene
    from replay.core.engine import run_scene

    scene = generate_scene(SyntheticSettings(n_agents=12, duration_s=1.5), seed=3)
    keep, out = _Keep(), tmp_path / "synthetic.rrd"
    summary = run_scene(scene, sinks=[keep, SceneRecorder(out)], progress=False)
    assert out in summary.outputs
    ents = read_rrd(out)
    times = [r.frame.t for r in keep.results]
    for model in keep.info.model_names:
        for agent in (1, 5, 11):
            expected = []
            for r in keep.results:
                hit = np.flatnonzero((r.frame.ids == agent) & r.frame.valid)
                expected.append(r.risks[model][hit[0]] if hit.size else np.nan)
            ent = ents[L.risk_path(model, agent)]
            present = np.flatnonzero(~np.isnan(expected))
            span = slice(present[0], present[-1] + 1)
            assert ent.times_s() == pytest.approx(times[span])
            np.testing.assert_array_equal(scalars(ent), np.array(expected)[span])
    for s, stage in enumerate(keep.info.cascade.stages):
        funnel = scalars(ents[f"{L.FUNNEL}/{L.stage_key(s, stage.model)}"])
        np.testing.assert_array_equal(funnel, [r.cascade.n_kept[s] for r in keep.results])
    for r_index, r in enumerate(keep.results):  # every valid other agent has a body
        for agent in r.frame.ids[r.frame.others]:
            strips = ents[L.body_path(int(agent))].column("strips", rows_with="strips")
            assert len(strips[r_index]) >= 2
