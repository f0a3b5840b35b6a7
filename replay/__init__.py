"""Replay: reads MCAP scenes, drives frames through the risk models and the cascade."""

from __future__ import annotations


def __getattr__(name: str) -> str:
    # ``__version__`` on demand: importlib.metadata costs every command's start-up about
    # 25 ms (email, zipfile, ...), and only --version and batch manifests read it.
    if name != "__version__":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("riskreplay")
    except PackageNotFoundError:  # running from a source tree without installation
        return "0.0.0+unknown"
