"""``replay inspect``: what a scene file holds, as a table or as JSON."""

from __future__ import annotations

import json
import os
import pathlib
from collections.abc import Sequence
from typing import Any

import click
import numpy as np

from converters.clock import (
    BAD_ROW_LIMIT,
    MOVING_SPEED_MS,
    RATIO_TOLERANCE,
    check_motion,
    motion_from_frames,
)
from converters.scene.reader import open_scene
from replay.errors import ReplayError

VALUE_WIDTH = 70  # long metadata values (e.g. settings JSON) are cut in the table


@click.command("inspect")
@click.argument(
    "scenes",
    metavar="SCENE...",
    nargs=-1,
    required=True,
    type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path),
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (for scripts).")
@click.option(
    "--check",
    is_flag=True,
    help="Check each scene's clock against its motion (converters.clock) and print the "
    "figures per scene and per dataset (the scene's folder); exit 1 when a scene fails.",
)
def inspect_cmd(scenes: tuple[pathlib.Path, ...], as_json: bool, check: bool) -> None:
    """Show what SCENE (an MCAP scene file) holds, without replaying it.

    Every frame is decoded and checked as 'replay run' checks it (paired /agents and
    /paths messages, finite times and values, unique ids, the format's limits), so a
    scene that inspect accepts is one that run accepts; otherwise it says what is wrong.

    Channels (topic, schema, message count), frames, time span and duration, agents per
    frame (min / median / max, stored and valid), the ego id and in how many frames it
    is present, the map size, the source's metadata and labels.

    With --check (any number of scenes): the clock check of docs/recorded-data.md, per
    scene and per dataset (scenes grouped by their folder): the clock ratio (positions
    over recorded speeds, agents above 2 m/s) now and at the file's time step, whether
    the time step was corrected and from what, the share of heading mismatches, speed and
    acceleration bound violations, teleports and the share of bad rows. A scene fails
    when its ratio is more than 5 % off 1 or more than 5 % of its rows are bad; the
    command then exits with status 1.

    \b
    Examples:
      replay inspect scene.mcap
      replay inspect scene.mcap --json | jq .agents_per_frame
      replay inspect --check scenes/*/*.mcap
    """
    if check:
        _check(scenes, as_json)
        return
    if len(scenes) != 1:
        raise click.UsageError("give one SCENE (several only with --check)")
    info = describe(scenes[0])
    if as_json:
        click.echo(json.dumps(info, indent=2))
    else:
        click.echo(render(info))


def _check(scenes: Sequence[pathlib.Path], as_json: bool) -> None:
    results = [clock_figures(p) for p in scenes]
    datasets = dataset_figures(results)
    failing = [r for r in results if r["fails"]]
    if as_json:
        click.echo(json.dumps({"scenes": results, "datasets": datasets,
                               "thresholds": CHECK_THRESHOLDS, "failing": len(failing)},
                              indent=2))  # fmt: skip
    else:
        click.echo(render_check(results, datasets))
    if failing:
        raise ReplayError(
            f"{len(failing)} of {len(results)} scene(s) fail the clock check: "
            + ", ".join(str(r["path"]) for r in failing[:3])
            + (" ..." if len(failing) > 3 else "")
        )


CHECK_THRESHOLDS = {
    "ratio_tolerance": RATIO_TOLERANCE,
    "bad_row_limit": BAD_ROW_LIMIT,
    "moving_speed_ms": MOVING_SPEED_MS,
}


def clock_figures(path: pathlib.Path) -> dict[str, Any]:
    """The clock check of one scene file: measured on its frames at its frame period,
    with what the conversion measured at the file's time step (metadata ``clock_check``)."""
    reader = open_scene(path)
    meta = reader.metadata
    try:
        at_conversion = json.loads(meta.get("clock_check", "null"))
    except ValueError:
        at_conversion = None
    if not isinstance(at_conversion, dict):
        at_conversion = {}
    recorded = bool(at_conversion.get("speeds_recorded", True))
    frames = [e.frame for e in reader.entries(any_ego=True) if e.frame is not None]
    now = check_motion(
        motion_from_frames(frames, speeds_recorded=recorded), reader.frame_period_s, "file"
    )
    corrected_from = meta.get("time_step_corrected_from")
    return {
        "path": str(path),
        "dataset": path.absolute().parent.name,
        "step_s": reader.frame_period_s,
        "time_step_corrected_from": None if corrected_from is None else float(corrected_from),
        "ratio_at_file_step": at_conversion.get("ratio_file", now.ratio),
        "ratio": now.ratio,
        "speeds_recorded": recorded,
        "agents_measured": now.agents_measured,
        "heading_mismatch_share": now.heading_mismatch_share,
        "speed_violations": now.speed_violations,
        "accel_violations": now.accel_violations,
        "teleports": now.teleports,
        "rows": now.rows,
        "bad_rows": now.bad_rows,
        "bad_row_share": now.bad_row_share,
        "fails": now.fails,
        "reasons": list(now.reasons),
    }


def dataset_figures(results: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per dataset (scene folder): counts and the spread of the figures."""
    out = []
    for name in sorted({r["dataset"] for r in results}):
        rows = [r for r in results if r["dataset"] == name]
        corrected = [r for r in rows if r["time_step_corrected_from"] is not None]
        out.append(
            {
                "dataset": name,
                "scenes": len(rows),
                "corrected": len(corrected),
                "corrections": sorted(
                    {f"{r['time_step_corrected_from']:g} -> {r['step_s']:g} s" for r in corrected}
                ),
                "ratio_at_file_step": _range([r["ratio_at_file_step"] for r in rows]),
                "ratio": _range([r["ratio"] for r in rows]),
                "bad_row_share": _range([r["bad_row_share"] for r in rows]),
                "heading_mismatch_share": _range([r["heading_mismatch_share"] for r in rows]),
                "speed_violations": sum(r["speed_violations"] for r in rows),
                "accel_violations": sum(r["accel_violations"] for r in rows),
                "teleports": sum(r["teleports"] for r in rows),
                "failing": sum(r["fails"] for r in rows),
            }
        )
    return out


def _range(values: Sequence[float | None]) -> dict[str, float] | None:
    known = [v for v in values if v is not None]
    if not known:
        return None
    return {"min": min(known), "median": float(np.median(known)), "max": max(known)}


def render_check(results: Sequence[dict[str, Any]], datasets: Sequence[dict[str, Any]]) -> str:
    """The tables of ``inspect --check``: one row per scene, one per dataset."""
    head: tuple[str, ...] = ("scene", "step s", "from s", "ratio file", "ratio", "agents", "heading",
            "speed>", "accel>", "teleports", "bad rows", "check")  # fmt: skip
    rows: list[tuple[str, ...]] = [head]
    for r in results:
        rows.append(
            (
                pathlib.Path(r["path"]).stem,
                f"{r['step_s']:g}",
                ""
                if r["time_step_corrected_from"] is None
                else f"{r['time_step_corrected_from']:g}",
                _num(r["ratio_at_file_step"]),
                _num(r["ratio"]) if r["speeds_recorded"] else "no speeds",
                str(r["agents_measured"]),
                _share(r["heading_mismatch_share"]),
                str(r["speed_violations"]),
                str(r["accel_violations"]),
                str(r["teleports"]),
                _share(r["bad_row_share"]),
                "FAIL: " + "; ".join(r["reasons"]) if r["fails"] else "ok",
            )
        )
    out = _table(rows)
    head = ("dataset", "scenes", "corrected", "ratio file (med, min-max)",
            "ratio (med, min-max)", "bad rows max", "heading max", "teleports", "failing")  # fmt: skip
    rows = [head]
    for d in datasets:
        fixes = ", ".join(d["corrections"])
        rows.append(
            (
                d["dataset"],
                str(d["scenes"]),
                f"{d['corrected']}" + (f" ({fixes})" if fixes else ""),
                _spread_text(d["ratio_at_file_step"]),
                _spread_text(d["ratio"]),
                _share(d["bad_row_share"]["max"] if d["bad_row_share"] else None),
                _share(d["heading_mismatch_share"]["max"] if d["heading_mismatch_share"] else None),
                str(d["teleports"]),
                str(d["failing"]),
            )
        )
    return out + "\n\nper dataset\n" + _table(rows, indent=2)


def _num(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _share(value: float | None) -> str:
    return "-" if value is None else f"{value:.1%}"


def _spread_text(spread: dict[str, float] | None) -> str:
    if spread is None:
        return "-"
    return f"{spread['median']:.2f} ({spread['min']:.2f}-{spread['max']:.2f})"


def describe(path: pathlib.Path) -> dict[str, Any]:
    """Everything ``inspect`` reports, as plain JSON-able values."""
    reader = open_scene(path)
    stats = reader.frame_stats()
    n_checked = sum(1 for _ in reader.entries())  # decodes every frame, as `replay run` does
    ego_ids = sorted({int(e) for e in stats.ego_id})
    return {
        "path": str(path),
        "size_bytes": os.path.getsize(path),
        "writer": reader.library,
        "format_version": int(reader.metadata.get("format_version", "0")),
        "frames": reader.n_frames,
        "frame_period_s": reader.frame_period_s,
        "duration_s": reader.duration_s,
        "t_first_s": float(stats.t_s[0]),
        "t_last_s": float(stats.t_s[-1]),
        "agents_per_frame": _spread(stats.n_agents),
        "valid_agents_per_frame": _spread(stats.n_valid),
        "ego_ids": ego_ids,
        "frames_with_ego": int(stats.ego_present.sum()),
        "frames_checked": n_checked,
        "lanes": len(reader.map.lanes),
        "channels": [
            {
                "topic": c.topic,
                "schema": c.schema_name,
                "encoding": c.message_encoding,
                "messages": c.message_count,
            }
            for c in reader.channels
        ],
        "metadata": dict(reader.metadata),
        "labels": {name: list(ids) for name, ids in reader.labels.items()},
    }


def _spread(values: np.ndarray) -> dict[str, float]:
    return {
        "min": int(values.min()),
        "median": float(np.median(values)),
        "max": int(values.max()),
    }


def render(info: dict[str, Any]) -> str:
    """The human-readable table of :func:`describe`'s result."""
    stored, valid = info["agents_per_frame"], info["valid_agents_per_frame"]
    ego = ", ".join(str(e) for e in info["ego_ids"])
    rows = [
        ("file", f"{info['path']}  ({_size(info['size_bytes'])}, {info['writer'] or 'unknown writer'})"),
        ("format version", str(info["format_version"])),
        ("frames", f"{info['frames']} at {info['frame_period_s']:g} s"),
        ("duration", f"{info['duration_s']:g} s  (t = {info['t_first_s']:g} .. {info['t_last_s']:g} s)"),
        ("agents/frame", f"{_mmm(stored)} stored, {_mmm(valid)} valid  (min / median / max)"),
        ("ego", f"id {ego}  (a valid agent in {info['frames_with_ego']} of {info['frames']} frames)"),
        ("map", f"{info['lanes']} lanes"),
    ]  # fmt: skip
    out = _table(rows)
    out += "\n\nchannels\n" + _table(
        [("topic", "schema", "messages")]
        + [(c["topic"], c["schema"], str(c["messages"])) for c in info["channels"]],
        indent=2,
    )
    if info["metadata"]:
        out += "\n\nsource metadata\n" + _table(
            [(k, _cut(v)) for k, v in sorted(info["metadata"].items())], indent=2
        )
    if info["labels"]:
        out += "\n\nlabels\n" + _table(
            [
                (k, _cut(f"{len(v)} agents: " + ", ".join(map(str, v))))
                for k, v in info["labels"].items()
            ],
            indent=2,
        )
    return out


def _table(rows: Sequence[tuple[str, ...]], indent: int = 0) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = []
    for row in rows:
        cells = [cell.ljust(w) for cell, w in zip(row[:-1], widths, strict=False)] + [row[-1]]
        lines.append(" " * indent + "  ".join(cells).rstrip())
    return "\n".join(lines)


def _mmm(spread: dict[str, float]) -> str:
    return f"{spread['min']} / {spread['median']:g} / {spread['max']}"


def _cut(text: str) -> str:
    return text if len(text) <= VALUE_WIDTH else text[: VALUE_WIDTH - 3] + "..."


def _size(n_bytes: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n_bytes < 1024 or unit == "GiB":
            return f"{n_bytes:.0f} {unit}" if unit == "B" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1024
    raise AssertionError("unreachable")
