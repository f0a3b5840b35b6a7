"""Driving risk models for importance filtering (Puphal et al., ICRAE 2022).

numpy and a compiled numba kernel (risk.kernel: ahead of time when built, else just in
time), no I/O but the kernel cache. The notebook
entry point::

    from risk import Frame, evaluate, MODELS

    frame = Frame.from_arrays(xy, heading, speed, length, width, paths, ego=0)
    risks = evaluate(frame)            # {"current_distance": (N,), ..., "survival": (N,)}
    important = baseline_mask(risks[BASELINE_MODEL])
"""

from risk.cascade import CascadeConfig
from risk.errors import FrameError, RiskError, UnknownModelError
from risk.evaluation import evaluate_references, pooled_roc
from risk.filtering import FilterResult, filter_frame, parse_filter
from risk.frame import KIND_NAMES, Frame, Kind, Lane, LaneMap, MapLine, Scene
from risk.hindsight import HindsightSettings, Tracks, Truth, hindsight_truth
from risk.prediction import (
    FrameContext,
    KindUncertainty,
    PredictionSettings,
    UncertaintyTable,
)
from risk.registry import (
    BASELINE_MODEL,
    BASELINE_THRESHOLD,
    MODELS,
    ModelSpec,
    baseline_mask,
    evaluate,
)

# The compiled kernel's module, loaded (numba) on first use: bound here so that
# ``from risk import kernel`` does not make the import system load it (risk/lazy.py).
from risk.registry import kernel as kernel

__all__ = [
    "BASELINE_MODEL",
    "BASELINE_THRESHOLD",
    "KIND_NAMES",
    "MODELS",
    "CascadeConfig",
    "FilterResult",
    "Frame",
    "FrameContext",
    "FrameError",
    "HindsightSettings",
    "Kind",
    "KindUncertainty",
    "Lane",
    "LaneMap",
    "MapLine",
    "ModelSpec",
    "PredictionSettings",
    "RiskError",
    "Scene",
    "Tracks",
    "Truth",
    "UncertaintyTable",
    "UnknownModelError",
    "baseline_mask",
    "evaluate",
    "evaluate_references",
    "filter_frame",
    "hindsight_truth",
    "parse_filter",
    "pooled_roc",
]
