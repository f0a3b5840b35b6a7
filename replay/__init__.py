"""Replay: reads MCAP scenes, drives frames through the risk models and the cascade."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("riskreplay")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"
