"""What the kernel's two compiled forms share, without importing numba: the layout of its
arguments (model slots, parameter vectors, constants) and the cache folder.

The kernel's code is :mod:`risk.kernel_numba`; numba compiles it just in time
(``cache=True``), or :mod:`risk.kernel_aot` compiles it ahead of time into an extension
module. :mod:`risk.kernel` loads one of the two.
"""

from __future__ import annotations

import math
import os
import pathlib
import platform
import sys
import tempfile

# Model slots, in registry order.
CUR, PATH, TRAJ, ENC, HW, H2D, CIRC, GAUSS, SURV = range(9)
N_MODELS = 9
# Float parameters.
F_EPS = 0  # 9 slots: eps of CUR, PATH, TRAJ, ENC, HW, H2D, CIRC (others unused)
F_LIM_ENC, F_LIM_HW, F_LIM_H2D = 9, 10, 11  # count an encounter when s_E < this
F_TAU_HW, F_TAU_H2D = 12, 13
F_TOL_HW, F_TOL_H2D = 14, 15
F_SCALE_CIRC = 16
F_DT_TAU = 17  # dt / tau_esc
N_FLOAT = 18
# Integer parameters.
I_NCIRC, I_RADIUS_RULE = 0, 1
N_INT = 2

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
