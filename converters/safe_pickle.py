"""Load a ScenarioNet pickle without running anything from it.

A pickle names Python callables (its "globals") and the loader calls them; a hostile file
can name ``os.system``. :class:`ScenarioUnpickler` resolves only the globals that plain
ScenarioNet files use (the globals of the format's own test data, written with numpy 1's
``numpy.core`` names, and of numpy 2.4's pickles of the same arrays, ``numpy._core``):

- ``numpy.core.multiarray._reconstruct`` / ``numpy._core.multiarray._reconstruct`` with
  ``numpy.ndarray`` and ``numpy.dtype``: numpy's array pickling (protocols 3 and 4; ScenarioNet
  writes ``pickle.dump``'s default, 4);
- ``collections.defaultdict`` (ScenarioNet's Waymo summaries hold ``defaultdict(int)``);
- the builtin scalars and containers (``int``, ``float``, ``str``, ...).

Every other global (``numpy._core.numeric._frombuffer`` of protocol 5,
``numpy.core.multiarray.scalar``, ``_codecs.encode`` of protocol 2, any class) is refused
with one line that names it. Even the allowed ones are narrowed to the one call shape
numpy's own pickles make: ``ndarray`` resolves to a marker that can only be passed to
``_reconstruct`` (so a file cannot allocate ``ndarray((10**12,))``), ``_reconstruct``
accepts only the empty seed array that ``__setstate__`` then fills from the file's own
bytes, ``dtype`` only a type string, and ``defaultdict`` becomes a plain ``dict`` (no
default factory survives). Files larger than :data:`MAX_FILE_BYTES` are refused before
reading; deep nesting is harmless (the C unpickler builds it without recursion, and
nothing here walks it), and a RecursionError would be reported, not crashed on.
"""

from __future__ import annotations

import builtins
import io
import os
import pathlib
import pickle
from typing import Any

import numpy as np

from converters.errors import ConversionError

MAX_FILE_BYTES = 2 * 1024**3
"""Largest scenario file read (2 GiB; the format's test scenes are 0.6-4 MB)."""

_NUMPY_CORE = ("numpy.core.multiarray", "numpy._core.multiarray")


class RefusedGlobal(ConversionError):
    """The pickle names a global that plain ScenarioNet files never use."""


class _ArrayType:
    """Stands for ``numpy.ndarray`` inside the pickle: not callable, only accepted by
    :func:`_reconstruct`."""

    def __repr__(self) -> str:
        return "numpy.ndarray"


_ARRAY = _ArrayType()


def _reconstruct(subtype: object, shape: object, dtype: object) -> np.ndarray:
    """numpy's ``_reconstruct(ndarray, (0,), b'b')``: the empty seed array that the
    pickle's BUILD then fills with ``ndarray.__setstate__`` (shape, dtype, raw bytes)."""
    if subtype is not _ARRAY or tuple(shape) != (0,) or dtype not in (b"b", "b"):  # type: ignore[arg-type]
        raise pickle.UnpicklingError("array reconstruction with unexpected arguments")
    return np.empty((0,), dtype=np.int8)


def _dtype(spec: object, align: object = False, copy: object = False) -> np.dtype:
    """``numpy.dtype('f8', False, True)`` as numpy pickles it; only type strings."""
    if not isinstance(spec, str) or len(spec) > 16:
        raise pickle.UnpicklingError(f"unexpected dtype argument {spec!r:.40}")
    return np.dtype(spec, align=bool(align), copy=bool(copy))


def _defaultdict(factory: object = None, *rest: object) -> dict:
    """``defaultdict(int)`` as a plain dict: its items follow as SETITEMS."""
    return {}


_BUILTINS = ("int", "float", "bool", "complex", "str", "list", "dict", "tuple", "set", "frozenset")
"""Builtins a pickle may name (calling them cannot allocate more than the file holds;
``bytes`` and ``bytearray`` could, and pickles never need them as globals)."""

ALLOWED: dict[tuple[str, str], Any] = {
    **{(m, "_reconstruct"): _reconstruct for m in _NUMPY_CORE},
    ("numpy", "ndarray"): _ARRAY,
    ("numpy", "dtype"): _dtype,
    ("collections", "defaultdict"): _defaultdict,
    **{("builtins", name): getattr(builtins, name) for name in _BUILTINS},
}
"""(module, name) -> what the pickle gets: the only globals a scenario file may name."""


class ScenarioUnpickler(pickle.Unpickler):
    """A :class:`pickle.Unpickler` that resolves only :data:`ALLOWED` globals."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return ALLOWED[(module, name)]
        except (KeyError, TypeError):
            raise RefusedGlobal(f"{module}.{name}") from None

    def persistent_load(self, pid: object) -> Any:
        raise pickle.UnpicklingError("persistent ids are not used by ScenarioNet files")


def load(path: str | os.PathLike, *, what: str = "ScenarioNet scenario") -> Any:
    """The object in the pickle file ``path``, loaded safely.

    Raises ConversionError (one line naming the file) for a file too large, a global
    outside :data:`ALLOWED` (named, nothing called), a truncated or damaged pickle, or a
    nesting too deep to load. ``what`` names the expected content in messages.
    """
    path = pathlib.Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise ConversionError(
                f"{path}: {size} bytes, more than the {MAX_FILE_BYTES} a {what} may have"
            )
        data = path.read_bytes()
    except OSError as exc:
        raise ConversionError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return loads(data, where=str(path), what=what)


def loads(data: bytes, *, where: str = "input", what: str = "ScenarioNet scenario") -> Any:
    """:func:`load` of bytes already read; ``where`` names them in messages."""
    try:
        return ScenarioUnpickler(io.BytesIO(data)).load()
    except RefusedGlobal as exc:
        raise ConversionError(
            f"{where}: refused to load: the pickle names the global {exc}; this file is not "
            f"a plain {what} (nothing in it was run)"
        ) from None
    except pickle.UnpicklingError as exc:
        if "truncated" not in str(exc):
            raise ConversionError(f"{where}: not a readable pickle ({exc})") from None
        raise ConversionError(
            f"{where}: the pickle ends early (truncated or incomplete file); copy it again"
        ) from None
    except EOFError:
        raise ConversionError(
            f"{where}: the pickle ends early (truncated or incomplete file); copy it again"
        ) from None
    except RecursionError:
        raise ConversionError(f"{where}: the pickle nests too deeply to be a {what}") from None
    except MemoryError:
        raise ConversionError(f"{where}: the pickle needs more memory than is free") from None
    except Exception as exc:  # damaged bytes: UnpicklingError, ValueError, ... (nothing ran)
        reason = " ".join(str(exc).split())[:120] or type(exc).__name__
        raise ConversionError(f"{where}: not a readable pickle ({reason})") from None
