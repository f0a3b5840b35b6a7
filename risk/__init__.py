"""Driving risk models for importance filtering (Puphal et al., ICRAE 2022).

numpy and a compiled numba kernel (risk.kernel: ahead of time when built, else just in
time), no I/O but the kernel cache. The notebook
entry point::

    from risk import Frame, evaluate, MODELS

    frame = Frame.from_arrays(xy, heading, speed, length, width, paths, ego=0)
    risks = evaluate(frame)            # {"current_distance": (N,), ..., "survival": (N,)}
    important = baseline_mask(risks[BASELINE_MODEL])
"""

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from risk.cascade import CascadeConfig
    from risk.errors import FrameError, RiskError, RiskReplayError, UnknownModelError
    from risk.evaluation import evaluate_references, pooled_roc
    from risk.filtering import FilterResult, filter_frame, parse_filter
    from risk.frame import KIND_NAMES, Frame, Kind, Lane, LaneMap, MapLine, Scene
    from risk.hindsight import HindsightSettings, Tracks, Truth, hindsight_truth
    from risk.prediction import FrameContext, KindUncertainty, PredictionSettings, UncertaintyTable
    from risk.registry import (
        BASELINE_MODEL,
        BASELINE_THRESHOLD,
        MODELS,
        ModelSpec,
        baseline_mask,
        evaluate,
    )
    from risk.registry import (
        kernel as kernel,
    )

# Each name is loaded from its module on first use (PEP 562), so that ``import
# risk.errors`` (the one error base, imported by the output process and the command
# line's start-up) does not load numpy and the models (0.25 s with ``python -X
# importtime``). ``from risk import kernel`` gives the compiled kernel's module, itself
# loaded (numba) on first use (risk/lazy.py).
_WHERE: dict[str, str] = {
    **dict.fromkeys(
        ("FrameError", "RiskError", "RiskReplayError", "UnknownModelError"), "risk.errors"
    ),
    **dict.fromkeys(("evaluate_references", "pooled_roc"), "risk.evaluation"),
    "CascadeConfig": "risk.cascade",
    **dict.fromkeys(("FilterResult", "filter_frame", "parse_filter"), "risk.filtering"),
    **dict.fromkeys(
        ("KIND_NAMES", "Frame", "Kind", "Lane", "LaneMap", "MapLine", "Scene"), "risk.frame"
    ),
    **dict.fromkeys(("HindsightSettings", "Tracks", "Truth", "hindsight_truth"), "risk.hindsight"),
    **dict.fromkeys(
        ("FrameContext", "KindUncertainty", "PredictionSettings", "UncertaintyTable"),
        "risk.prediction",
    ),
    **dict.fromkeys(
        (
            "BASELINE_MODEL",
            "BASELINE_THRESHOLD",
            "MODELS",
            "ModelSpec",
            "baseline_mask",
            "evaluate",
            "kernel",
        ),
        "risk.registry",
    ),
}


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])


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
    "RiskReplayError",
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
