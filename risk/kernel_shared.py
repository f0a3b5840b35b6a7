"""What the kernel's two compiled forms share, without importing numba: the layout of its
arguments (model slots and parameter vectors, generated from :mod:`risk.registry`),
constants and the cache folder.

The kernel's code is :mod:`risk.kernel_numba`; numba compiles it just in time
(``cache=True``), or :mod:`risk.kernel_aot` compiles it ahead of time into an extension
module. :mod:`risk.kernel` loads one of the two.
"""

from __future__ import annotations

import hashlib
import math
import os
import pathlib
import platform
import sys
import tempfile

from risk.registry import MODELS

# ---------------------------------------------------------------- the generated layout
# Everything model-specific in the kernel's arguments comes from the registry
# (:class:`risk.registry.KernelArgs`): a model's slot is its place in registry order
# (the rows of the kernel's ``(models, N)`` result and of its ``want`` flags), and each
# model's numbers sit model after model in the float and int parameter vectors.
#: Model names in slot order (registry order).
SLOTS: tuple[str, ...] = tuple(MODELS)
N_MODELS = len(SLOTS)
SLOT: dict[str, int] = {name: slot for slot, name in enumerate(SLOTS)}


def _layout(kind: str) -> dict[tuple[str, str], int]:
    """(model, number's name) -> its index in the ``kind`` ("floats"/"ints") vector."""
    at: dict[tuple[str, str], int] = {}
    for name, spec in MODELS.items():
        for arg in getattr(spec.kernel_args, kind):
            at[name, arg] = len(at)
    return at


#: Where each model's float and int numbers sit in the kernel's parameter vectors.
FLOAT_AT = _layout("floats")
INT_AT = _layout("ints")
N_FLOAT = max(len(FLOAT_AT), 1)
N_INT = max(len(INT_AT), 1)


def layout_key(
    slots: tuple[str, ...], float_at: dict[tuple[str, str], int], int_at: dict[tuple[str, str], int]
) -> str:
    """A short hash of a layout. numba's cache checks only the changed source file of a
    function, not the constants it read from other modules, so the just-in-time cache
    lives in a folder per layout (:mod:`risk.kernel_jit`): a registry that adds or moves
    a model never loads code compiled for another layout."""
    text = repr((slots, sorted(float_at.items()), sorted(int_at.items())))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


#: This registry's layout (:func:`layout_key`).
LAYOUT_KEY = layout_key(SLOTS, FLOAT_AT, INT_AT)

# The kernel code's names for the slots and numbers it reads (numba freezes module-level
# integers into the compiled code as constants). A model's kernel function names its own.
CUR, PATH, TRAJ = SLOT["current_distance"], SLOT["path_distance"], SLOT["trajectory_distance"]
ENC, HW, H2D = SLOT["closest_encounter"], SLOT["headway"], SLOT["headway_2d"]
CIRC, GAUSS, SURV = SLOT["circles"], SLOT["gaussian"], SLOT["survival"]
EPS_CUR = FLOAT_AT["current_distance", "epsilon"]
EPS_PATH = FLOAT_AT["path_distance", "epsilon"]
EPS_TRAJ = FLOAT_AT["trajectory_distance", "epsilon"]
EPS_ENC = FLOAT_AT["closest_encounter", "epsilon"]
LIM_ENC = FLOAT_AT["closest_encounter", "encounter_limit"]  # an encounter counts if s_E < this
EPS_HW = FLOAT_AT["headway", "epsilon"]
LIM_HW = FLOAT_AT["headway", "encounter_limit"]
TAU_HW = FLOAT_AT["headway", "tau"]
TOL_HW = FLOAT_AT["headway", "on_path_tolerance"]
EPS_H2D = FLOAT_AT["headway_2d", "epsilon"]
LIM_H2D = FLOAT_AT["headway_2d", "encounter_limit"]
TAU_H2D = FLOAT_AT["headway_2d", "tau"]
TOL_H2D = FLOAT_AT["headway_2d", "on_path_tolerance"]
EPS_CIRC = FLOAT_AT["circles", "epsilon"]
SCALE_CIRC = FLOAT_AT["circles", "sigma_scale"]
N_CIRC = INT_AT["circles", "n_circles"]
RADIUS_RULE = INT_AT["circles", "radius_rule"]  # index into registry.RADIUS_RULES
DT_TAU = FLOAT_AT["survival", "dt_over_escape_time"]

#: What the corridor stage (risk.kernel_corridor.corridor_keep) says of an agent: nothing
#: (the other stages judge it), kept as an in-corridor leader, kept as a path crossing
#: into the corridor, dropped as a follower that cannot reach the ego within the horizon.
NOT_KEPT, LEADER, CROSSING, BEHIND = 0, 1, 2, 3

#: Segments per chunk of the bounding-box pruning (as risk.geometry.CHUNK_SEGMENTS).
K = 8
#: Numpy's pairwise summation block (numpy/core/src/umath/loops_utils.h).
PW_BLOCK = 128
TIE = 1e-9  # risk.temporal.TIE_TOLERANCE_M
#: exp(x) is exactly 0 in float64 below about -745.13; a margin keeps it exact.
EXP_ZERO = -760.0
INF = math.inf

#: Whether :func:`cascade_agents` may run here: it reads the cycle counter
#: (``llvm.readcyclecounter``), which is the TSC on x86 but traps in user space on other
#: CPUs (e.g. ``PMCCNTR_EL0`` on AArch64). Elsewhere the cascade times one call per stage.
HAVE_CYCLE_COUNTER = platform.machine().lower() in {"x86_64", "amd64", "i386", "i686", "x86"}


def default_cache_dir() -> pathlib.Path:
    """The per-user kernel cache folder used when ``NUMBA_CACHE_DIR`` is not set."""
    if sys.platform == "win32":
        base = pathlib.Path(os.environ.get("LOCALAPPDATA") or pathlib.Path.home() / "AppData")
    else:
        base = pathlib.Path(os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache")
    return base / "riskreplay" / "numba"


def cache_dir() -> str:
    """``NUMBA_CACHE_DIR`` when set, else :func:`default_cache_dir`; exported to the
    environment so that worker processes share the folder."""
    path = os.environ.get("NUMBA_CACHE_DIR") or str(default_cache_dir())
    os.environ["NUMBA_CACHE_DIR"] = path
    return path


def cache_problem(path: str) -> str | None:
    """Why the cache folder ``path`` cannot be written, or None when it can. numba then
    caches nothing, silently, and compiles the kernels again in every process."""
    try:
        os.makedirs(path, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".riskreplay-probe-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    return None
