"""``replay plan``: a planner in the loop, with all agents and with each filter's agents."""

from __future__ import annotations

import pathlib
import shlex
import sys

import click

from outputs.transaction import OutputGuard
from replay.analysis.planner_eval.closed_loop import (
    AGENT_MODES,
    DEFAULT_AGENTS,
    DEFAULT_TRACKER,
    load_tracker,
)
from replay.analysis.planner_eval.open_loop import PlanSettings
from replay.analysis.planner_eval.report import write_report
from replay.analysis.planner_eval.study import (
    describe_jobs,
    format_study,
    resolve_matched,
    run_study,
    scene_files,
    write_study,
)
from replay.cli.ego_options import ego_option, every_option
from replay.cli.engine_options import check_engine_options, engine_options
from replay.cli.limits import FiniteRange, refuse_idle
from replay.cli.settings_option import CASCADE_NAMES_HELP, CascadeFile, load_cascade, set_option
from replay.core.engine import Stride
from replay.errors import ReplayError
from replay.jobs.place import JobPlace
from replay.planning.registry import PLANNERS, make_planner, warm_up
from replay.planning.tracking import TRACKERS
from risk.filtering import FILTER_FORMS


@click.command("plan")
@click.argument(
    "scenes", nargs=-1, required=True,
    type=click.Path(exists=True, path_type=pathlib.Path),
)  # fmt: skip
@click.option(
    "-o", "--output", "out_dir", required=True,
    type=click.Path(file_okay=False, path_type=pathlib.Path),
    help="Output folder (created): plans.parquet, summary.json, plots.",
)  # fmt: skip
@ego_option("Default: each scene's own ego.")
@every_option
@click.option(
    "--ego-kinds", type=click.Choice(["vehicles", "all"]), default="vehicles",
    show_default=True,
    help="Which egos the car planners plan for: vehicles (ego-frames of pedestrians, "
    "cyclists and other agents are skipped and counted in summary.json) or all.",
)  # fmt: skip
@click.option(
    "--planner", "planners", multiple=True, default=("idm",), show_default=True,
    type=click.Choice(list(PLANNERS)),
    help="The planner (repeatable: each runs the same frames). idm: the built-in IDM "
    "planner along the ego's path (core dependencies only); fop, fiss, fiss_plus: "
    "fiss-planner's Frenet planners (pip install 'riskreplay[planner]'); pdm: a "
    "PDM-Closed-style planner (core dependencies only; docs/planners.md).",
)  # fmt: skip
@click.option(
    "--filter", "filters", multiple=True, default=("cascade",), show_default=True,
    metavar="SPEC",
    help="A filter to compare with all agents (repeatable): " + ", ".join(FILTER_FORMS)
    + ". cascade: the shipped thresholds or --cascade FILE; model:NAME: NAME's stage "
    "threshold in that cascade, or model:NAME:THRESHOLD; nearest:match and radius:match: "
    "the cut that keeps as many agents per frame, on average, as the cascade.",
)  # fmt: skip
@click.option(
    "--cascade", "cascade_file",
    type=CascadeFile(),
    help="Cascade TOML for the cascade filter (default: the shipped calibrated cascade). "
    + CASCADE_NAMES_HELP,
)  # fmt: skip
@click.option(
    "--truth", is_flag=True,
    help="Also plan without each agent in turn and write agents.parquet: an agent is "
    "planner-important when removing it alone changes the plan (agents the planner "
    "provably cannot react to are labelled without that plan).",
)  # fmt: skip
@click.option(
    "--closed-loop", is_flag=True,
    help="Also drive each vehicle ego with the planner (re-plan at 10 Hz, the ego follows "
    "each plan through --tracker) while the others move as --agents says; once with all "
    "agents and once per filter. Writes closed_loop.parquet.",
)  # fmt: skip
@click.option(
    "--agents", type=click.Choice(list(AGENT_MODES)), default=DEFAULT_AGENTS,
    show_default=True,
    help="With --closed-loop: reactive: vehicles follow their logged path with IDM speed "
    "control, reacting to the ego and each other (never ahead of their log); "
    "pedestrians, cyclists and objects replay their log. log: everyone replays the log.",
)  # fmt: skip
@click.option(
    "--tracker", type=click.Choice(list(TRACKERS)), default=DEFAULT_TRACKER,
    show_default=True,
    help="With --closed-loop: how the ego follows each plan. perfect: on the plan's own "
    "state; lqr: a kinematic bicycle with an LQR controller.",
)  # fmt: skip
@click.option(
    "--closed-loop-egos", type=click.IntRange(min=1), default=None, metavar="K",
    help="With --closed-loop: at most K egos per scene, those present longest "
    "(default: every ego of --ego).",
)  # fmt: skip
@click.option(
    "--closed-loop-sample", type=click.IntRange(min=1), default=None, metavar="N",
    help="With --closed-loop: N vehicle egos in all, spread evenly over the datasets (the "
    "scenes' folders), then over each dataset's scenes (those present longest first).",
)  # fmt: skip
@click.option(
    "--tolerance", "tolerance_m", type=FiniteRange(min=0.0), default=0.5,
    show_default=True,
    help="A plan changed when it moves more than this many metres from the all-agents "
    "plan at an equal time within the horizon, or its stop/go, lane or success differs.",
)  # fmt: skip
@click.option("--horizon", "horizon_s", type=FiniteRange(min=0.5, max=30.0), default=5.0,
              show_default=True, help="Planning horizon (s).")  # fmt: skip
@click.option(
    "--report", "report_path", default=None,
    type=click.Path(dir_okay=False, path_type=pathlib.Path),
    help="Also write a Markdown report of the run (e.g. docs/planner-evaluation.md), its "
    "plots into the folder of the same name without .md.",
)  # fmt: skip
@engine_options
@click.option("--plots/--no-plots", default=True, show_default=True, help="Write the PNG plots.")
@click.option(
    "--progress/--no-progress", default=True, show_default=True, help="Progress bar on stderr."
)
@set_option
def plan(
    scenes: tuple[pathlib.Path, ...],
    out_dir: pathlib.Path,
    ego: int | str | None,
    every: Stride,
    ego_kinds: str,
    planners: tuple[str, ...],
    filters: tuple[str, ...],
    cascade_file: pathlib.Path | None,
    truth: bool,
    closed_loop: bool,
    agents: str,
    tracker: str,
    closed_loop_egos: int | None,
    closed_loop_sample: int | None,
    tolerance_m: float,
    horizon_s: float,
    workers: int | None,
    report_path: pathlib.Path | None,
    plots: bool,
    progress: bool,
    engine: str = "local",
    ray_address: str | None = None,
    sets: tuple[str, ...] = (),
) -> None:
    """Plan every frame of SCENES with all agents and with each filter's agents.

    SCENES are MCAP scenes or folders of them (searched recursively). At each replayed
    frame (see --every) the planner gets the ego's state, its path, its lanes and the
    other agents with their predicted trajectories; it plans once with all of them and
    once per --filter, and each filtered plan is compared with the all-agents plan.

    \b
    Writes into OUTPUT:
      plans.parquet    one row per (scene, ego, frame, filter): n_agents, filter_ms,
                       plan_ms, plan_ok, changed, max_shift_m, blocking_dropped, ...
      closed_loop.parquet  with --closed-loop: one row per (scene, ego, filter):
                       collisions by class, at_fault_collisions, drivable_area_ok,
                       progress_ratio, min_ttc_s, comfortable, score, plan_ms_median
      agents.parquet   with --truth: one row per (scene, ego, frame, agent):
                       planner_label, planner_shift_m
      summary.json     per planner and filter: kept agents, changed share (95 % scene
                       bootstrap), planning time vs all agents by agent-count bins
                       and dataset; the closed loop's paired differences
      plan_time.png    (plan_time_<planner>.png with several planners),
      plan_changed.png
      failures.csv     the scenes that failed (one line each; left out)
      parts/           every scene's rows and its done-marker, per pass (matching,
                       open loop and closed loop per planner): a rerun into OUTPUT
                       skips complete scenes (see docs/batch.md)

    Scenes run as jobs on --engine (local processes or Ray; docs/batch.md). Exits
    non-zero when every scene failed; scenes that fail while others succeed are listed
    (and in failures.csv), with exit code 0.

    Example, the corpus study of docs/planner-evaluation.md:

    \b
      replay plan corpus/scenes/ --ego all --every 1s --planner idm
          --planner fiss_plus --filter cascade --filter nearest:match
          --filter radius:match --closed-loop --closed-loop-sample 400
          -o plan-out/ --report docs/planner-evaluation.md
    """
    refuse_idle("--closed-loop", closed_loop, "closed_loop_egos", "closed_loop_sample")
    check_engine_options(engine, ray_address)
    cascade = load_cascade(cascade_file, sets)
    planners = tuple(dict.fromkeys(planners))
    settings = PlanSettings(
        planner=planners[0], filters=tuple(filters), cascade=cascade,
        tolerance_m=tolerance_m, horizon_s=horizon_s, truth=truth, ego_kinds=ego_kinds,
    )  # fmt: skip
    resolve_matched(settings, {"nearest_k": 1, "radius_m": 1.0}).make_filters()  # bad specs
    for name in planners:
        # a missing optional extra fails before anything is read; compiled code is
        # compiled (or loaded) here once, not in every worker
        warm_up(make_planner(name))
    if closed_loop:
        load_tracker(tracker)  # so does a tracker that is not installed
    found = scene_files(scenes)
    if not found:
        raise ReplayError(f"{', '.join(map(str, scenes))}: no .mcap scene found")
    report_folder = None if report_path is None else report_path.with_suffix("")
    with OutputGuard(
        inputs=[*found, cascade_file], folders=(out_dir, report_folder), files=(report_path,)
    ):
        result = run_study(
            found, settings, planners=planners, ego=ego, every=every, progress=progress,
            place=JobPlace(out_dir, engine, workers, ray_address, progress),
            closed_loop=closed_loop, closed_loop_egos=closed_loop_egos,
            closed_loop_sample=closed_loop_sample, agents=agents, tracker=tracker,
            notify=lambda message: click.echo(message, err=True),
        )  # fmt: skip
        files = write_study(result, out_dir, plots=plots or report_path is not None)
        if report_path is not None:
            words = ["replay", "plan", *sys.argv[2:]] if len(sys.argv) > 2 else ["replay plan"]
            files.update(
                write_report(report_path, result.summary, result.points, command=shlex.join(words))
            )
    click.echo(format_study(result.summary))
    click.echo("Scenes:\n" + describe_jobs(result))
    click.echo("Wrote:")
    for path in files.values():
        click.echo(f"  {path}")
