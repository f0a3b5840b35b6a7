"""The kernel's code, gathered: the compiled production path of :func:`risk.evaluate` and
of the fused cascade. :mod:`risk.kernel` loads it (compiled ahead of time by
:mod:`risk.kernel_aot`, or just in time here); call it through that module.

Its parts, by job (:data:`PARTS`): :mod:`risk.kernel_jit` (how numba compiles it, and
numpy's summation), :mod:`risk.kernel_paths` (path geometry and distances),
:mod:`risk.kernel_prediction` (prediction and the ego's candidates),
:mod:`risk.kernel_overlap` (the Gaussian overlap and survival analysis),
:mod:`risk.kernel_evaluate` (every model, :func:`evaluate_agents`) and
:mod:`risk.kernel_cascade` (the bound, the tier sort and the fused cascade) and
:mod:`risk.kernel_corridor` (the corridor stage). This module
names every compiled function of them, so that :mod:`risk.kernel` warms them up by name.

One pass per agent row: for each path candidate of each requested agent the kernel

1. extends the path straight to ``v T`` (and cuts it at ``v T`` when trajectory distance
   is asked for);
2. predicts it at constant speed along the path, with the per-kind covariances;
3. runs every requested model against every ego candidate: exact segment distances
   pruned by chunk bounding boxes, the closest encounter, headway and 2D headway, the
   circles, and one loop for the Gaussian overlap and survival analysis.

Everything per row lives in scratch buffers of one path or one horizon (a few kB), so
nothing grows with ``N^2`` and memory stays cache-sized; only the ego's candidates are
kept for the whole call. The maths follows the vectorised numpy modules
(:mod:`risk.distance`, :mod:`risk.temporal`, :mod:`risk.stochastic`, :mod:`risk.prediction`)
operation by operation, including numpy's pairwise summation, so that the results agree
with them within a few ulps, mostly bit for bit (numpy's AVX-512 ``exp`` differs from the C
library's in the last bit; the pruned distance search may round a least distance another
way; tests/exactness.py); those modules and :mod:`risk.reference` are the oracles the
tests compare with.

Compile cost: see :mod:`risk.kernel_jit`.
"""

from __future__ import annotations

from risk import (
    kernel_cascade,
    kernel_corridor,
    kernel_evaluate,
    kernel_jit,
    kernel_overlap,
    kernel_paths,
    kernel_prediction,
)
from risk.kernel_cascade import (
    _cycles,
    _gauss_reaches,
    _reach_keep,
    _reach_limits,
    cascade_agents,
    reachable,
    tiers,
)
from risk.kernel_corridor import (
    _at_arc,
    _corridor_line,
    _corridor_project,
    _corridor_range,
    _line_box,
    corridor_keep,
)
from risk.kernel_evaluate import (
    _time_gap,
    evaluate_agents,
)
from risk.kernel_jit import (
    CACHE_DIR,
    CACHE_PROBLEM,
    _CompileNotice,
    _pw_leaf,
    compile_like,
    np_sum,
)
from risk.kernel_overlap import (
    _escape_track,
    _overlap_risks,
    _pair_q,
)
from risk.kernel_paths import (
    _boxes,
    _chunk_box,
    _cut,
    _cut_boxes,
    _extend,
    _first_crossing,
    _gap2,
    _interp,
    _polyline_distance,
    _project,
    _pseg2,
    _segment_lengths,
    _segments,
    _sign,
    _touch0,
)
from risk.kernel_prediction import (
    _ego_candidates,
    _others,
    _predict,
    _row_starts,
)

#: The kernel's modules (their compiled functions are all named here).
PARTS = (
    kernel_jit,
    kernel_paths,
    kernel_prediction,
    kernel_overlap,
    kernel_evaluate,
    kernel_cascade,
    kernel_corridor,
)

__all__ = [
    "CACHE_DIR",
    "CACHE_PROBLEM",
    "PARTS",
    "_CompileNotice",
    "_at_arc",
    "_boxes",
    "_chunk_box",
    "_corridor_line",
    "_corridor_project",
    "_corridor_range",
    "_cut",
    "_cut_boxes",
    "_cycles",
    "_ego_candidates",
    "_escape_track",
    "_extend",
    "_first_crossing",
    "_gap2",
    "_gauss_reaches",
    "_interp",
    "_line_box",
    "_others",
    "_overlap_risks",
    "_pair_q",
    "_polyline_distance",
    "_predict",
    "_project",
    "_pseg2",
    "_pw_leaf",
    "_reach_keep",
    "_reach_limits",
    "_row_starts",
    "_segment_lengths",
    "_segments",
    "_sign",
    "_time_gap",
    "_touch0",
    "cascade_agents",
    "compile_like",
    "corridor_keep",
    "evaluate_agents",
    "np_sum",
    "reachable",
    "tiers",
]
