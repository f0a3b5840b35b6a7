"""How numba compiles the risk kernel (:mod:`risk.kernel_numba` lists its parts): the
cache folder, the one-time compile notice, the decorators every kernel function uses, and
numpy's pairwise summation, which the paths and the survival sum share.

Every function is ``@njit(cache=True)`` and none is recursive (a recursive cached
function crashed on cache load). The cache folder is ``NUMBA_CACHE_DIR`` when set, else a
per-user folder (``$XDG_CACHE_HOME/riskreplay/numba`` or ``~/.cache/riskreplay/numba``;
:func:`risk.kernel_shared.cache_dir`). A cold start logs one warning that it is compiling.
"""

from __future__ import annotations

import importlib.util
import logging
import pathlib
import sys
from typing import ClassVar

import numba
import numpy as np
from numba.core import event

from risk.kernel_shared import LAYOUT_KEY, PW_BLOCK, cache_dir, cache_problem

log = logging.getLogger("risk")


CACHE_DIR = cache_dir()
#: numba's cache folder inside it, one per argument layout (kernel_shared.layout_key says
#: why); read by the decorators.
JIT_CACHE_DIR = str(pathlib.Path(CACHE_DIR) / f"jit-{LAYOUT_KEY}")
numba.config.CACHE_DIR = JIT_CACHE_DIR  # type: ignore[attr-defined]
#: Why the cache folder cannot be written (None: it can); the compile notice says so.
CACHE_PROBLEM = cache_problem(CACHE_DIR)


def _answer_numba_blas_probe() -> bool:
    """Spare each process numba's BLAS probe: 0.3-0.6 s of importing ``scipy.linalg``.

    When the first kernel loads, numba's target set-up imports ``numba.np.arraymath``,
    which imports ``scipy.linalg.cython_blas`` only to learn whether ``np.dot`` and
    friends can be compiled. The kernels use no BLAS. This imports ``arraymath`` with the
    probe answered from the installed files instead (the same yes or no), then puts the
    real probe back, so that compiling code that does use BLAS still imports scipy's
    BLAS as numba expects. Does nothing (and returns False) when numba's layout differs.
    """
    if "numba.np.arraymath" in sys.modules:
        return False
    try:
        from numba.np import linalg as numba_linalg
    except ImportError:
        return False
    real_probe = getattr(numba_linalg, "ensure_blas", None)
    if real_probe is None:
        return False
    spec = importlib.util.find_spec("scipy")
    folders = list(spec.submodule_search_locations or []) if spec else []
    have_blas = any(any((pathlib.Path(f) / "linalg").glob("cython_blas.*")) for f in folders)

    def installed_probe() -> None:
        if not have_blas:
            raise ImportError("scipy 0.16+ is required for linear algebra")

    numba_linalg.ensure_blas = installed_probe
    try:
        from numba.np import arraymath
    finally:
        numba_linalg.ensure_blas = real_probe
    if getattr(arraymath, "ensure_blas", None) is installed_probe:
        arraymath.ensure_blas = real_probe
    return True


_answer_numba_blas_probe()


class _CompileNotice(event.Listener):
    """Logs once per process and module of kernels that they are being compiled (a cache
    miss): the risk kernels, or another module's that compiles with :data:`_jit`."""

    said: ClassVar[set[str]] = set()

    def on_start(self, ev: event.Event) -> None:
        data = getattr(ev, "data", None)
        data = data if isinstance(data, dict) else {}
        module = getattr(getattr(data.get("dispatcher"), "py_func", None), "__module__", "")
        module = str(module)
        if not module or module.startswith("risk"):  # unnamed: the risk kernels' notice
            what, how_long = "the risk kernels", "about 20-25 s on two cores"
        elif module.startswith(("replay.", "converters.")):
            what, how_long = f"the kernels of {module}", "a few seconds"
        else:  # numba's own helpers, compiled for one of the above
            return
        if what in _CompileNotice.said:
            return
        _CompileNotice.said.add(what)
        if CACHE_PROBLEM is None:
            log.warning(
                "riskreplay: compiling %s once (%s); later runs load them from %s",
                what,
                how_long,
                CACHE_DIR,
            )
        else:
            log.warning(
                "riskreplay: compiling %s (%s) in every run: the cache folder %s cannot be "
                "written (%s); set NUMBA_CACHE_DIR to a writable folder",
                what,
                how_long,
                CACHE_DIR,
                CACHE_PROBLEM,
            )

    def on_end(self, ev: event.Event) -> None:
        pass


event.register("numba:compile", _CompileNotice())

#: Every kernel function: cached; numpy's error model (a float division by zero gives
#: inf or NaN, as in the numpy oracle, instead of a Python ZeroDivisionError check
#: around every division).
_jit = numba.njit(cache=True, error_model="numpy")
#: The same for the inner functions, which only kernel code calls: without the Python and
#: C wrappers that numba otherwise generates and optimises for every function (0.05-0.15 s
#: of cold compile each, 3-4 s in all). Python compiles them with :func:`compile_like`.
#: (numba's own type hints leave out these two of its options.)
_inner = numba.njit(  # type: ignore[call-overload]
    cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True
)
# A bare literal passed to a kernel function (or a variable that starts as one) makes
# numba compile the callee once more, for Literal[int](0) or Literal[bool](False): seconds
# of cold compile. Where the callee is compiled for int64/bool anyway, such constants are
# written np.int64(0) / np.bool_(False). Two literal calls stay (_pw_leaf(a, 0, n) in
# np_sum, _interp(..., 0) in _cut): their speed against the plain form was within noise.


def compile_like(function: numba.core.registry.CPUDispatcher, *args: object) -> None:
    """Compile (or load from the cache) ``function`` for the types that a call with
    ``args`` would have, without calling it (an inner function cannot be called from
    Python: it has no Python wrapper)."""
    function.compile(tuple(numba.typeof(a) for a in args))


# ---------------------------------------------------------------------- summation
@_inner
def _pw_leaf(a: np.ndarray, s: int, n: int) -> float:
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[s + i]
        return res
    r0, r1, r2, r3 = a[s], a[s + 1], a[s + 2], a[s + 3]
    r4, r5, r6, r7 = a[s + 4], a[s + 5], a[s + 6], a[s + 7]
    i = 8
    stop = n - (n % 8)
    while i < stop:
        r0 += a[s + i]
        r1 += a[s + i + 1]
        r2 += a[s + i + 2]
        r3 += a[s + i + 3]
        r4 += a[s + i + 4]
        r5 += a[s + i + 5]
        r6 += a[s + i + 6]
        r7 += a[s + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[s + i]
        i += 1
    return res


@_inner
def np_sum(a: np.ndarray, n: int) -> float:
    """``a[:n].sum()`` exactly as numpy adds (pairwise), without recursion."""
    if n <= PW_BLOCK:
        return _pw_leaf(a, 0, n)
    fs = np.empty(64, np.int64)
    fn = np.empty(64, np.int64)
    stage = np.empty(64, np.int64)
    vals = np.empty(64)
    top, vtop = 0, 0
    fs[0], fn[0], stage[0] = 0, n, 0
    while top >= 0:
        s, m = fs[top], fn[top]
        if m <= PW_BLOCK:
            vals[vtop] = _pw_leaf(a, s, m)
            vtop += 1
            top -= 1
            continue
        n2 = m // 2
        n2 -= n2 % 8
        if stage[top] == 0:
            stage[top] = 1
            top += 1
            fs[top], fn[top], stage[top] = s, n2, 0
        elif stage[top] == 1:
            stage[top] = 2
            top += 1
            fs[top], fn[top], stage[top] = s + n2, m - n2, 0
        else:
            vtop -= 1
            vals[vtop - 1] = vals[vtop - 1] + vals[vtop]
            top -= 1
    return vals[0]
