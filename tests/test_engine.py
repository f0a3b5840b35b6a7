"""The replay engine and the table sink, on small in-memory scenes."""

from __future__ import annotations

import warnings

import numpy as np
import polars as pl
import pytest

import replay.core.engine as engine
from replay.core.engine import FrameResult, ReplayWarning, SceneInfo, run_scene
from replay.core.tables import TableSink
from replay.errors import ReplayError
from risk.cascade import CascadeConfig, Stage, Tier
from risk.frame import Frame, Lane, LaneMap, Scene

MODEL_NAMES = ("current_distance", "path_distance", "trajectory_distance", "gaussian", "survival")
CONFIG = CascadeConfig(
    stages=(Stage("path_distance", 0.1), Stage("gaussian", 0.2)),
    tiers=(Tier("behavior", 1e-25), Tier("interactive", 0.3, 2), Tier("cooperative", 0.6, 1)),
)


def distance_evaluator(calls: list | None = None):
    """A stand-in for ``risk.evaluate`` whose every model is ``1 / (1 + d)`` of the current
    distance to the ego, scaled per model, so that values are known by hand."""
    scale = {m: 1.0 + 0.1 * k for k, m in enumerate(MODEL_NAMES)}

    def evaluate(frame, models=None, params=None, *, prediction=None):
        if calls is not None:
            calls.append((tuple(models), frame.n_agents))
        d = np.linalg.norm(frame.xy - frame.xy[frame.ego], axis=1)
        out = {}
        for m in models:
            r = 1.0 / (1.0 + d) / scale[m]
            r[~frame.others] = np.nan
            out[m] = r
        return out

    return evaluate


def make_frame(t: float, xs: list[float], ids: list[int], ego: int, valid=None) -> Frame:
    xy = np.c_[np.asarray(xs, dtype=float), np.zeros(len(xs))]
    paths = [np.array([p, p + np.array([1.0, 0.0])]) for p in xy]
    n = len(xs)
    return Frame.from_arrays(
        xy, np.zeros(n), np.ones(n), np.full(n, 4.0), np.full(n, 2.0), paths, ego,
        ids=ids, valid=valid, t=t, kinds=["vehicle"] * (n - 1) + ["pedestrian"],
    )  # fmt: skip


def make_scene(with_missing_ego: bool = False) -> Scene:
    frames = [
        make_frame(0.0, [0.0, 1.0, 5.0, 20.0], [7, 1, 2, 3], ego=0),
        make_frame(0.1, [0.0, 2.0, 4.0, 30.0], [7, 1, 2, 3], ego=0),
        make_frame(0.2, [0.0, 3.0, 3.0], [7, 1, 2], ego=0),
    ]
    if with_missing_ego:
        # Frame 1: the ego (7) is present but invalid, so the frame is seen from agent 1.
        frames[1] = make_frame(0.1, [0.0, 2.0, 4.0, 30.0], [7, 1, 2, 3], ego=1,
                               valid=[False, True, True, True])  # fmt: skip
    lane = Lane(id=1, centerline=np.array([[0.0, 0.0], [50.0, 0.0]]))
    return Scene(
        map=LaneMap((lane,)), frames=frames, frame_period_s=0.1, metadata={"source": "test"}
    )


class ListSink:
    """Records what the engine hands to a sink."""

    def __init__(self, fail_at: int | None = None):
        self.info: SceneInfo | None = None
        self.results: list[FrameResult] = []
        self.events: list[str] = []
        self.fail_at = fail_at

    def begin(self, info):
        self.info = info
        self.events.append("begin")

    def add(self, result):
        if self.fail_at is not None and len(self.results) == self.fail_at:
            raise OSError("disk full")
        self.results.append(result)
        self.events.append("add")

    def close(self):
        self.events.append("close")

    def abort(self):
        self.events.append("abort")


@pytest.fixture(autouse=True)
def registry(monkeypatch):
    """The engine validates model names against ``risk.MODELS``; make sure ours are in it
    (the real registry has them all)."""
    import risk

    if not hasattr(risk, "MODELS"):
        monkeypatch.setattr(risk, "MODELS", dict.fromkeys(MODEL_NAMES), raising=False)


def run(scene, **kwargs):
    kwargs.setdefault("models", MODEL_NAMES)
    kwargs.setdefault("cascade", CONFIG)
    kwargs.setdefault("evaluate", distance_evaluator())
    return run_scene(scene, progress=False, **kwargs)


def test_every_frame_reaches_every_sink_with_all_risks():
    a, b = ListSink(), ListSink()
    summary = run(make_scene(), sinks=[a, b])
    assert a.events == ["begin", "add", "add", "add", "close"] == b.events
    assert a.info.ego_id == 7 and a.info.model_names == MODEL_NAMES and a.info.n_frames == 3
    assert a.info.frame_period_s == 0.1 and a.info.metadata == {"source": "test"}
    first = a.results[0]
    assert first.index == 0 and list(first.risks) == list(MODEL_NAMES)
    # Frame 0: distances 1, 5, 20 -> path_distance risk 1/2/1.1, 1/6/1.1, 1/21/1.1.
    np.testing.assert_allclose(
        first.risks["path_distance"], [np.nan, 1 / 2 / 1.1, 1 / 6 / 1.1, 1 / 21 / 1.1]
    )
    # The survival timeline is the cascade's survival on all agents.
    np.testing.assert_array_equal(first.risks["survival"], first.cascade.survival_all)
    # Stage 0 (>= 0.1) drops agent 3 (0.043); stage 1 gaussian (scale 1.3, >= 0.2) keeps
    # agent 1 (0.385) and drops agent 2 (0.128).
    np.testing.assert_array_equal(first.cascade.kept, [[0, 1, 1, 0], [0, 1, 0, 0]])
    assert summary.frames == 3 and summary.skipped_frames == 0
    assert summary.agents == 4
    assert summary.mean_others == pytest.approx((3 + 3 + 2) / 3)
    assert summary.stage_names == ("path_distance", "gaussian")
    assert len(summary.mean_kept) == 2 and summary.mean_kept[0] >= summary.mean_kept[1]


def test_summary_false_negatives_add_up_over_frames():
    sink = ListSink()
    summary = run(make_scene(), sinks=[sink])
    fn = np.sum([r.cascade.false_negatives for r in sink.results], axis=0)
    assert summary.false_negatives == tuple(fn)
    assert summary.baseline_agents == sum(int(r.cascade.baseline.sum()) for r in sink.results)
    # Every other agent has a positive survival risk here, so all are baseline-important.
    assert summary.baseline_agents == 8
    kept = np.mean([r.cascade.n_kept for r in sink.results], axis=0)
    np.testing.assert_allclose(summary.mean_kept, kept)
    assert summary.cascade_time_s >= sum(summary.stage_time_s) + summary.sort_time_s


def test_frames_without_the_ego_are_skipped_with_a_warning():
    sink = ListSink()
    with pytest.warns(ReplayWarning, match=r"1 frame\(s\) skipped .*id 7.*frames 1\)"):
        summary = run(make_scene(with_missing_ego=True), sinks=[sink])
    assert [r.index for r in sink.results] == [0, 2]
    assert summary.frames == 2 and summary.skipped_frames == 1


def test_another_ego_sees_the_scene_from_that_agent():
    sink = ListSink()
    summary = run(make_scene(), sinks=[sink], ego=2)
    assert summary.ego_id == 2
    assert all(r.frame.ego_id == 2 for r in sink.results)
    # Frame 0 from agent 2 (x = 5): agent 1 at distance 4, the old ego 7 at 5.
    np.testing.assert_allclose(sink.results[0].risks["current_distance"][:2], [1 / 6, 1 / 5])


def test_an_ego_missing_in_some_frames_is_skipped_there():
    sink = ListSink()
    with pytest.warns(ReplayWarning, match="1 frame"):
        summary = run(make_scene(), sinks=[sink], ego=3)  # agent 3 leaves in frame 2
    assert [r.index for r in sink.results] == [0, 1] and summary.skipped_frames == 1


def test_unknown_ego_is_an_error_listing_valid_ids_and_aborts_sinks():
    sink = ListSink()
    with pytest.raises(ReplayError, match=r"agent id 99 is not .* valid ids include 1, 2, 3, 7"):
        run(make_scene(), sinks=[sink], ego=99)
    assert sink.events[0] == "begin" and sink.events[-1] == "abort"
    assert "close" not in sink.events


def test_a_failing_sink_aborts_every_sink():
    good, bad = ListSink(), ListSink(fail_at=1)
    with pytest.raises(OSError, match="disk full"):
        run(make_scene(), sinks=[good, bad])
    assert good.events[-1] == "abort" and bad.events[-1] == "abort"
    assert "close" not in good.events


def test_the_cascade_runs_its_stages_on_survivors_only():
    calls: list = []
    run(make_scene(), evaluate=distance_evaluator(calls))
    frame0 = calls[:5]
    # One call for the timeline models on all 4 agents, survival on all 4, then the
    # stages on shrinking sub-frames (ego + 3, ego + 2), then survival on ego + 1.
    assert frame0 == [
        (("current_distance", "path_distance", "trajectory_distance", "gaussian"), 4),
        (("survival",), 4),
        (("path_distance",), 4),
        (("gaussian",), 3),
        (("survival",), 2),
    ]


# ---------------------------------------------------------------------- table sink
@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_table_has_one_row_per_frame_and_other_agent(tmp_path, suffix):
    path = tmp_path / f"out{suffix}"
    table = TableSink(path)
    sink = ListSink()
    with pytest.warns(ReplayWarning):
        run(make_scene(with_missing_ego=True), sinks=[table, sink])
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temp file left
    df = pl.read_parquet(path) if suffix == ".parquet" else pl.read_csv(path)
    assert df.columns == [
        "frame", "t_s", "ego_id", "agent_id", "kind", "x_m", "y_m", "speed_mps",
        *(f"risk_{m}" for m in MODEL_NAMES),
        "kept_path_distance", "kept_gaussian", "dropped_by", "tier", "baseline",
        "truth_gap_m", "truth_pet_s", "truth_label",
    ]  # fmt: skip
    # A 3-frame scene is far shorter than the 5 s hindsight horizon: no negative label.
    assert not (df["truth_label"] == False).any()  # noqa: E712
    # Frames 0 and 2 processed (1 skipped): 3 + 2 other agents.
    assert df.height == 5
    assert df["frame"].to_list() == [0, 0, 0, 2, 2]
    assert df["agent_id"].to_list() == [1, 2, 3, 1, 2]
    assert df["kind"].to_list() == ["vehicle", "vehicle", "pedestrian", "vehicle", "pedestrian"]
    first = sink.results[0]
    np.testing.assert_allclose(df["risk_gaussian"][:3].to_numpy(), first.risks["gaussian"][1:])
    assert df["dropped_by"][:3].to_list() == [None, "gaussian", "path_distance"]
    assert df["kept_path_distance"][:3].to_list() == [True, True, False]
    # Agent 1 (the only survivor of frame 0, survival risk 1/2/1.4 = 0.357): behavior and
    # interactive (>= 0.3) but not cooperative (>= 0.6).
    assert df["tier"][:3].to_list() == ["interactive", None, None]
    assert df["baseline"].all()


def test_table_rejects_unknown_suffix_and_missing_folder(tmp_path):
    with pytest.raises(ReplayError, match=r"\.parquet or \.csv"):
        TableSink(tmp_path / "out.xlsx")
    with pytest.raises(ReplayError, match="does not exist"):
        TableSink(tmp_path / "nowhere" / "out.csv")


def test_table_is_not_written_when_the_run_fails(tmp_path):
    path = tmp_path / "out.parquet"
    with pytest.raises(OSError):
        run(make_scene(), sinks=[TableSink(path), ListSink(fail_at=2)])
    assert list(tmp_path.iterdir()) == []


def test_no_warning_without_skipped_frames():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        run(make_scene())


# ---------------------------------------------------------------------- from a file
def write_mcap(path, scene: Scene, *, ego_less: tuple[int, ...] = ()) -> None:
    """Write ``scene``; frames in ``ego_less`` name agent 7 as ego although it is invalid
    there, which readers report as frames without their ego."""
    from converters.scene.writer import SceneWriter

    with SceneWriter(path, scene.map, frame_period_s=scene.frame_period_s,
                     metadata=scene.metadata) as writer:  # fmt: skip
        for k, frame in enumerate(scene.frames):
            writer.add_frame(frame, ego_id=7 if k in ego_less else None)


def test_run_scene_reads_an_mcap_file_and_skips_ego_less_frames(tmp_path):
    path = tmp_path / "scene.mcap"
    write_mcap(path, make_scene(with_missing_ego=True), ego_less=(1,))
    sink = ListSink()
    with pytest.warns(ReplayWarning, match=r"1 frame\(s\) skipped"):
        summary = run(path, sinks=[sink])
    assert summary.source == path and sink.info.source == path
    assert sink.info.ego_id == 7 and sink.info.n_frames == 3
    assert [r.index for r in sink.results] == [0, 2]
    assert summary.frames == 2 and summary.skipped_frames == 1
    # Stored in millimetres: the same risks as the in-memory scene.
    memory = ListSink()
    with pytest.warns(ReplayWarning):
        run(make_scene(with_missing_ego=True), sinks=[memory])
    for a, b in zip(sink.results, memory.results, strict=True):
        for m in MODEL_NAMES:
            np.testing.assert_allclose(a.risks[m], b.risks[m], rtol=1e-9)


def test_kernels_are_loaded_before_the_first_frame_is_timed(monkeypatch):
    # Loading a compiled kernel from the cache takes tens of ms on its first call in a
    # process; done inside frame 0 it showed as a spike in every stage's compute time.
    order: list[str] = []
    monkeypatch.setattr(engine, "warm_up", lambda: order.append("warm_up"))

    class Recording(ListSink):
        def begin(self, info):
            order.append("begin")
            super().begin(info)

        def add(self, result):
            order.append("frame")
            super().add(result)

    run(make_scene(), sinks=[Recording()])
    # The sinks begin first: a background recorder starts its process there, so that it
    # imports rerun while the kernels load.
    assert order[:3] == ["begin", "warm_up", "frame"] and order.count("warm_up") == 1
