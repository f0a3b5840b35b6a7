"""Issue 28: planner truth beside hindsight, complete windows, the yielded label, track
consistency, budgets and every reference in ``replay evaluate``."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st
from planner_scenes import BEHIND, PARKED_OFF_ROAD, STOPPED, road_map, yielding_road_scene

from replay.analysis.evaluation.corpus import EvaluationSettings, evaluate_table
from replay.cli.app import main
from replay.core.engine import run_scene
from replay.core.tables import TableSink
from replay.planning.annotator import PlannerAnnotator
from replay.planning.idm import IdmPlanner
from replay.planning.inputs import plan_request
from replay.planning.registry import make_planner
from replay.planning.truth import planner_truth
from risk.budgets import budget_recall, ranks_in_situation
from risk.frame import Frame
from risk.hindsight import (
    HindsightSettings,
    inconsistent_steps,
    rows_truth,
    tracks_from_states,
)


# ---------------------------------------------------------------------- the road
@pytest.fixture(scope="module")
def yield_table() -> pl.DataFrame:
    """The yielding road replayed at 1 Hz with idm planner truth beside the engine."""
    table = TableSink(None)
    run_scene(
        yielding_road_scene(), sinks=[table], progress=False, every=10,
        annotators=[PlannerAnnotator(make_planner("idm"), truth=True)],
    )  # fmt: skip
    return table.dataframe()


def test_the_standing_car_is_planner_important_a_hindsight_negative_and_yielded_to(yield_table):
    first = yield_table.filter(pl.col("frame") == 0)
    stopped = first.filter(pl.col("agent_id") == STOPPED).row(0, named=True)
    assert stopped["planner_label"] is True  # removing it changes the plan
    assert stopped["truth_complete"] is True  # the whole 5 s are recorded
    assert stopped["truth_label"] is False  # the ego stopped 3.5 m short: never close
    assert stopped["truth_gap_m"] > 3.0
    assert stopped["truth_yielded"] is True  # ... because the ego braked for it
    # Every complete window from the start while the ego is still braking says the same.
    early = yield_table.filter((pl.col("agent_id") == STOPPED) & (pl.col("frame") <= 40))
    assert early["planner_label"].all() and early["truth_yielded"].all()
    assert not early["truth_label"].any()


@pytest.mark.parametrize("agent", [PARKED_OFF_ROAD, BEHIND])
def test_a_car_parked_off_the_road_and_a_slower_car_behind_are_neither(yield_table, agent):
    rows = yield_table.filter(pl.col("agent_id") == agent)
    assert rows.height > 0
    assert not rows["planner_label"].fill_null(True).any()
    assert not rows["truth_yielded"].any()
    assert not rows["truth_label"].fill_null(False).any()  # negative or unknown, never close
    assert (rows["truth_label"] == False).sum() >= 5  # noqa: E712  (complete windows: negative)
    assert rows["track_ok"].all()


# ---------------------------------------------------------------------- tracks
def _pedestrian(jump_at: int | None, *, n: int = 60, kind: int = 1, speed: float = 1.0):
    """One agent walking along +x at ``speed`` m/s at 10 Hz (and an ego standing far
    off); with ``jump_at`` its track jumps 75 m forward at that frame."""
    frames = np.arange(n)
    x = speed * 0.1 * frames
    if jump_at is not None:
        x[jump_at:] += 75.0
    fi = np.r_[frames, frames]
    ids = np.r_[np.zeros(n, int), np.ones(n, int)]
    xy = np.r_[np.stack([np.full(n, -50.0), np.full(n, 40.0)], 1), np.stack([x, np.zeros(n)], 1)]
    kinds = np.r_[np.zeros(n, int), np.full(n, kind)]
    return tracks_from_states(
        fi, ids, kinds, xy, np.zeros(2 * n), np.full(2 * n, 1.0), np.full(2 * n, 1.0),
        t0_s=0.0, dt_s=0.1,
    )  # fmt: skip


def test_a_teleport_is_flagged_and_kept_out_of_the_truth():
    n, jump = 160, 100
    tracks = _pedestrian(jump_at=jump, n=n)
    bad = inconsistent_steps(tracks)
    agent = int(np.flatnonzero(tracks.ids == 1)[0])
    assert bad[jump, agent]  # 75 m in 0.1 s
    assert not bad[: jump - 5, agent].any()  # walking at 1 m/s is fine
    assert not bad[jump + 6 :, agent].any()  # and again once the jump is behind
    assert not bad[:, 1 - agent].any()  # the standing ego
    t = np.arange(n) * 0.1
    rows = rows_truth(tracks, t, np.zeros(n, int), np.ones(n, int))
    h = HindsightSettings().horizon_steps(0.1)
    # Windows that reach the jump are flagged; those that end before it are not.
    assert not rows.track_ok[jump - h : jump + 1].any()
    assert rows.track_ok[: jump - h - 5].all()
    assert rows.track_ok[jump + 6 :].all()
    assert (rows.label[~rows.track_ok] == -1).all()  # unknown: out of the truth
    assert (rows.label[: jump - h - 5] == 0).all()  # the ego is far off: negatives


def test_a_fast_car_is_not_a_teleport_but_a_fast_pedestrian_is():
    car = _pedestrian(jump_at=None, kind=0, speed=30.0)
    walker = _pedestrian(jump_at=None, kind=1, speed=30.0)
    col = int(np.flatnonzero(car.ids == 1)[0])
    assert not inconsistent_steps(car)[:, col].any()
    assert inconsistent_steps(walker)[1:, col].all()


# ---------------------------------------------------------------------- budgets
def test_recall_at_k_by_hand():
    # Situation 0: scores 0.9, 0.1, 0.5 (positives: the 0.1 and the 0.5 agent);
    # situation 1: scores 0.3, 0.8 (positive: the 0.3 agent).
    scores = np.array([0.9, 0.1, 0.5, 0.3, 0.8])
    sit = np.array([0, 0, 0, 1, 1])
    ref = np.array([0, 1, 1, 1, 0], dtype=np.int8)
    dist = np.array([5.0, 12.0, 30.0, 8.0, 2.0])
    rows = budget_recall(
        {"m": scores}, ref, situations=sit, codes=np.zeros(5, int), distance_m=dist,
        kept_sets={"cascade": np.array([True, True, False, False, True])},
        budgets=(1, 2, 4), radii_m=(10.0, 15.0),
    )  # fmt: skip
    got = {(r["rule"], r["k"], r["radius_m"]): (r["value"], r["mean_kept"]) for r in rows}
    # K = 1 keeps 0.9 and 0.8: no positive. K = 2 adds 0.5 and 0.3: 2 of 3. K = 4: all.
    assert got[("m", 1, None)] == (0.0, 1.0)
    assert got[("m", 2, None)] == (pytest.approx(2 / 3), 2.0)
    assert got[("m", 4, None)] == (1.0, 2.5)  # min(4, 3) and min(4, 2)
    # Nearest: K = 1 keeps 5 m and 2 m (no positive); K = 2 adds 12 m and 8 m: 2 of 3.
    assert got[("nearest", 1, None)][0] == 0.0
    assert got[("nearest", 2, None)][0] == pytest.approx(2 / 3)
    # Radius 10 m: 5, 8, 2 m kept (one positive, the 8 m one); 15 m adds the 12 m one.
    assert got[("radius", None, 10.0)] == (pytest.approx(1 / 3), 1.5)
    assert got[("radius", None, 15.0)] == (pytest.approx(2 / 3), 2.0)
    # The cascade's fixed set keeps the 0.1 agent only among the positives.
    assert got[("cascade", None, None)] == (pytest.approx(1 / 3), 1.5)


def test_recall_of_a_reference_without_positives_is_nan_not_an_error():
    rows = budget_recall(
        {"m": np.array([1.0, 2.0])}, np.array([0, -1], dtype=np.int8),
        situations=np.array([0, 0]), codes=np.zeros(2, int), budgets=(1,),
    )  # fmt: skip
    assert rows[0]["positives"] == 0 and math.isnan(rows[0]["value"])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.floats(-5, 5) | st.just(float("nan"))),
                min_size=1, max_size=30))  # fmt: skip
def test_ranks_match_a_plain_loop(rows):
    sit = np.array([r[0] for r in rows])
    s = np.array([r[1] for r in rows])
    got = ranks_in_situation(s, sit)
    for i in range(len(rows)):
        same = [j for j in range(len(rows)) if sit[j] == sit[i]]
        key = [(math.inf if math.isnan(s[j]) else -s[j], j) for j in same]
        order = [j for _, j in sorted(key)]
        assert got[i] == order.index(i)


# ---------------------------------------------------------------------- evaluation
def _table(rows: list[dict]) -> pl.DataFrame:
    base = {"scene": "s", "ego_id": 0, "kind": "vehicle", "truth_pet_s": None}
    df = pl.DataFrame([{**base, **r} for r in rows])
    return df.with_columns(
        pl.col("truth_label").cast(pl.Boolean), pl.col("truth_gap_m").cast(pl.Float64),
        pl.col("truth_pet_s").cast(pl.Float64),
    )  # fmt: skip


CENSORING_ROWS = [
    # A censored positive (came close in the recorded part of a cut-off window) ...
    {"frame": 0, "t_s": 0.0, "agent_id": 1, "risk_current_distance": 0.9, "risk_survival": 1.0,
     "truth_gap_m": 0.2, "truth_label": True, "truth_complete": False},
    # ... and three complete windows: one positive, two negatives.
    {"frame": 1, "t_s": 0.1, "agent_id": 2, "risk_current_distance": 0.5, "risk_survival": 1.0,
     "truth_gap_m": 0.3, "truth_label": True, "truth_complete": True},
    {"frame": 1, "t_s": 0.1, "agent_id": 3, "risk_current_distance": 0.7, "risk_survival": 0.0,
     "truth_gap_m": 4.0, "truth_label": False, "truth_complete": True},
    {"frame": 1, "t_s": 0.1, "agent_id": 4, "risk_current_distance": 0.2, "risk_survival": 0.0,
     "truth_gap_m": 9.0, "truth_label": False, "truth_complete": True},
]  # fmt: skip


def test_the_censoring_rule_changes_the_auc_by_hand():
    df = _table(CENSORING_ROWS)
    opts = {"models": ("current_distance",), "n_boot": 0, "groupings": ()}
    complete = evaluate_table(df, settings=EvaluationSettings(**opts))
    any_ = evaluate_table(df, settings=EvaluationSettings(**opts, hindsight_windows="any"))
    # Any window: positives 0.9, 0.5; negatives 0.7, 0.2. Pairs ranked right: 0.9 > 0.7,
    # 0.9 > 0.2, 0.5 > 0.2, not 0.5 > 0.7: AUC 3/4.
    assert any_["models"]["current_distance"]["hindsight"]["auc"]["value"] == pytest.approx(0.75)
    # Complete windows: the censored positive is out; 0.5 against 0.7 and 0.2: AUC 1/2.
    auc = complete["models"]["current_distance"]["hindsight"]["auc"]["value"]
    assert auc == pytest.approx(0.5)
    # The other rule is reported beside it.
    other = complete["models"]["current_distance"]["hindsight_any"]["auc"]["value"]
    assert other == pytest.approx(0.75)
    assert complete["composition"]["hindsight"]["positive"]["agent_frames"] == 1
    assert complete["composition"]["hindsight_any"]["positive"]["agent_frames"] == 2


def test_a_table_without_planner_columns_names_what_it_lacks():
    summary = evaluate_table(
        _table(CENSORING_ROWS),
        settings=EvaluationSettings(models=("current_distance",), n_boot=0, groupings=()),
    )
    assert "planner" in summary["references_missing"]
    assert "planner" not in summary["reference_names"]
    assert set(summary["reference_names"]) == {"survival", "hindsight", "hindsight_any"}


def test_a_reference_without_positives_is_reported_not_a_nan():
    df = _table(CENSORING_ROWS).with_columns(
        pl.lit(False).alias("planner_label"), pl.lit(0.0).alias("planner_shift_m"),
        pl.Series("label_focal", [True, False, False, False]),
    )  # fmt: skip
    summary = evaluate_table(
        df, settings=EvaluationSettings(models=("current_distance",), n_boot=0, groupings=())
    )
    assert "no positive among 4 agent-frames" in summary["references_without_positives"]["planner"]
    assert "planner" not in summary["models"]["current_distance"]
    assert "planner" not in summary["budgets"]
    # The dataset's own labels are a reference of their own.
    assert summary["models"]["current_distance"]["dataset_focal"]["auc"]["value"] == 1.0


def test_agreement_counts_planner_important_hindsight_negatives_the_ego_yielded_to():
    df = _table(CENSORING_ROWS).with_columns(
        pl.Series("planner_label", [False, True, True, False]),
        pl.Series("truth_yielded", [False, False, True, False]),
        pl.lit(True).alias("track_ok"),
    )  # fmt: skip
    summary = evaluate_table(
        df, settings=EvaluationSettings(models=("current_distance",), n_boot=0, groupings=())
    )
    block = summary["agreement"]["planner"]["hindsight"]
    assert summary["agreement"]["planner"]["important"]["agent_frames"] == 2
    assert block["positive"]["agent_frames"] == 1  # agent 2
    assert block["negative"]["agent_frames"] == 1  # agent 3, which the ego yielded to
    assert block["negative_yielded"]["agent_frames"] == 1
    pair = next(
        p for p in summary["agreement"]["pairs"] if (p["a"], p["b"]) == ("hindsight", "planner")
    )
    assert pair["counts"]["negative/positive"] == 1
    assert pair["counts"]["unknown/negative"] == 1  # the censored positive of agent 1


def test_evaluate_with_a_planner_on_the_yielding_road(tmp_path):
    from converters.scene.writer import write_scene  # the scene file for the CLI

    folder = tmp_path / "road"
    folder.mkdir()
    write_scene(folder / "road.mcap", yielding_road_scene())
    out = tmp_path / "out"
    r = CliRunner().invoke(
        main,
        ["evaluate", str(folder), "-o", str(out), "--planner", "idm", "--every", "1s",
         "--bootstrap", "5", "--workers", "1", "--no-progress", "--no-plots",
         "--report", str(tmp_path / "report.md"), "--report-note", "Made by hand."],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert "planner" in summary["reference_names"]
    planner = summary["agreement"]["planner"]
    assert planner["important"]["agents"] == 1  # the standing car only
    assert planner["hindsight"]["negative_yielded"]["agent_frames"] >= 1
    budgets = pl.read_parquet(out / "budgets.parquet")
    assert set(budgets["reference"]) >= {"planner", "survival"}
    report = (tmp_path / "report.md").read_text()
    assert "- Made by hand." in report
    assert "planner idm" in report and "**Yielded count:**" in report


def test_an_unknown_planner_is_a_one_line_error(tmp_path):
    r = CliRunner().invoke(
        main, ["evaluate", str(tmp_path), "-o", str(tmp_path / "o"), "--planner", "nope"]
    )
    assert r.exit_code != 0
    assert r.output.startswith("Error: ") and r.output.count("\n") == 1, r.output


# ---------------------------------------------------------------------- the IDM skip
class _EveryAgent(IdmPlanner):
    """The IDM planner without its sole-constraint report: planner truth then plans
    without every agent that may matter (the slow, obvious oracle)."""

    def plan(self, request):
        return dataclasses.replace(super().plan(request), sole_constraints=None)


@settings(max_examples=25, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-30, 120), st.sampled_from([0.0, 3.5, -6.0]), st.floats(0, 15),
                  st.sampled_from([0.0, np.pi, np.pi / 2])),
        min_size=1, max_size=8,
    ),
    st.floats(0, 15),
)  # fmt: skip
def test_idm_sole_constraints_skip_exactly_the_agents_that_cannot_change_the_plan(agents, v):
    n = len(agents) + 1
    xy = np.array([(0.0, 0.0), *((x, y) for x, y, _, _ in agents)])
    heading = np.array([0.0, *(h for *_, h in agents)])
    speed = np.array([v, *(s for _, _, s, _ in agents)])
    paths = [
        np.array([p, p + 300 * np.array([np.cos(h), np.sin(h)])])
        for p, h in zip(xy, heading, strict=True)
    ]
    frame = Frame.from_arrays(
        xy, heading, speed, np.full(n, 4.5), np.full(n, 1.8), paths, ego=0, ids=np.arange(n)
    )
    request = plan_request(frame, road_map(), target_speed_mps=12.0, horizon_s=5.0, dt_s=0.1)
    fast, slow = IdmPlanner(), _EveryAgent()
    a = planner_truth(fast, request, fast.plan(request))
    b = planner_truth(slow, request, slow.plan(request))
    np.testing.assert_array_equal(a.label, b.label)
    np.testing.assert_allclose(a.shift_m, b.shift_m)
    assert a.plans <= b.plans


def test_idm_sole_constraints_on_the_road_label_the_standing_car_with_one_plan():
    from planner_scenes import road_frame

    request = plan_request(road_frame(), road_map(), target_speed_mps=10.0, horizon_s=5.0, dt_s=0.1)
    planner = IdmPlanner()
    reference = planner.plan(request)
    assert list(reference.sole_constraints) == [STOPPED]
    truth = planner_truth(planner, request, reference)
    assert truth.plans == 1
    assert truth.label[list(truth.ids).index(STOPPED)] == 1.0
    assert truth.label.sum() == 1.0


def test_dataset_labels_are_references_and_path_source_lists_are_not(yield_table):
    from replay.analysis.evaluation.corpus import reference_arrays

    n = yield_table.height
    table = yield_table.with_columns(
        pl.Series("label_objects_of_interest", [True] + [False] * (n - 1)),
        pl.Series("label_paths_lane_graph", [True] * n),
    )
    refs, missing = reference_arrays(table, baseline_threshold=1e-25, windows="complete")
    assert "dataset_objects_of_interest" in refs
    assert "dataset_paths_lane_graph" not in refs
    assert "dataset labels" not in missing
    refs, missing = reference_arrays(
        yield_table.with_columns(pl.Series("label_paths_straight", [True] * n)),
        baseline_threshold=1e-25, windows="complete",
    )  # fmt: skip
    assert not any(r.startswith("dataset_") for r in refs) and "dataset labels" in missing
