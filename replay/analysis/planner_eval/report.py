"""The Markdown report of ``replay plan --report FILE.md`` (docs/planner-evaluation.md):
every number comes from the run's summary; the plots are copied beside the report.

The verdict on the paper's claim ("fewer agents, less planning, no safety issue") is
computed from the same numbers, with the rule stated in the text: a filter *keeps the plan*
when the upper end of the 95 % scene-bootstrap interval of its changed share is below
the threshold given (default 1 %), and *saves planning* when its median filter-plus-plan
time is at most 0.95x the all-agents plan's (:data:`SAVES_PLANNING_RATIO`).
"""

from __future__ import annotations

import datetime
import math
import pathlib
from collections.abc import Sequence
from typing import Any

from outputs.atomic import write_text
from replay.analysis.planner_eval.plots import write_plots
from replay.analysis.planner_eval.streaming import PlotPoints

#: The changed share (upper 95 % bound) below which a filter "keeps the plan".
KEEPS_PLAN_SHARE = 0.01
#: A filter saves planning when its median filter-plus-plan time is at most this share of
#: the all-agents plan's: re-runs of one study on the shared machine moved the ratio by up
#: to 0.04 (1.02x-1.06x), so a ratio of 0.99x says nothing.
SAVES_PLANNING_RATIO = 0.95


def _pct(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{100 * value:.{digits}f} %"


def _ci(ci: list[float | None] | None) -> str:
    if not ci or ci[0] is None or ci[1] is None:
        return ""
    return f" [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def _ms(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def _m(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.1f}"


def _open_loop(name: str, entry: dict[str, Any], plots: dict[str, str]) -> list[str]:
    every = entry.get("all_agents", {})
    lines = [
        f"### {name}: open loop",
        "",
        f"{entry['ego_frames']} ego-frames of {entry['scenes']} scenes, "
        f"{entry['distinct_egos']} distinct egos; {entry['ego_frames_without_path']} "
        "ego-frames had no path to plan along (counted, never as unchanged). With all "
        f"agents the planner got {every.get('mean_agents', 0):.1f} agents per frame and "
        f"found a plan in {_pct(every.get('plan_ok_share'))} of the frames.",
        "",
        "| filter | agents kept | plan changed [95 % CI] | comparable frames (egos, scenes "
        "changed) | blocking agent dropped | filter + plan, median / p95 (ms) | all agents, "
        "median / p95 (ms) | time ratio |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for filt, f in entry["filters"].items():
        ch, bl = f["changed"], f["blocking_agent_dropped"]
        ratio = f["median_time_ratio"]
        lines.append(
            f"| {filt} | {f['mean_kept']:.1f} | {_pct(ch['share'])}{_ci(ch['ci95'])} | "
            f"{ch['n']} ({f['changed_egos']}, {f['changed_scenes']}) | "
            f"{_pct(bl['share'])} of {bl['n']} | "
            f"{_ms(f['filter_plus_plan_ms']['median'])} / {_ms(f['filter_plus_plan_ms']['p95'])} | "
            f"{_ms(f['all_agents_plan_ms']['median'])} / {_ms(f['all_agents_plan_ms']['p95'])} | "
            f"{'n/a' if ratio is None else f'{ratio:.2f}x'} |"
        )
    lines.append("")
    for filt, f in entry["filters"].items():
        why = f.get("changed_why") or {}
        if not why:
            continue
        shift = f.get("changed_shift_m") or {}
        parts = ", ".join(f"{k} {n}" for k, n in why.items())
        lines.append(
            f"- {filt}: the changed frames by the first rule that caught them: {parts}; "
            f"shifts of {_m(shift.get('median'))} m median, {_m(shift.get('p95'))} m p95."
        )
    lines += _safety_table(entry)
    lines += [
        "",
        "*Blocking agent dropped*: of the frames where the all-agents plan named the agent "
        "that constrained it, the share where the filter dropped that agent. *Comparable "
        "frames*: frames where at least one of the two plans exists.",
        "",
    ]
    bins = entry.get("by_agent_count", {})
    if bins:
        lines += [
            "By the number of other agents in the frame (frames where both plans exist):",
            "",
            "| filter | agents | frames | all agents, median / p95 (ms) | filter + plan, "
            "median / p95 (ms) | plan changed |",
            "|---|---|---:|---:|---:|---:|",
        ]
        for filt, rows in bins.items():
            for b in rows:
                lines.append(
                    f"| {filt} | {b['agents']} | {b['ego_frames']} | "
                    f"{_ms(b['all_agents_plan_ms']['median'])} / "
                    f"{_ms(b['all_agents_plan_ms']['p95'])} | "
                    f"{_ms(b['filter_plus_plan_ms']['median'])} / "
                    f"{_ms(b['filter_plus_plan_ms']['p95'])} | {_pct(b['changed_share'])} |"
                )
        lines.append("")
    by_dataset = entry.get("by_dataset", {})
    if by_dataset:
        datasets = sorted({d for rows in by_dataset.values() for d in rows})
        lines += [
            "Plans changed per dataset (share of the dataset's comparable frames; mean "
            "agents kept of the mean others):",
            "",
            "| dataset | " + " | ".join(by_dataset) + " |",
            "|---|" + "---:|" * len(by_dataset),
        ]
        for d in datasets:
            cells = []
            for filt in by_dataset:
                r = by_dataset[filt].get(d)
                cells.append(
                    ""
                    if r is None
                    else f"{_pct(r['changed_share'])} ({r['mean_kept']:.1f} "
                    f"of {r['mean_others']:.1f})"
                )
            lines.append(f"| {d} | " + " | ".join(cells) + " |")
        lines.append("")
    if name in plots:
        lines += [f"![Planning time, {name}]({plots[name]})", ""]
    return lines


def _mean_ci(d: dict[str, Any] | None, *, signed: bool = True, digits: int = 3) -> str:
    """``mean [lo, hi]`` of a mean with its interval (signed: a difference)."""
    if not d or d.get("mean") is None:
        return "n/a"
    form = f"{'+' if signed else ''}.{digits}f"
    ci = d.get("ci95") or [None, None]
    text = f"{d['mean']:{form}}"
    if ci[0] is not None and ci[1] is not None and math.isfinite(ci[0]):
        text += f" [{ci[0]:{form}}, {ci[1]:{form}}]"
    return text


def _safety_table(entry: dict[str, Any]) -> list[str]:
    """Changed at 0.5, 1 and 2 m and speed-scaled, changed in the first second, unsafe
    (docs/planners.md, "Is the filtered plan safe?"), with 95 % scene-bootstrap intervals."""
    rows = {k: f for k, f in entry["filters"].items() if "unsafe" in f}
    if not rows:
        return []
    lines = [
        "",
        "Changed at other tolerances, in the executed first second, and unsafe (the filtered "
        "plan collides with, or comes within 1 s time-to-collision of, an agent the filter "
        "dropped, where the all-agents plan does not), with 95 % scene-bootstrap intervals:",
        "",
        "| filter | changed > 0.5 m | > 1 m | > 2 m | speed-scaled | changed in 1 s | unsafe |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for filt, f in rows.items():
        at = f["changed_at"]
        cells = [at["0.5"], at["1"], at["2"], at["speed_scaled"], f["changed_1s"], f["unsafe"]]
        lines.append(
            f"| {filt} | " + " | ".join(f"{_pct(c['share'])}{_ci(c['ci95'])}" for c in cells) + " |"
        )
    unsafe_counts = ", ".join(
        f"{k} {f['unsafe']['count']} of {f['unsafe']['n']}" for k, f in rows.items()
    )
    lines += ["", f"Unsafe filtered plans: {unsafe_counts}."]
    return lines


def _closed_loop(name: str, closed: dict[str, Any]) -> list[str]:
    if not closed.get("runs"):
        return []
    agents = closed.get("agents", "log")
    others = (
        "vehicles follow their logged path with IDM speed control and react to the ego "
        "and each other; pedestrians, cyclists and objects replay their log"
        if agents == "reactive"
        else "the others replay their log (non-reactive)"
    )
    datasets = ", ".join(f"{d} {n}" for d, n in closed.get("datasets", {}).items())
    egos = closed.get("egos", {})
    skipped = egos.get("skipped_not_vehicles", 0)
    sampled_from = (
        f" (sampled from {egos['vehicle_egos']} vehicle egos; {skipped} pedestrian, "
        "cyclist or object egos are no car-planner egos and were skipped)"
        if egos
        else ""
    )
    lines = [
        f"### {name}: closed loop",
        "",
        f"{closed['runs']} vehicle egos in {closed['scenes']} scenes ({datasets}){sampled_from}, each "
        "driven by the planner from its first recorded frame to the scene's end, once with "
        f"all agents and once per filter, following its plans with the "
        f"{closed.get('tracker', 'perfect')} tracker; {others}. Collisions are classified "
        "and counted at fault by nuPlan's rules; the score is nuPlan's closed-loop score "
        'shape (docs/planners.md, "Closed-loop metrics and score").',
        "",
        "| filter | agents given | collisions: stopped ego / stopped track / front / rear "
        "/ lateral | at fault | runs with an at-fault collision [95 % CI] | score [95 % CI] "
        "| progress ratio, median | TTC < 0.95 s | uncomfortable | plan, median of medians "
        "/ p95 (ms) | plan failures |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for filt, f in closed["filters"].items():
        by = f.get("collisions_by_class", {})
        classes = " / ".join(
            str(by.get(c, 0))
            for c in ("stopped_ego", "stopped_track", "front", "rear_end", "lateral")
        )
        fault = f.get("runs_at_fault", {})
        score = f.get("score", {})
        score_text = _mean_ci(score, signed=False)
        lines.append(
            f"| {filt} | {f['mean_agents']:.1f} | {classes} | {f.get('at_fault_collisions', 0)} "
            f"| {_pct(fault.get('share'))}{_ci(fault.get('ci95'))} | {score_text} | "
            f"{_ratio(f.get('progress_ratio', {}).get('median'))} | "
            f"{f.get('ttc_below_bound', 0)} | {f.get('uncomfortable', 0)} | "
            f"{_ms(f['plan_ms_median'])} / {_ms(f['plan_ms_p95'])} | {f['plan_failures']} |"
        )
    paired = [(filt, f["paired"]) for filt, f in closed["filters"].items() if "paired" in f]
    if paired:
        lines += [
            "",
            "Paired with the all-agents run of the same ego (filter minus all agents; mean "
            "difference per run with its 95 % scene-bootstrap interval):",
            "",
            "| filter | pairs | at-fault collisions | score | progress ratio | runs with "
            "more / fewer at-fault collisions |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for filt, p in paired:
            lines.append(
                f"| {filt} | {p['runs']} | {_mean_ci(p.get('at_fault_difference'))} | "
                f"{_mean_ci(p.get('score_difference'))} | "
                f"{_mean_ci(p.get('progress_ratio_difference'))} | "
                f"{p.get('more_at_fault', 0)} / {p.get('fewer_at_fault', 0)} |"
            )
    lines.append("")
    return lines


def _ratio(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def verdict(summary: dict[str, Any], *, keeps_plan_share: float = KEEPS_PLAN_SHARE) -> list[str]:
    """The claim, filter by filter and planner by planner, from the numbers."""
    lines = []
    for name, entry in summary["planners"].items():
        all_kept = entry.get("all_agents", {}).get("mean_agents", 0.0)
        for filt, f in entry["filters"].items():
            ch = f["changed"]
            hi = (ch["ci95"] or [None, None])[1]
            ratio = f["median_time_ratio"]
            fewer = f["mean_kept"] < all_kept
            faster = ratio is not None and ratio <= SAVES_PLANNING_RATIO
            same = hi is not None and hi < keeps_plan_share
            closed = entry.get("closed_loop", {}).get("filters", {}).get(filt, {})
            more = closed.get("paired", {}).get(
                "more_at_fault", closed.get("paired", {}).get("more_collisions")
            )
            parts = [
                f"**{name}, {filt}**: "
                + ("fewer agents" if fewer else "no fewer agents")
                + f" ({f['mean_kept']:.1f} of {all_kept:.1f}); "
                + ("less planning" if faster else "no less planning")
                + (f" ({ratio:.2f}x the median)" if ratio is not None else "")
                + "; "
                + (
                    f"the plan kept (changed in {_pct(ch['share'], 2)}, upper 95 % bound "
                    f"{_pct(hi, 2)} < {_pct(keeps_plan_share, 0)})"
                    if same
                    else f"the plan **not** kept: changed in {_pct(ch['share'], 2)}"
                    f"{_ci(ch['ci95'])} of {ch['n']} frames"
                )
            ]
            if more is not None:
                parts.append(
                    f"; closed loop: {more} of {closed['paired']['runs']} runs with more "
                    "at-fault collisions than with all agents"
                )
            claim = fewer and faster and same and (more in (None, 0))
            lines.append("- " + "".join(parts) + (". **Holds.**" if claim else ". Does not hold."))
    return lines


def write_report(
    path: pathlib.Path,
    summary: dict[str, Any],
    points: Sequence[PlotPoints],
    *,
    command: str,
) -> dict[str, pathlib.Path]:
    """The report at ``path``, its plots drawn into the folder of the same name
    (``points``: each planner's planning-time scatter, from the study's summary pass)."""
    folder = path.with_suffix("")
    folder.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    relative: dict[str, str] = {}
    if points:
        for key, target in write_plots(points, summary, folder).items():
            written[f"report:{key}"] = target
            relative[key] = f"{folder.name}/{target.name}"
    per_planner = {}
    for name in summary["planners"]:
        for key in (f"plan_time_{name}.png", "plan_time.png"):
            if key in relative:
                per_planner[name] = relative[key]
                break
    first: dict[str, Any] = next(iter(summary["planners"].values()), {})
    matched = summary.get("matched_cuts")
    lines = [
        "# A planner in the loop: what filtering saves, and what it changes",
        "",
        "Generated by `replay plan` "
        f"({datetime.date.today().isoformat()}); every number below comes from its "
        "summary.json. Reproduce with:",
        "",
        "```bash",
        command,
        "```",
        "",
        "## Set-up",
        "",
        f"- {first.get('scenes', 0)} scenes; every moving agent as the ego at the stride "
        "given; at each ego-frame the planner plans once with all valid other agents "
        "(each predicted at constant speed along its path, the toolkit's own prediction) "
        "and once with each filter's agents.",
        f"- A plan *changed* when it moves more than {summary.get('tolerance_m', 0.5):g} m "
        "from the all-agents plan at any equal time within the "
        f"{summary.get('horizon_s', 5.0):g} s horizon, or its stop/go, lane or success "
        "differs (`replay.planning.compare`). Frames where neither plan exists are not "
        "comparable and left out.",
        "- Intervals: 95 % scene bootstrap (1000 resamples of whole scenes; frames of one "
        "scene are not independent).",
        "- Times are wall-clock per call on this 2-core machine, planner and filter in "
        "turns at every frame; the filter's time is its own compute (the cascade without "
        "the survival-on-all comparison).",
    ]
    if matched:
        lines.append(
            f"- nearest-K and radius cuts matched to the cascade's mean of "
            f"{matched['cascade_mean_kept']:.2f} agents per ego-frame: K = "
            f"{matched['nearest_k']}, R = {matched['radius_m']:g} m."
        )
    if "closed_loop_selection" in summary:
        lines.append(
            "- Closed loop: the planner drives the ego from its first recorded frame, "
            "re-planning at 10 Hz (the log's rate where slower) and following each plan "
            f"with the {summary.get('closed_loop_tracker', 'perfect')} tracker; the others: "
            f"{summary.get('closed_loop_agents', 'log')}. Egos: "
            f"{summary['closed_loop_selection']}."
        )
    lines += ["", "## Does the claim hold?", "", *verdict(summary), ""]
    lines += [
        f"A filter keeps the plan here when the upper end of the 95 % interval of its "
        f"changed share is below {_pct(KEEPS_PLAN_SHARE, 0)}; it saves planning when the "
        "median of its time plus the filtered plan is at most "
        f"{SAVES_PLANNING_RATIO:.2f}x the all-agents plan's (re-runs on the shared machine "
        "move the ratio by a few hundredths).",
        "",
    ]
    if "plan_changed" in relative or "plan_changed.png" in relative:
        lines += [f"![Plans changed per filter]({relative.get('plan_changed.png')})", ""]
    lines += ["## Results", ""]
    for name, entry in summary["planners"].items():
        lines += _open_loop(name, entry, per_planner)
        lines += _closed_loop(name, entry.get("closed_loop", {}))
    lines += [
        "## What the data cannot decide",
        "",
        "- The planners plan against the toolkit's constant-speed predictions, not the "
        "recorded future: a changed plan says the filter dropped an agent this planner "
        "would have reacted to, not that the recorded driver reacted to it.",
        "- In the closed loop the others replay their log or follow it with IDM: a "
        "planner that brakes where the recorded driver did not can still be hit from "
        "behind by a replayed follower (counted, not at fault), and reactive agents never "
        "run ahead of their log.",
        "- Drone and camera recordings have no real ego; every moving agent stands in for "
        "one, so egos of one scene share their traffic (the intervals resample scenes).",
        "",
    ]
    written["report"] = write_text(path, "\n".join(lines))
    return written
