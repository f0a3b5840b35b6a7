"""The safety verdict of a filtered plan (issue 37): checked against every agent, the
dropped ones included; and ``changed_1s``."""

from __future__ import annotations

import numpy as np
import pytest

from replay.planning.compare import changed_within, conflicts, safety_verdict
from replay.planning.types import AgentForecasts, EgoState, Plan

TIMES = np.round(np.arange(51) * 0.1, 10)


def straight_plan(speed_mps: float, *, stop_at_m: float | None = None) -> Plan:
    """Along +x from 0 at ``speed_mps``; with ``stop_at_m``, at constant speed until it
    brakes at 5 m/s^2 to a stop there."""
    x = speed_mps * TIMES
    if stop_at_m is not None:
        brake = speed_mps**2 / 10.0  # braking distance at 5 m/s^2
        t_brake = max(stop_at_m - brake, 0.0) / speed_mps
        after = np.clip(TIMES - t_brake, 0.0, speed_mps / 5.0)
        braking = speed_mps * t_brake + speed_mps * after - 2.5 * after**2
        x = np.where(t_brake <= TIMES, braking, x)
    speed = np.gradient(x, TIMES)
    return Plan(
        ok=True, times_s=TIMES, xy=np.c_[x, np.zeros_like(x)], heading_rad=np.zeros_like(x),
        speed_mps=speed, plan_ms=1.0,
    )  # fmt: skip


def standing(ids: list[int], xs: list[float]) -> AgentForecasts:
    k = len(ids)
    xy = np.zeros((k, TIMES.size, 2))
    xy[:, :, 0] = np.asarray(xs, dtype=float)[:, None]
    return AgentForecasts(
        ids=np.array(ids), kinds=np.zeros(k, np.int8), length_m=np.full(k, 4.5),
        width_m=np.full(k, 1.8), times_s=TIMES, xy=xy, heading_rad=np.zeros((k, TIMES.size)),
    )  # fmt: skip


EGO = EgoState(xy=np.zeros(2), heading_rad=0.0, speed_mps=10.0)


def test_a_dropped_car_standing_in_the_path_makes_the_plan_unsafe():
    agents = standing([7], [30.0])
    reference = straight_plan(10.0, stop_at_m=15.0)  # stops 15 m short of the car
    filtered = straight_plan(10.0)  # the filter dropped the car: drives into it
    ref = conflicts(reference, agents, EGO)
    assert np.isinf(ref).all()
    verdict = safety_verdict(filtered, agents, np.array([False]), EGO, reference_conflicts=ref)
    assert verdict.unsafe is True and verdict.agent_id == 7
    # the first conflict is the 1 s time-to-collision, before the boxes touch (at 2.55 s)
    assert conflicts(filtered, agents, EGO)[0] == pytest.approx(1.6, abs=0.11)


def test_a_dropped_car_behind_does_not():
    agents = standing([3], [-30.0])
    reference = straight_plan(10.0)
    filtered = straight_plan(10.0, stop_at_m=15.0)
    ref = conflicts(reference, agents, EGO)
    verdict = safety_verdict(filtered, agents, np.array([False]), EGO, reference_conflicts=ref)
    assert verdict.unsafe is False and verdict.agent_id == -1


def test_kept_agents_and_shared_conflicts_do_not_count():
    agents = standing([7], [30.0])
    plan = straight_plan(10.0)
    ref = conflicts(plan, agents, EGO)  # the all-agents plan hits it too
    assert (
        safety_verdict(plan, agents, np.array([False]), EGO, reference_conflicts=ref).unsafe
        is False
    )
    none = np.full(1, np.inf)
    assert (
        safety_verdict(plan, agents, np.array([True]), EGO, reference_conflicts=none).unsafe
        is False
    )
    failed = Plan.failed("no plan")
    assert (
        safety_verdict(failed, agents, np.array([False]), EGO, reference_conflicts=none).unsafe
        is None
    )


def test_changed_within_the_first_second():
    a = straight_plan(10.0)
    b = straight_plan(10.0, stop_at_m=35.0)  # the same for 2.5 s
    c = straight_plan(9.0)  # 1 m apart at 1 s
    assert changed_within(a, b) is False
    assert changed_within(a, c) is True
    assert changed_within(a, c, tolerance_m=1.5) is False
    assert changed_within(a, Plan.failed("x")) is True
    assert changed_within(Plan.failed("x"), Plan.failed("y")) is None


def test_replay_plan_writes_the_verdict_and_the_shares(tmp_path):
    """End to end on issue 32's road: a cut that drops the car standing 40 m ahead gives an
    unsafe plan naming it; the cascade's plan is safe; summary and report carry the
    shares with intervals."""
    import json

    import polars as pl
    from click.testing import CliRunner
    from planner_scenes import STOPPED, write_road_scene

    from replay.cli.app import main

    (tmp_path / "road").mkdir()
    road = write_road_scene(tmp_path / "road" / "road.mcap")
    out = tmp_path / "out"
    result = CliRunner().invoke(main, [
        "plan", str(road), "-o", str(out), "--planner", "idm", "--filter", "radius:10",
        "--filter", "cascade", "--no-progress", "--workers", "1", "--report",
        str(tmp_path / "report.md"),
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = pl.read_parquet(out / "plans.parquet")
    by = {r["filter"]: r for r in rows.filter(pl.col("frame") == 0).iter_rows(named=True)}
    assert by["radius:10"]["unsafe"] is True and by["radius:10"]["unsafe_agent_id"] == STOPPED
    assert by["cascade"]["unsafe"] is False and by["cascade"]["unsafe_agent_id"] == -1
    assert by["none"]["unsafe"] is False and by["none"]["changed_1s"] is False
    assert {"changed_1s", "max_shift_1s_m", "ego_speed_mps"} <= set(rows.columns)
    summary = json.loads((out / "summary.json").read_text())
    f = summary["planners"]["idm"]["filters"]["radius:10"]
    assert f["unsafe"]["share"] > 0.5 and len(f["unsafe"]["ci95"]) == 2
    assert set(f["changed_at"]) == {"0.5", "1", "2", "speed_scaled"}
    assert f["changed_at"]["2"]["share"] <= f["changed_at"]["0.5"]["share"]
    assert "changed_1s" in f
    report = (tmp_path / "report.md").read_text()
    assert (
        "| filter | changed > 0.5 m | > 1 m | > 2 m | speed-scaled | changed in 1 s | unsafe |"
        in report
    )
