"""Failures of per-scene work: the record (a row of ``failures.csv``), the one-line reason
made from an exception, and the file. Shared by ``replay batch`` and the job runner."""

from __future__ import annotations

import csv
import io
import os
import pathlib
import traceback
from collections.abc import Iterable, Sequence
from dataclasses import astuple, dataclass
from typing import Any

from converters.scene.errors import SceneFormatError
from outputs.atomic import write_text
from risk.errors import RiskReplayError

FAILURE_COLUMNS: tuple[str, ...] = ("input", "scene", "stage", "error_type", "reason")


@dataclass(frozen=True)
class Failure:
    """One failed scene (or input): a row of ``failures.csv``."""

    input: str  # the file the user's inputs named
    scene: str  # the scene's name or key; "" when the whole input failed before naming scenes
    stage: str  # where it failed (replay.batch.STAGES; the job runner: read, run, write, worker)
    error_type: str  # exception class name
    reason: str  # one line


def one_line(text: str, limit: int = 400) -> str:
    line = " ".join(text.split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def failure_from(input_: str, scene: str, stage: str, exc: BaseException) -> Failure:
    """A Failure from an exception; the stage follows the exception type where it says
    more than the step we were in (a damaged MCAP found mid-replay is a read error)."""
    # Imported on a failure only: the recordings package loads rerun (about 1 s with
    # ``python -X importtime``), which a worker that writes no recording need not pay.
    from recordings.errors import RecordingError

    if isinstance(exc, SceneFormatError):
        stage = "read"
    elif isinstance(exc, RecordingError):
        stage = "record"
    reason = one_line(str(exc)) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in reason:
        reason = f"{reason}: {exc.filename}"
    if not isinstance(exc, (RiskReplayError, OSError)):
        reason += _where(exc)  # an unexpected error: say where, for a bug report
    return Failure(input_, scene, stage, type(exc).__name__, reason)


def worker_failure(input_: str, scene: str, exc: BaseException) -> Failure:
    """The failure of a task whose worker did not come back (died, lost by Ray)."""
    reason = one_line(str(exc)) or type(exc).__name__
    return Failure(input_, scene, "worker", type(exc).__name__, reason)


def _where(exc: BaseException) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return ""
    last = frames[-1]
    return f" (at {pathlib.Path(last.filename).name}:{last.lineno} in {last.name})"


def write_failures(path: pathlib.Path, failures: Iterable[Failure]) -> None:
    """``failures.csv``: one row per failure (a header only when nothing failed)."""
    rows = [astuple(f) for f in failures]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, csv_text(FAILURE_COLUMNS, rows))


def read_failures(path: str | os.PathLike[str]) -> list[Failure]:
    """The rows of a ``failures.csv``."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [Failure(**row) for row in csv.DictReader(fh)]


def csv_text(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buf.getvalue()
