"""How much memory a computation may take: refuse, naming the limit, before allocating.

A single bad number in a scene or an option (a frame period of 1e-12 s, a path of two
million points) can size an array far beyond the machine. Such inputs are refused with
:class:`MemoryLimitError` (one line for the user) instead of a ``MemoryError`` after
minutes or the out-of-memory killer. The limit is the memory available now (Linux
``MemAvailable``; elsewhere the physical memory), or ``RISKREPLAY_MEMORY_LIMIT_GB`` when
set (lower it to keep room for other work). Standard library only (and the error base).
"""

from __future__ import annotations

import os

from risk.errors import RiskReplayError

LIMIT_ENV = "RISKREPLAY_MEMORY_LIMIT_GB"
GIB = 1024**3


class MemoryLimitError(RiskReplayError):
    """The input or option would need more memory than the limit (the message says which
    and what to do)."""


def available_bytes() -> int | None:
    """Memory this process may still take: ``RISKREPLAY_MEMORY_LIMIT_GB`` if set, else
    ``MemAvailable`` of /proc/meminfo, else the physical memory (None if unknown)."""
    text = os.environ.get(LIMIT_ENV, "").strip()
    if text:
        try:
            value = float(text)
        except ValueError:
            value = -1.0
        if value > 0:
            return int(value * GIB)
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (OSError, ValueError, AttributeError):
        return None


def format_bytes(n: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"


def check_fits(nbytes: float, what: str, hint: str) -> None:
    """Raise :class:`MemoryLimitError` when ``nbytes`` exceed the available memory.

    ``what``: the thing that needs it (naming the input); ``hint``: what to do."""
    limit = available_bytes()
    if limit is None or nbytes <= limit:
        return
    source = f"{LIMIT_ENV}" if os.environ.get(LIMIT_ENV, "").strip() else "available memory"
    raise MemoryLimitError(
        f"{what} would need {format_bytes(nbytes)}, more than the {format_bytes(limit)} of"
        f" {source}; {hint}"
    )
