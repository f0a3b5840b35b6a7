"""The summary document of a recording: outcome, legend, cascade settings, scene facts.

Markdown, shown by the recording's "Summary" view (``rr.TextDocument``). The view is
small, so the most important comes first: the outcome in one line, how to read the
views, the cascade, then the scene's facts.
"""

from __future__ import annotations

import pathlib

import numpy as np

from outputs.sinks import SceneInfo
from recordings import layout as L
from recordings.frames import SceneRows


def recording_name(info: SceneInfo) -> str:
    if info.source is not None:
        return pathlib.Path(info.source).stem
    return info.metadata.get("scenario_id") or info.metadata.get("scenario") or "scene"


def _cell(value: object, limit: int = 120) -> str:
    """A markdown table cell: one line, pipes escaped, long values cut."""
    text = " ".join(str(value).split()).replace("|", "\\|")
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if values.size else float("nan")


def summary_markdown(info: SceneInfo, scene: SceneRows) -> str:
    """The summary document (markdown) of a recorded scene."""
    lines = [f"# {_cell(recording_name(info))}", "", _headline(info, scene), ""]
    lines += _legend_section(info)
    lines += _cascade_section(info, scene)
    lines += _scene_section(info, scene)
    return "\n".join(lines) + "\n"


def _headline(info: SceneInfo, scene: SceneRows) -> str:
    n, r = scene.times_s.size, scene.rows
    if n == 0:
        return f"No frame recorded (the scene has {info.n_frames}; the ego was never present)."
    per_frame = np.bincount(scene.frame_of[~r["is_ego"]], minlength=n)
    kept = (
        np.bincount(scene.frame_of[r["kept"][-1]], minlength=n) if r["kept"].shape[0] else per_frame
    )
    missed = int(scene.false_negatives[:, -1].sum()) if scene.false_negatives.shape[1] else 0
    return (
        f"Ego {info.ego_id}, {n} frames every {info.frame_period_s:g} s: the cascade keeps "
        f"**{_mean(kept):.1f}** of {_mean(per_frame):.1f} other agents per frame, with "
        f"**{missed}** false negatives (baseline-important agent-frames dropped)."
    )


def _scene_section(info: SceneInfo, scene: SceneRows) -> list[str]:
    n = scene.times_s.size
    others = ~scene.rows["is_ego"]
    duration = f"{scene.times_s[-1] - scene.times_s[0]:.1f} s" if n else "-"
    out = [
        "## Scene",
        "",
        "| | |",
        "|---|---|",
        f"| source | {_cell(info.source or 'in memory')} |",
        f"| ego id | {info.ego_id} |",
        f"| frames recorded | {n} of {info.n_frames} (skipped: {info.n_frames - n}) |",
        f"| frame period | {info.frame_period_s:g} s; recorded span {duration} |",
        f"| other agents | {np.unique(scene.rows['ids'][others]).size} distinct; "
        f"{_mean(np.bincount(scene.frame_of[others], minlength=n)):.1f} per frame |",
        f"| lanes | {len(info.map.lanes)} |",
    ]
    out += [f"| {_cell(k)} | {_cell(v)} |" for k, v in sorted(info.metadata.items())]
    for name, ids in sorted(info.labels.items()):
        shown = ", ".join(str(i) for i in ids[:12]) + (" …" if len(ids) > 12 else "")
        out.append(f"| label {_cell(name)} | {shown} |")
    return [*out, ""]


def _cascade_section(info: SceneInfo, scene: SceneRows) -> list[str]:
    casc, r = info.cascade, scene.rows
    n = scene.times_s.size
    per_frame = lambda mask: np.bincount(scene.frame_of[mask], minlength=n)  # noqa: E731
    out = [
        "## Cascade",
        "",
        f"Baseline: an agent is important when its survival risk R_S >= "
        f"{casc.baseline_threshold:g}; mean {_mean(per_frame(r['baseline'])):.1f} per frame.",
        "",
        "| stage | model | keeps risk >= | mean kept | false negatives | mean time |",
        "|---|---|---|---|---|---|",
        f"| input | | | {_mean(per_frame(~r['is_ego'])):.1f} | | |",
    ]
    for s, stage in enumerate(casc.stages):
        fn_total = int(scene.false_negatives[:, s].sum()) if n else 0
        out.append(
            f"| {s + 1} ({L.stage_color_name(s)}) | {stage.model} | {stage.threshold:.4g} "
            f"| {_mean(per_frame(r['kept'][s])):.1f} | {fn_total} "
            f"| {_mean(scene.stage_time_ms[:, s]):.2f} ms |"
        )
    out += [
        "",
        "| tier | outline | survival risk >= | max agents | mean agents |",
        "|---|---|---|---|---|",
    ]
    for k, tier in enumerate(casc.tiers):
        cap = "-" if tier.max_agents is None else str(tier.max_agents)
        out.append(
            f"| {tier.name} | {L.tier_color_name(k)} | {tier.min_survival_risk:.3g} | {cap} "
            f"| {_mean(per_frame(r['tier'] >= k)):.1f} |"
        )
    cascade_ms = _mean(scene.stage_time_ms.sum(axis=1) + scene.sort_time_ms)
    out += [
        "",
        f"Mean time per frame: cascade {cascade_ms:.2f} ms (stages + survival on the "
        f"survivors + tiers) against {_mean(scene.survival_all_time_ms):.2f} ms for survival "
        "analysis on all agents. False negatives count agent-frames that were "
        "baseline-important but dropped, up to and including each stage.",
        "",
        "Provenance of the thresholds:",
        "",
        *[
            f"> {line}" if line else ">"
            for line in (casc.provenance or "(not recorded)").splitlines()
        ],
        "",
    ]
    return out


def _synthetic_note(info: SceneInfo) -> list[str]:
    """Synthetic traffic follows its paths blindly: its near misses and collisions are
    not what drivers would do, and the rings should say so (issue 31)."""
    if not info.metadata.get("converter", "").startswith("synthetic"):
        return []
    return [
        "  This scene is synthetic: its agents follow their paths and do not react to each"
        " other, so some of the agents that really came close ran into the ego or another"
        " agent where real drivers would have braked. Recorded scenes do not have this.",
    ]


def _legend_section(info: SceneInfo) -> list[str]:
    casc = info.cascade
    tiers = ", ".join(f"{L.tier_color_name(k)} = {t.name}" for k, t in enumerate(casc.tiers))
    return [
        "## Reading the views",
        "",
        "Scene: top-down, x east, y north, metres; scrub the time line to replay.",
        "",
        "- **Green**: the ego and its path.",
        "- **Red**: agents kept by every stage; deeper red = higher survival risk R_S (log "
        f"scale, palest at {casc.baseline_threshold:g}, full red at 1). Thin red lines: the "
        "forward paths of the agents in the second tier and deeper.",
        f"- **Outline**: the deepest planner tier reached ({tiers}); the label is the id "
        "and the tier's initial (none: kept, but below the first tier).",
        "- **Grey**: dropped by a stage (hover for its id; label `id ✗k` with labels=all).",
        "- **Yellow with a yellow ring**, `id MISS ✗k`: a miss, dropped by stage k although "
        "the survival baseline or the hindsight truth (it really came close) marks it "
        "important. Every miss is a row of the **Misses** tab (time, agent, stage, "
        "reference): click a row to select the agent and jump to the time.",
        "- **Orange ring**: a kept agent that really came close (hindsight positive).",
        *_synthetic_note(info),
        "- Muted lines: lane boundaries (dark grey), road edges (brown), crosswalks "
        "(blue-grey) where the source has them. Dark nose: heading.",
        "- Labels: the ego, the tier agents and the misses; a label gives way to a more "
        f"important one within {L.LABEL_SPACING_M:g} m. Hover any agent for its id.",
        "",
        "Risk per agent: one tab per model, opening on the agents that matter (misses, "
        "hindsight positives, the deepest tiers); each agent's nine timelines live in its "
        "own subtree `/scene/agents/<id>/risk*` (drag one into a view, or right-click it "
        "in the streams panel, to add it). `log10` tabs: the values span many decades; "
        "zero risk is a gap. White: the stage threshold. Gaps: the agent is absent.",
        "Funnel: agents left after each stage and per tier. False negatives: in each "
        "frame, the baseline-important agents dropped by stage k or an earlier one. Compute time: per stage, against survival analysis on all agents.",
        "",
    ]
