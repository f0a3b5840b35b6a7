"""Modules loaded on first use, with the standard library's ``importlib.util.LazyLoader``.

``risk.kernel`` loads the compiled kernel (1 ms ahead of time, 0.9 s with numba just in
time); most
commands' start-up (``--help``, the converters, a process that writes output files for
the replay) never calls a model. :func:`lazy_module` gives a module object that
executes the module the first time one of its attributes is used.
"""

from __future__ import annotations

import importlib.util
import sys
import types


def lazy_module(name: str) -> types.ModuleType:
    """``name``, imported on its first attribute access (at once if already imported)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        raise ImportError(f"no module named {name!r}")
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module
