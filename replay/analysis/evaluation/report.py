"""The generated Markdown report of an outcome evaluation (``replay evaluate --report``):
which of the paper's findings hold against what really happened, with what confidence,
the positives as distinct agents, the sensitivity sweep, and what the data cannot decide.

Every sentence that states a result is chosen by a test on the summary (never written by
hand); the fixed prose is in ``report_templates/recorded_evaluation.md``.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import math
import os
import pathlib
import platform
import shutil
import string
from collections.abc import Mapping
from typing import Any

import polars as pl

from outputs.atomic import atomic_output
from replay.analysis.evaluation.corpus import HEADLINE_THRESHOLD
from replay.analysis.evaluation.files import auc_bound_note
from replay.analysis.evaluation.sensitivity import RANKED, SweepResult
from risk.registry import MODELS

TEMPLATE = pathlib.Path(__file__).with_name("report_templates") / "recorded_evaluation.md"
#: Each model's name inside a sentence, from the registry (``ModelSpec.label``).
TITLES = {name: spec.label for name, spec in MODELS.items()}


def _auc(summary: Mapping[str, Any], model: str, ref: str) -> tuple[float, float, float]:
    a = summary["models"][model][ref]["auc"]
    ci = a.get("ci") or [None, None]

    def num(x: Any) -> float:
        return math.nan if x is None else float(x)

    return num(a["value"]), num(ci[0]), num(ci[1])


def _fmt(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.3f}"


def _fmt_ci(a: tuple[float, float, float]) -> str:
    return f"{_fmt(a[0])} [{_fmt(a[1])}, {_fmt(a[2])}]"


def _above(a: tuple[float, float, float], b: tuple[float, float, float]) -> str:
    """'yes, intervals apart' / 'yes, intervals overlap' / 'no ...' for a > b."""
    if not (math.isfinite(a[0]) and math.isfinite(b[0])):
        return "undecided (no AUC)"
    if a[0] > b[0]:
        return (
            "holds, intervals apart"
            if a[1] > b[2]
            else "holds on the point estimate only (intervals overlap)"
        )
    return (
        "reversed, intervals apart"
        if b[1] > a[2]
        else "reversed on the point estimate only (intervals overlap)"
    )


def paper_findings(summary: Mapping[str, Any], ref: str) -> list[tuple[str, str]]:
    """(finding, verdict) of the paper's ranking findings against ``ref``. With fewer
    than two scenes there is no interval, so no order is "intervals apart"."""
    if any(ref not in per for per in summary["models"].values()):
        return []
    a = {m: _auc(summary, m, ref) for m in summary["models"]}
    if summary["scenes"] < 2:
        a = {m: (v[0], -math.inf, math.inf) for m, v in a.items()}
    out: list[tuple[str, str]] = []
    others = [m for m in RANKED if m != "current_distance" and m in a]
    if "current_distance" in a and others:
        verdicts = [_above(a[m], a["current_distance"]) for m in others]
        below = [m for m, v in zip(others, verdicts, strict=True) if v.startswith("reversed")]
        apart = sum(v == "holds, intervals apart" for v in verdicts)
        if below:
            verdict = "does not hold: " + ", ".join(TITLES[m] for m in below) + " score(s) lower"
        else:
            verdict = f"holds; against {apart} of {len(others)} models the intervals are apart"
        out.append(("Current distance is the worst model", verdict))
    if "gaussian" in a:
        rest = [m for m in RANKED if m != "gaussian" and m in a]
        verdicts = [_above(a["gaussian"], a[m]) for m in rest]
        above = [m for m, v in zip(rest, verdicts, strict=True) if v.startswith("reversed")]
        apart = sum(v == "holds, intervals apart" for v in verdicts)
        verdict = (
            "does not hold: " + ", ".join(TITLES[m] for m in above) + " score(s) higher"
            if above
            else f"holds; against {apart} of {len(rest)} models the intervals are apart"
        )
        out.append(("2D Gaussians come closest to survival (best of the other models)", verdict))
    for other in ("closest_encounter", "headway_2d"):
        if "trajectory_distance" in a and other in a:
            out.append(
                (
                    f"Trajectory distance ranks above {TITLES[other]}",
                    _above(a["trajectory_distance"], a[other]),
                )
            )
    return out


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _positives_section(pos: pl.DataFrame) -> str:
    if pos.is_empty():
        return "No agent came close."
    per: list[str] = []
    for col in ("dataset", "kind"):
        g = (
            pos.group_by(col)
            .agg(
                pl.len().alias("pairs"),
                pl.struct("scene", "agent_id").n_unique().alias("agents"),
                pl.col("positive_frames").sum().alias("frames"),
                pl.col("scene").n_unique().alias("scenes"),
            )
            .sort(col)
        )
        rows = [
            [str(r[col]), str(r["agents"]), str(r["pairs"]), str(r["frames"]), str(r["scenes"])]
            for r in g.iter_rows(named=True)
        ]
        per.append(
            f"Per {col}:\n\n"
            + _table([col, "distinct agents", "(ego, agent) pairs", "agent-frames", "scenes"], rows)
        )
    total = pos.select(pl.struct("scene", "agent_id").n_unique()).item()
    return (
        f"{total} distinct agents (scene, agent id) came close to at least one ego; "
        f"{pos.height} distinct (ego, agent) pairs; {int(pos['positive_frames'].sum())} "
        "positive agent-frames.\n\n" + "\n\n".join(per)
    )


def _ref_names(summary: Mapping[str, Any]) -> list[str]:
    return list(summary.get("reference_names", ["survival", "hindsight"]))


def _auc_all(summary: Mapping[str, Any]) -> str:
    """Every model's AUC against every reference with positives, side by side."""
    names = _ref_names(summary)
    rows = [
        [TITLES.get(m, m), *(_fmt_ci(_auc(summary, m, n)) for n in names)]
        for m in summary["models"]
    ]
    counts = summary["references"]
    header = [
        "model",
        *(f"{n} ({counts[n]['positive_agent_frames']} pos. / "
          f"{counts[n]['negative_agent_frames']} neg.)" for n in names),
    ]  # fmt: skip
    return _table(header, rows)


def _agreement_section(summary: Mapping[str, Any]) -> str:
    agree = summary.get("agreement", {})
    lines = []
    planner = agree.get("planner")
    if planner:
        imp = planner["important"]
        lines.append(
            f"Planner-important: {imp['agent_frames']} agent-frames, {imp['agents']} distinct "
            "(scene, ego, agent). What hindsight says of them:\n"
        )
        rows = []
        for h in [n for n in planner if n.startswith("hindsight")]:
            b = planner[h]
            rows.append(
                [
                    h,
                    _n(b["positive"]),
                    _n(b["negative"]),
                    _n(b["negative_yielded"]),
                    _n(b["unknown"]),
                    _n(b["unknown_yielded"]),
                    _n(b["unknown_censored"]),
                    _n(b["unknown_track_flagged"]),
                ]
            )
        lines.append(
            _table(
                [
                    "hindsight rule",
                    "positive (came close)",
                    "negative",
                    "negative, the ego yielded",
                    "unknown",
                    "unknown, the ego yielded",
                    "unknown: censored window",
                    "unknown: track flagged",
                ],
                rows,
            )
        )
        b = planner.get("hindsight")
        if b:
            lines.append(
                f"\n**Yielded count:** {b['negative_yielded']['agent_frames']} planner-important "
                f"agent-frames ({b['negative_yielded']['agents']} distinct (scene, ego, agent)) "
                "are hindsight negatives where the recorded ego braked hard or halved its "
                "speed while the agent was ahead on its path: agents the driver reacted to, "
                "which the came-close rule calls unimportant."
            )
    else:
        lines.append("No planner truth in these inputs (give the scenes with `--planner NAME`).")
    y = agree.get("yielded")
    if y and agree.get("has_yielded"):
        parts = [f"{y['all']['agent_frames']} agent-frames with the ego yielding in all"]
        for h in [n for n in y if n.startswith("hindsight")]:
            parts.append(
                f"under {h}: {y[h]['positive']['agent_frames']} positive, "
                f"{y[h]['negative']['agent_frames']} negative, {y[h]['unknown']['agent_frames']} "
                "unknown"
            )
        lines.append("\nYielded (kept apart from came-close): " + "; ".join(parts) + ".")
    pairs = agree.get("pairs", [])
    if pairs:
        lines.append(
            "\nEvery pair of references, agent-frames (rows: the first, columns: the second):\n"
        )
        rows = []
        for p in pairs:
            c = p["counts"]
            for sa in ("positive", "negative", "unknown"):
                if not any(c[f"{sa}/{sb}"] for sb in ("positive", "negative", "unknown")):
                    continue
                rows.append(
                    [f"{p['a']} {sa}", p["b"]]
                    + [str(c[f"{sa}/{sb}"]) for sb in ("positive", "negative", "unknown")]
                )
        lines.append(_table(["first", "second", "positive", "negative", "unknown"], rows))
    return "\n".join(lines)


def _n(block: Mapping[str, Any]) -> str:
    return f"{block['agent_frames']} ({block['agents']})"


def _windows_section(summary: Mapping[str, Any]) -> str:
    names = _ref_names(summary)
    hs = [n for n in names if n.startswith("hindsight")]
    lines = []
    if len(hs) == 2:
        a, b = hs
        rows = []
        for m in summary["models"]:
            x, y = _auc(summary, m, a), _auc(summary, m, b)
            rows.append([TITLES.get(m, m), _fmt_ci(x), _fmt_ci(y), _fmt(x[0] - y[0])])
        lines.append(_table(["model", f"AUC {a}", f"AUC {b}", "difference"], rows))
    else:
        lines.append(
            "Only one hindsight rule could be scored: "
            + "; ".join(
                f"{k}: {v}"
                for k, v in summary.get("references_missing", {}).items()
                if k.startswith("hindsight")
            )
        )
    comp = summary.get("composition", {})
    rows = []
    for h, block in comp.items():
        for label in ("positive", "negative"):
            c = block.get(label, {})
            rows.append(
                [
                    h, label, str(c.get("agent_frames", 0)),
                    _fmt(c.get("median_time_in_scene_s", math.nan)),
                    _fmt(c.get("share_first_2s", math.nan)),
                    _fmt(c.get("median_speed_mps", math.nan)),
                    _fmt(c.get("share_standing", math.nan)),
                ]
            )  # fmt: skip
    if rows:
        lines.append(
            "\nWhat the positives and negatives are made of (time since the scene's first "
            "frame, the agent's speed):\n"
        )
        lines.append(
            _table(
                [
                    "rule",
                    "label",
                    "agent-frames",
                    "median time in scene s",
                    "share in the first 2 s",
                    "median speed m/s",
                    "share standing (< 0.5 m/s)",
                ],
                rows,
            )
        )
    return "\n".join(lines)


def _budget_section(summary: Mapping[str, Any], plot_dir: str, pngs: list[str]) -> str:
    out = []
    for ref, rows in summary.get("budgets", {}).items():
        name = f"budget_{ref}.png"
        if name in pngs:
            out.append(f"![budgets against {ref}]({plot_dir}/{name})\n")
        ks = sorted({r["k"] for r in rows if r["kind"] == "top_k"})
        by_rule: dict[str, dict[int, Mapping[str, Any]]] = {}
        for r in rows:
            if r["kind"] == "top_k":
                by_rule.setdefault(r["rule"], {})[r["k"]] = r
        table = []
        for rule, per in by_rule.items():
            table.append([TITLES.get(rule, rule), *(_rc(per[k]) for k in ks)])
        out.append(f"Against **{ref}** ({rows[0]['positives']} positive agent-frames): share kept "
                   "at K agents per situation [95 %]:\n")  # fmt: skip
        out.append(_table(["rule", *(f"K = {k}" for k in ks)], table))
        extra = [
            f"radius {r['radius_m']:g} m keeps {r['mean_kept']:.1f} agents on average: {_rc(r)}"
            for r in rows
            if r["kind"] == "radius"
        ] + [
            f"the {r['rule']} keeps {r['mean_kept']:.1f} agents on average: {_rc(r)}"
            for r in rows
            if r["kind"] == "fixed"
        ]
        if extra:
            out.append("\n" + "; ".join(extra) + ".\n")
    return "\n".join(out) or "No budgets (no reference with positives)."


def _rc(r: Mapping[str, Any]) -> str:
    v = math.nan if r.get("value") is None else float(r["value"])
    ci = r.get("ci") or [None, None]
    if ci[0] is None or not math.isfinite(v):
        return _fmt(v)
    return f"{_fmt(v)} [{_fmt(float(ci[0]))}, {_fmt(float(ci[1]))}]"


def _tracks_section(summary: Mapping[str, Any]) -> str:
    t = summary.get("track_flags", {})
    if not t.get("available"):
        return "The inputs carry no track flags (tables written before the check existed)."
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(t["by_kind"].items())) or "none"
    shares = ", ".join(
        f"{d} {100 * v:.1f} %" for d, v in sorted(t.get("share_by_dataset", {}).items())
    )
    return (
        f"{t['agent_frames']} agent-frames ({100 * t['share']:.1f} %; {t['agents']} distinct "
        f"agents in {t['scenes']} scenes) have an ego or agent track that moves faster or "
        "accelerates harder than its kind can (or jumps) within the hindsight window; their "
        f"hindsight truth is left unknown. Per kind: {kinds}. Share per dataset: {shares}."
    )


def _auc_section(summary: Mapping[str, Any]) -> str:
    rows = []
    if "hindsight" not in _ref_names(summary):
        return "Hindsight has no positive in these inputs: no miss rate against it."
    for m in summary["models"]:
        s, h = _auc(summary, m, "survival"), _auc(summary, m, "hindsight")
        miss = summary["models"][m]["hindsight"]["miss_rate"].get(HEADLINE_THRESHOLD, {})
        rows.append(
            [
                TITLES.get(m, m),
                _fmt_ci(s),
                _fmt_ci(h),
                f"{_fmt(math.nan if miss.get('value') is None else float(miss['value']))} "
                f"({miss.get('missed_agents', 0)} (ego, agent) pairs)",
            ]
        )
    return _table(
        [
            "model",
            "AUC against survival [95 %]",
            "AUC against hindsight [95 %]",
            "miss rate against hindsight at the threshold keeping every survival positive",
        ],
        rows,
    )


def _undecided(summary: Mapping[str, Any]) -> list[str]:
    if "hindsight" not in _ref_names(summary):
        return ["anything against hindsight: no positive in these inputs"]
    a = {m: _auc(summary, m, "hindsight") for m in RANKED if m in summary["models"]}
    order = sorted(a, key=lambda m: -a[m][0] if math.isfinite(a[m][0]) else math.inf)
    out = []
    for hi, lo in itertools.pairwise(order):
        if a[hi][1] <= a[lo][2]:
            out.append(
                f"whether {TITLES[hi]} ({_fmt_ci(a[hi])}) ranks above {TITLES[lo]} "
                f"({_fmt_ci(a[lo])}) against hindsight: the intervals overlap"
            )
    refs = summary["references"]["hindsight"]
    if refs["unknown_agent_frames"]:
        share = refs["unknown_agent_frames"] / max(1, refs["agent_frames"])
        out.append(
            f"anything about the {refs['unknown_agent_frames']} censored agent-frames "
            f"({100 * share:.0f} %): the recording ends or the agent leaves before the "
            "hindsight horizon, so whether they came close is unknown"
        )
    for name, why in {
        **summary.get("references_missing", {}),
        **summary.get("references_without_positives", {}),
    }.items():
        out.append(f"anything against {name}: {why}")
    flags = summary.get("track_flags", {})
    for d, share in sorted(flags.get("share_by_dataset", {}).items()):
        if share > 0.1:
            out.append(
                f"hindsight on {d}: {100 * share:.0f} % of its agent-frames have an ego or "
                "agent track that moves faster or accelerates harder than its kind can "
                "within the window, so their truth is unknown; the recording itself is in "
                "doubt there"
            )
    if "planner" in _ref_names(summary):
        planner = summary["settings"].get("planner")
        which = f"planners other than {planner}" if planner else "other planners"
        out.append(
            f"whether the planner truth holds for {which}: the labels "
            "are one planner's reactions to the toolkit's own predictions (constant speed "
            "along each agent's path), so an agent the prediction misplaces is judged by "
            "where it was predicted, not where it went"
        )
    for grouping, blocks in summary.get("by", {}).items():
        for name, block in blocks.items():
            n = block["references"]["hindsight"]["positive_agents"]
            if n < 10:
                out.append(
                    f"any rate for {grouping} {name}: {n} positive (ego, agent) pair(s), too few"
                )
    return out


def _sweep_section(sweep: SweepResult | None, plot_dir: str) -> str:
    if sweep is None:
        return "No sensitivity sweep was run (give `--sensitivity`)."
    rank_rows = [
        [
            r["group"],
            r["variant"],
            r["reference"],
            _fmt(r["spearman"]),
            _fmt(r["kendall"]),
            str(r["flips"]),
            r["recomputed"],
        ]
        for r in sweep.variants.iter_rows(named=True)
        if r["group"] != "defaults"
    ]
    text = [
        f"![sensitivity]({plot_dir}/sensitivity.png)",
        "",
        _table(
            [
                "choice",
                "variant",
                "reference",
                "Spearman",
                "Kendall",
                "findings flipped",
                "recomputed",
            ],
            rank_rows,
        ),
    ]
    flipped = sweep.findings.filter(pl.col("flipped") & (pl.col("group") != "defaults"))
    if flipped.is_empty():
        text.append("\nNo finding flips under any variant.")
    else:
        text.append("\nFindings that flip:\n")
        for r in flipped.iter_rows(named=True):
            text.append(
                f"- {r['group']} = {r['variant']} (against {r['reference']}): *{r['finding']}* "
                f"{'holds' if r['default'] else 'does not hold'} at the defaults, "
                f"{'holds' if r['variant_holds'] else 'does not'} here."
            )
    text.append("\n" + _better_defaults(sweep))
    return "\n".join(text)


def _better_defaults(sweep: SweepResult) -> str:
    """Variants that raise the hindsight AUC of a model they recompute, with intervals
    apart from the defaults' (else: point estimate only)."""
    rows = sweep.rows.filter(pl.col("reference") == "hindsight")
    base = {
        r["model"]: (r["auc"], r["ci_lo"], r["ci_hi"])
        for r in rows.filter(pl.col("group") == "defaults").iter_rows(named=True)
    }
    lines = []
    recomputed = {
        (r["group"], r["variant"]): r["recomputed"] for r in sweep.variants.iter_rows(named=True)
    }
    for r in rows.filter(pl.col("group") != "defaults").iter_rows(named=True):
        models = recomputed.get((r["group"], r["variant"]), "")
        if r["model"] not in models.split(", "):
            continue
        b = base[r["model"]]
        if math.isfinite(r["auc"]) and r["auc"] > b[0] + 0.01:
            sure = r["ci_lo"] > b[2]
            lines.append(
                f"- {TITLES.get(r['model'], r['model'])}: {r['group']} = {r['variant']} raises "
                f"its AUC against hindsight from {_fmt(b[0])} to {_fmt(r['auc'])} "
                + ("(intervals apart)" if sure else "(intervals overlap: not decided)")
            )
    if not lines:
        return (
            "No variant raises a recomputed model's AUC against hindsight by more than 0.01: "
            "the data show no better default for filtering."
        )
    return (
        "Variants that serve filtering better against what really happened (AUC against "
        "hindsight up by more than 0.01; the paper's values stay the defaults):\n\n"
        + "\n".join(lines)
    )


def write_report(
    path: str | os.PathLike[str],
    summary: Mapping[str, Any],
    positives: pl.DataFrame,
    *,
    out_dir: str | os.PathLike[str],
    sweep: SweepResult | None = None,
    command: str = "",
    datasets: Mapping[str, str] | None = None,
    note: str = "",
    plots: Mapping[pathlib.Path, pathlib.Path] | None = None,
) -> dict[str, pathlib.Path]:
    """The report at ``path`` and its plots (copied from ``out_dir``) in the folder of
    the same name without ``.md``; each file atomically. ``plots``: the plots to copy,
    as their path in ``out_dir`` -> the file to read (a temporary file while the
    command's outputs wait to be committed together); default: the PNGs in ``out_dir``.
    Returns name -> path."""
    path = pathlib.Path(path)
    plot_dir = path.with_suffix("")
    plot_dir.mkdir(parents=True, exist_ok=True)
    written: dict[str, pathlib.Path] = {}
    if plots is None:
        plots = {p: p for p in pathlib.Path(out_dir).glob("*.png")}
    pngs = sorted(plots)
    for png in pngs:
        target = plot_dir / png.name
        with atomic_output(target) as tmp:
            shutil.copyfile(plots[png], tmp)
        written[f"report/{png.name}"] = target
    rel = plot_dir.name
    miss_plots = "\n\n".join(
        f"![{p.stem}]({rel}/{p.name})" for p in pngs if p.name.startswith("miss_rate_by_")
    )
    findings = []
    for ref in ("hindsight", "planner", "survival"):
        for name, verdict in paper_findings(summary, ref):
            findings.append([name, ref, verdict])
    cascade = summary.get("cascade", {}).get("hindsight") or []
    cascade_text = (
        ", ".join(
            f"{st['stage']}: {st['missed_agent_frames']} agent-frames ({st['missed_agents']} "
            "(ego, agent) pairs)"
            for st in cascade
        )
        or "no cascade columns"
    )
    undecided = _undecided(summary)
    ds_names = sorted(set((datasets or {}).values()))
    times = summary.get("time_s", {})
    fields = {
        "command": command or "replay evaluate ... --report",
        "when": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "python": platform.python_version(),
        "load": ", ".join(f"{x:.1f}" for x in os.getloadavg()),
        "cpus": str(os.cpu_count()),
        "datasets": ", ".join(ds_names) or "unknown",
        "scenes": str(summary["scenes"]),
        "egos": str(summary["egos"]),
        "situations": str(summary["situations"]),
        "times": ", ".join(f"{k} {v:.0f} s" for k, v in times.items()) or "not measured",
        "hindsight": ", ".join(f"{k} {v}" for k, v in (summary.get("hindsight") or {}).items())
        or "as the tables were written",
        "baseline": f"{summary['baseline']['model']} >= {summary['baseline']['threshold']:g}",
        "n_boot": str(summary["bootstrap"]["n_boot"]),
        "positives": _positives_section(positives),
        "auc_table": _auc_section(summary),
        "findings": _table(["finding of the paper", "reference", "verdict"], findings),
        "cascade": cascade_text,
        "roc_plot": f"![ROC against hindsight]({rel}/roc_hindsight.png)"
        if any(p.name == "roc_hindsight.png" for p in pngs)
        else "",
        "auc_all": _auc_all(summary)
        + (f"\n\n{bound}." if (bound := auc_bound_note(summary)) else ""),
        "agreement": _agreement_section(summary),
        "windows_section": _windows_section(summary),
        "budgets": _budget_section(summary, rel, [p.name for p in pngs]),
        "tracks": _tracks_section(summary),
        "windows": summary["settings"].get("hindsight_windows", "any"),
        "planner_note": (
            f"planner {summary['settings']['planner']}, with all agents and without each "
            "agent that could change its plan (tolerance 0.5 m)"
            if summary["settings"].get("planner")
            else (
                "from the tables' planner_label column"
                if "planner" in summary["references"]
                else "none"
            )
        ),
        "note": f"- {note}\n" if note else "",
        "absent": "; ".join(
            f"{k}: {v}"
            for k, v in {
                **summary.get("references_missing", {}),
                **summary.get("references_without_positives", {}),
            }.items()
        )
        or "none",
        "miss_plots": miss_plots or "(no plots)",
        "sweep": _sweep_section(sweep, rel),
        "undecided": "\n".join(f"- {u}" for u in undecided) or "- nothing flagged",
        "references": ", ".join(
            f"{k}: {v['positive_agent_frames']} positive / {v['negative_agent_frames']} "
            f"negative / {v['unknown_agent_frames']} unknown agent-frames"
            for k, v in summary["references"].items()
        ),
    }
    text = string.Template(TEMPLATE.read_text(encoding="utf-8")).substitute(fields)
    with atomic_output(path) as tmp:
        pathlib.Path(tmp).write_text(text, encoding="utf-8")
    written["report"] = path
    return written
