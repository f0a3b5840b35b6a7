"""``replay inspect``: what a scene file holds, as a table or as JSON."""

from __future__ import annotations

import json
import os
import pathlib
from collections.abc import Sequence
from typing import Any

import click
import numpy as np

from converters.scene.reader import open_scene

VALUE_WIDTH = 70  # long metadata values (e.g. settings JSON) are cut in the table


@click.command("inspect")
@click.argument("scene", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (for scripts).")
def inspect_cmd(scene: pathlib.Path, as_json: bool) -> None:
    """Show what SCENE (an MCAP scene file) holds, without replaying it.

    Every frame is decoded and checked as 'replay run' checks it (paired /agents and
    /paths messages, finite times and values, unique ids, the format's limits), so a
    scene that inspect accepts is one that run accepts; otherwise it says what is wrong.

    Channels (topic, schema, message count), frames, time span and duration, agents per
    frame (min / median / max, stored and valid), the ego id and in how many frames it
    is present, the map size, the source's metadata and labels.

    \b
    Examples:
      replay inspect scene.mcap
      replay inspect scene.mcap --json | jq .agents_per_frame
    """
    info = describe(scene)
    if as_json:
        click.echo(json.dumps(info, indent=2))
    else:
        click.echo(render(info))


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
