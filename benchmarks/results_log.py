"""Dated results files for the benchmarks: ``benchmarks/results/<name>.md``, newest first.

``with recorded("name"):`` around a benchmark's ``main`` copies what it prints (and the
command, the date, the machine and its load before and after) into the results file, so
that the README quotes figures a benchmark wrote, never ones typed by hand.
"""

from __future__ import annotations

import contextlib
import datetime
import io
import os
import pathlib
import platform
import sys
from collections.abc import Iterator

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


class _Tee(io.TextIOBase):
    def __init__(self, *streams: io.TextIOBase) -> None:
        self.streams = streams

    def write(self, text: str) -> int:
        for stream in self.streams:
            stream.write(text)
        return len(text)

    def flush(self) -> None:
        for stream in self.streams:
            stream.flush()


def _load() -> str:
    return ", ".join(f"{v:.1f}" for v in os.getloadavg())


@contextlib.contextmanager
def recorded(name: str, title: str = "") -> Iterator[None]:
    """Print as usual, and append the printed text to ``results/<name>.md``."""
    captured = io.StringIO()
    before = _load()
    real = sys.stdout
    sys.stdout = _Tee(real, captured)  # type: ignore[assignment]
    try:
        yield
    finally:
        sys.stdout = real
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    command = " ".join(["python", *sys.argv])
    entry = (
        f"## {stamp}\n\n`{command}` ({platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}; load average {before} before, {_load()} after)\n\n"
        f"```\n{captured.getvalue().rstrip()}\n```\n"
    )
    path = RESULTS / f"{name}.md"
    head = f"# {title or name}\n\nWritten by `benchmarks/`; newest first.\n\n"
    old = path.read_text().split("\n\n", 2)[2] if path.is_file() else ""
    RESULTS.mkdir(exist_ok=True)
    path.write_text(head + entry + ("\n" + old if old else ""))
