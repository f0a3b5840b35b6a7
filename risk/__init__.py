"""Driving risk models for importance filtering (Puphal et al., ICRAE 2022).

Pure numpy, no I/O. The notebook entry point::

    from risk import Frame, evaluate, MODELS
"""

from risk.errors import FrameError, RiskError, UnknownModelError
from risk.frame import KIND_NAMES, Frame, Kind, Lane, LaneMap, Scene

__all__ = [
    "KIND_NAMES",
    "Frame",
    "FrameError",
    "Kind",
    "Lane",
    "LaneMap",
    "RiskError",
    "Scene",
    "UnknownModelError",
]
