"""``replay plan`` on the job engine (issue 38): a failing scene is listed while the others
complete, a rerun skips the complete scenes and gives the same summary, and Ray gives the
local answers (timing columns aside), for the open loop, the matched cuts and the closed
loop (one task per scene for its sampled egos)."""

from __future__ import annotations

import pathlib

import polars as pl
import pytest
from click.testing import CliRunner, Result
from jobs_fixtures import ray_instance, road_corpus, summary, timing_key  # noqa: F401

from replay.cli.app import main
from replay.jobs import read_failures

#: A small study: two filters (one matched to the cascade), the closed loop on two of
#: the three scenes' egos.
STUDY = (
    "--every", "5", "--filter", "cascade", "--filter", "nearest:match",
    "--closed-loop", "--closed-loop-sample", "2", "--agents", "log", "--tracker", "perfect",
    "--no-plots", "--no-progress",
)  # fmt: skip


def plan(*args: object) -> Result:
    return CliRunner().invoke(main, ["plan", *map(str, args)])


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> pathlib.Path:
    root = tmp_path_factory.mktemp("plan-jobs")
    road_corpus(root)
    return root


def untimed_table(path: pathlib.Path) -> pl.DataFrame:
    df = pl.read_parquet(path)
    return df.select([c for c in df.columns if not timing_key(c)])


@pytest.fixture(scope="module")
def local_run(corpus, tmp_path_factory) -> pathlib.Path:
    out = tmp_path_factory.mktemp("plan-local") / "out"
    result = plan(corpus, "-o", out, *STUDY, "--workers", "2")
    assert result.exit_code == 0, result.output
    assert "1 failed" in result.output and "local engine" in result.output
    return out


def test_a_failing_scene_is_listed_once_and_the_others_complete(local_run):
    [failure] = read_failures(local_run / "failures.csv")
    assert failure.scene == "setB/broken" and failure.stage == "read"
    plans = pl.read_parquet(local_run / "plans.parquet")
    assert sorted(plans["scene"].unique().to_list()) == [
        "setA/S_SiteA-1_1", "setA/S_SiteA-1_2", "setB/S_SiteB-2_1",
    ]  # fmt: skip
    assert sorted(plans["dataset"].unique().to_list()) == ["setA", "setB"]
    runs = pl.read_parquet(local_run / "closed_loop.parquet")
    assert runs.filter(pl.col("filter") == "none").height == 2  # the sample
    data = summary(local_run)
    assert data["failed_scenes"] == ["setB/broken"]
    assert data["planners"]["idm"]["scenes"] == 3
    assert data["planners"]["idm"]["closed_loop"]["egos"]["sampled"] == 2


def test_a_rerun_skips_the_complete_scenes_and_gives_the_same_summary(corpus, local_run):
    before = summary(local_run)
    plans = untimed_table(local_run / "plans.parquet")
    again = plan(corpus, "-o", local_run, *STUDY, "--workers", "2")
    assert again.exit_code == 0, again.output
    assert "0 scene(s) computed, 3 skipped (complete)" in again.output
    assert "recomputed" not in again.output
    assert summary(local_run) == before
    assert untimed_table(local_run / "plans.parquet").equals(plans)


def test_one_worker_in_this_process_gives_the_same_answers(corpus, local_run, tmp_path):
    out = tmp_path / "out"
    result = plan(corpus, "-o", out, *STUDY, "--workers", "1")
    assert result.exit_code == 0, result.output
    assert summary(out) == summary(local_run)
    for name in ("plans", "closed_loop"):
        assert untimed_table(out / f"{name}.parquet").equals(
            untimed_table(local_run / f"{name}.parquet")
        ), name


def test_ray_gives_the_local_answers(corpus, local_run, ray_instance, tmp_path):  # noqa: F811
    out = tmp_path / "out"
    result = plan(corpus, "-o", out, *STUDY, "--engine", "ray")
    assert result.exit_code == 0, result.output
    assert "ray engine" in result.output and "1 failed" in result.output
    assert read_failures(out / "failures.csv") == read_failures(local_run / "failures.csv")
    assert summary(out) == summary(local_run)
    for name in ("plans", "closed_loop"):
        assert untimed_table(out / f"{name}.parquet").equals(
            untimed_table(local_run / f"{name}.parquet")
        ), name


def test_ego_tasks_cut_a_scenes_egos_into_runs_of_at_most_n():
    from replay.analysis.planner_eval.jobs import ego_tasks

    tasks = ego_tasks({"b/s2": [7], "a/s1": [1, 2, 3, 4, 5, 6, 8, 9, 10]}, per_task=4)
    assert tasks == [
        ("a/s1", "a/s1", (1, 2, 3, 4)),
        ("a/s1#egos-001", "a/s1", (5, 6, 8, 9)),
        ("a/s1#egos-002", "a/s1", (10,)),
        ("b/s2", "b/s2", (7,)),
    ]
    assert [t for t, _, _ in tasks] == sorted(t for t, _, _ in tasks)


def test_a_scenes_egos_split_over_tasks_give_the_rows_of_one_task(corpus, tmp_path, monkeypatch):
    from replay.analysis.planner_eval import jobs

    study = [*STUDY[: STUDY.index("--closed-loop-sample")], "--closed-loop-sample", "5"]
    study += [*STUDY[STUDY.index("--closed-loop-sample") + 2 :], "--ego", "all"]
    tables = []
    for per_task in (1, 100):
        monkeypatch.setattr(jobs, "EGOS_PER_TASK", per_task)
        out = tmp_path / f"out{per_task}"
        result = plan(corpus, "-o", out, *study, "--workers", "1")
        assert result.exit_code == 0, result.output
        tables.append(untimed_table(out / "closed_loop.parquet").sort("scene", "ego_id", "filter"))
    split, whole = tables
    runs = split.filter(pl.col("filter") == "none")
    assert runs.height == 5
    assert runs.group_by("scene").len()["len"].max() >= 2  # one scene's egos in two tasks
    assert split["scene"].unique().sort().to_list() == whole["scene"].unique().sort().to_list()
    assert "#" not in "".join(split["scene"].to_list())
    assert split.equals(whole)
