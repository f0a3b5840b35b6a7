"""Done-markers and atomic files: what makes a batch run resumable.

Every output is written to a temporary file in its folder and renamed into place
(``os.replace``); a scene's marker is written last, after all its outputs, so a marker
that matches (see :func:`completed_scene`) means a finished scene. The rules are in the
package docstring (:mod:`replay.batch`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
from typing import Any

from outputs.atomic import atomic_output, write_text
from replay.batch.records import ConvertTask, Failure, ReplayTask, SceneDone

MARKER_FORMAT = 1


def fingerprint(path: str | os.PathLike[str]) -> tuple[int, int]:
    st = os.stat(path)
    return st.st_size, st.st_mtime_ns


def file_entry(path: str | os.PathLike[str]) -> dict[str, Any]:
    size, mtime_ns = fingerprint(path)
    return {"path": os.fspath(path), "size": size, "mtime_ns": mtime_ns}


def _entry_intact(entry: Any, *, check_time: bool = True) -> bool:
    """True when a marker's file entry (path, size, mtime_ns) still matches the file."""
    try:
        size, mtime_ns = fingerprint(entry["path"])
        return size == entry["size"] and (not check_time or mtime_ns == entry["mtime_ns"])
    except (OSError, KeyError, TypeError):
        return False


def _read_marker(path: pathlib.Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == MARKER_FORMAT else None


def completed_scene(
    marker: pathlib.Path, scene: pathlib.Path, digest: str, *, rrd: bool
) -> SceneDone | None:
    """The scene's result when its outputs are complete (rules in replay.batch), else None."""
    data = _read_marker(marker)
    if data is None or data.get("settings") != digest:
        return None
    source = data.get("scene", {})
    if source.get("path") != os.fspath(scene) or not _entry_intact(source):
        return None
    outputs = data.get("outputs", {})
    if not {"table", "frames"} <= outputs.keys() or (rrd and "recording" not in outputs):
        return None
    # Outputs are checked by size only: a copy of OUT elsewhere keeps its sizes.
    if not all(_entry_intact(e, check_time=False) for e in outputs.values()):
        return None
    try:
        return SceneDone(
            name=str(data["name"]),
            input=str(data["input"]),
            table=str(outputs["table"]["path"]),
            frames_table=str(outputs["frames"]["path"]),
            recording=str(outputs["recording"]["path"]) if "recording" in outputs else None,
            frames=int(data["frames"]),
            skipped_frames=int(data["skipped_frames"]),
            agents=int(data["agents"]),
            seconds=float(data["seconds"]),
            status="skipped",
        )
    except (KeyError, TypeError, ValueError):
        return None


def completed_conversion(
    marker: pathlib.Path, source: pathlib.Path, digest: str
) -> tuple[list[tuple[str, str]], list[Failure]] | None:
    """(scenes, failures) of a complete conversion of ``source``, else None: complete
    when the input and every other file it read are unchanged (size and time), the
    settings digest matches and every scene it wrote is still there (size and time)."""
    data = _read_marker(marker)
    if data is None or data.get("settings") != digest:
        return None
    entry = data.get("input", {})
    if entry.get("path") != os.fspath(source) or not _entry_intact(entry):
        return None
    try:
        scenes = [(str(s["name"]), str(s["path"])) for s in data["scenes"]]
        if not all(_entry_intact(e) for e in [*data["also_read"], *data["scenes"]]):
            return None
        failures = [Failure(**f) for f in data["failures"]]
    except (KeyError, TypeError, ValueError):
        return None
    return scenes, failures


def write_json(path: pathlib.Path, data: dict[str, Any]) -> None:
    """``data`` as JSON to ``path`` atomically (its folder created if needed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, json.dumps(data, indent=1, sort_keys=True) + "\n")


def write_parquet(path: pathlib.Path, df: Any) -> None:
    """A polars DataFrame to ``path`` atomically (temp file in the folder, os.replace)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(path) as tmp:
        df.write_parquet(tmp, compression="zstd")


def write_replay_marker(task: ReplayTask, done: SceneDone) -> None:
    outputs = {"table": file_entry(task.table), "frames": file_entry(task.frames_table)}
    if task.recording is not None:
        outputs["recording"] = file_entry(task.recording)
    write_json(
        pathlib.Path(task.marker),
        {
            "format": MARKER_FORMAT,
            "name": task.name,
            "input": task.input,
            "scene": file_entry(task.scene),
            "settings": task.digest,
            "outputs": outputs,
            "frames": done.frames,
            "skipped_frames": done.skipped_frames,
            "agents": done.agents,
            "seconds": round(done.seconds, 4),
        },
    )


def write_convert_marker(
    task: ConvertTask,
    scenes: list[tuple[str, str]],
    failures: list[Failure],
    also_read: list[pathlib.Path],
) -> None:
    """The marker of a conversion; ``also_read``: files besides the input that the
    conversion read (a map beside the tracks), checked like the input on resume."""
    write_json(
        pathlib.Path(task.marker),
        {
            "format": MARKER_FORMAT,
            "input": file_entry(task.input),
            "also_read": [file_entry(p) for p in also_read],
            "settings": task.digest,
            "scenes": [{"name": n, **file_entry(p)} for n, p in scenes],
            "failures": [dataclasses.asdict(f) for f in failures],
        },
    )
