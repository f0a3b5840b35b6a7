"""Load a ScenarioNet pickle without running anything from it, and without letting it
crash, hang or flood the process.

A pickle names Python callables (its "globals") and the loader calls them; a hostile file
can name ``os.system``. Beyond that, a small file can make a plain unpickler do unbounded
work with harmless names only (issue 36): an object array whose state claims 10**6 items
but holds 3 (numpy reads past the list), a dict keyed by a deeply nested tuple (a C stack
overflow while hashing), a frozenset keyed by a 64-level shared tuple (2**64 hash calls),
a 40-level shared list whose ``str()`` never ends.

So the file is read by :class:`ScenarioUnpickler`, the pure-Python unpickler with every
opcode that builds, fills or calls checked. It is safe by construction, not by luck:

- **Globals**: only those plain ScenarioNet files use in any pickle protocol 0-5
  (:data:`ALLOWED`), each a narrowed stand-in that accepts only the call shape numpy and
  Python themselves write: ``_reconstruct(ndarray, (0,), b'b')`` (an empty seed that BUILD
  fills), ``_frombuffer(bytes, dtype, shape, order)`` with a buffer exactly the size of
  the shape, ``dtype(type string)`` with BUILD state equal to that type's own,
  ``_codecs.encode(str, 'latin1')``, ``set``/``frozenset``/``bytearray``/``complex`` of
  plain values, ``defaultdict`` (as a plain ``dict``). Every other global is refused with
  one line that names it; no class is ever instantiated.
- **Arrays**: an array's state is checked against its claimed shape before numpy sees it
  (object arrays: a list of exactly that many items; others: exactly ``items x itemsize``
  bytes); only plain dtypes (numbers, booleans, text, objects; no records, sub-arrays or
  dates).
- **Keys**: dict keys and set items must be flat (``str``, ``bytes``, numbers, ``None``,
  or a tuple of up to :data:`MAX_KEY_TUPLE` of these), so hashing is linear in the file.
- **Shape**: nesting depth at most :data:`MAX_DEPTH`; any object's size counted with
  every shared reference expanded at most :data:`MAX_NODES` (a shared 40-level list is
  2**40); a container can no longer change once placed inside another (no cycles, no
  growth after it was counted); at most :data:`MAX_OPS` opcodes.
- **Time**: :data:`TIME_BUDGET_S` of CPU time plus :data:`SECONDS_PER_MB` per MB of file.

Files larger than :data:`MAX_FILE_BYTES` are refused before reading. The bounds sit far
above what real scenarios use (depth 7, 71,000 objects, 150,000 opcodes for a 4 MB
nuScenes scene); each refusal is one line naming the file and the limit.
"""

from __future__ import annotations

import io
import math
import os
import pathlib
import pickle
import signal
import struct
import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from converters.errors import ConversionError

MAX_FILE_BYTES = 2 * 1024**3
"""Largest scenario file read (2 GiB; the format's test scenes are 0.6-4 MB)."""

MAX_DEPTH = 64
"""Deepest nesting of containers (real scenarios: 7)."""

MAX_NODES = 5_000_000
"""Most objects one object may hold, every shared reference counted each time it is
reached (real scenarios: 71,000); walking or printing it stays bounded."""

MAX_OPS = 20_000_000
"""Most opcodes in one file (each makes at most one object; real: 150,000 for 4 MB)."""

MAX_STACK = 100_000
"""Most objects on the unpickler's stack, or marks, at once (pickle writes items in batches
of 1,000; a deep nesting pushes every level first)."""

MAX_KEY_TUPLE = 16
"""Longest tuple allowed as a dict key or set item (its items must be flat)."""

MAX_ARRAY_DIMS = 32
TIME_BUDGET_S = 1.0
SECONDS_PER_MB = 0.25
"""CPU time allowed: the budget plus this per MB of file (real files: 0.03 s per MB)."""

_CHECK_EVERY_OPS = 4096
_NUMPY_CORE = ("numpy.core", "numpy._core")
_FLAT_KEYS = (str, bytes, int, float, complex, bool, type(None))
_ARRAY_KINDS = "biufcUSO"  # numbers, booleans, text, objects; no records, voids, dates
_LEAVES = (str, bytes, bytearray, int, float, complex, bool, type(None), np.dtype)


class RefusedGlobal(ConversionError):
    """The pickle names a global that plain ScenarioNet files never use."""


class _Refused(ConversionError):
    """The pickle does something a scenario file never does (the message says what)."""


class _Global:
    """A global the pickle may name: ``call`` (checked) when the pickle calls it."""

    def __init__(self, name: str, call: Callable[..., Any] | None = None) -> None:
        self.name, self.call = name, call

    def __repr__(self) -> str:
        return self.name


def _flat_key(value: object) -> bool:
    if isinstance(value, _FLAT_KEYS):
        return True
    return (
        type(value) is tuple
        and len(value) <= MAX_KEY_TUPLE
        and all(isinstance(v, _FLAT_KEYS) for v in value)
    )


def _check_key(value: object) -> None:
    """Dict keys and set items: flat, so that hashing them costs what the file holds."""
    if not _flat_key(value):
        raise _Refused(
            f"a dict key or set item is a {type(value).__name__} (only text, numbers and"
            f" flat tuples of up to {MAX_KEY_TUPLE} of them are read)"
        )


def _shape(value: object) -> tuple[int, ...]:
    if type(value) is not tuple or len(value) > MAX_ARRAY_DIMS:
        raise _Refused("an array shape that is not a short tuple")
    if not all(type(n) is int and n >= 0 for n in value):
        raise _Refused("an array shape with a negative or non-integer length")
    return value


def _plain_dtype(value: object) -> np.dtype:
    if not isinstance(value, np.dtype) or value.kind not in _ARRAY_KINDS:
        raise _Refused(f"an array of dtype {value!r:.40} (not plain numbers, text or objects)")
    if value.fields is not None or value.subdtype is not None or value.itemsize <= 0:
        raise _Refused(f"an array of dtype {value!r:.40} (records or sub-arrays)")
    return value


def _canonical_states(dtype: np.dtype) -> list[Any]:
    """The BUILD states numpy writes for ``dtype`` in either byte order."""
    return [d.__reduce__()[2] for d in (dtype, dtype.newbyteorder("<"), dtype.newbyteorder(">"))]


class ScenarioUnpickler(pickle._Unpickler):
    """The pure-Python unpickler with every opcode that builds, fills or calls checked
    (see the module docstring); ``budget_s`` is the CPU time allowed."""

    dispatch: ClassVar[dict[int, Callable[..., Any]]] = dict(pickle._Unpickler.dispatch)
    pop_mark: Callable[[], list[Any]]  # (the base class's; not in its type stubs)
    metastack: list[list[Any]]

    def __init__(self, file: io.BytesIO, *, budget_s: float = TIME_BUDGET_S) -> None:
        super().__init__(file, fix_imports=True, encoding="ASCII", errors="strict")
        self._budget_s = budget_s
        # id -> [depth, expanded size, sealed] of every container made; _keep holds them
        # so that their ids stay theirs while loading.
        self._info: dict[int, list[int]] = {}
        self._keep: list[object] = []
        self._unbuilt: dict[int, str] = {}  # dtype and array seeds waiting for BUILD
        self._globals = _allowed_globals(self)

    # ------------------------------------------------------------------ bookkeeping
    def _made(self, obj: Any, depth: int = 1, size: int = 1) -> Any:
        if depth > MAX_DEPTH:
            raise _Refused(f"it nests deeper than {MAX_DEPTH} levels")
        if size > MAX_NODES:
            raise _Refused(
                f"an object holds more than {MAX_NODES} items (shared parts counted each time)"
            )
        self._info[id(obj)] = [depth, size, 0]
        self._keep.append(obj)
        return obj

    def _node(self, obj: object) -> list[int]:
        info = self._info.get(id(obj))
        if info is not None:
            return info
        if isinstance(obj, _LEAVES) or (isinstance(obj, np.ndarray) and obj.dtype.kind != "O"):
            return [0, 1, 0]
        if isinstance(obj, _Global) or (type(obj) is tuple and not obj):
            return [0, 1, 0]
        raise _Refused(f"an unexpected {type(obj).__name__}")

    def _add(self, parent: object, children: list[object]) -> None:
        """Account for ``children`` placed into the container ``parent``."""
        info = self._info[id(parent)]
        if info[2]:
            raise _Refused("it changes a container after placing it inside another")
        for child in children:
            if child is parent:
                raise _Refused("a container holds itself")
            node = self._node(child)
            node[2] = 1  # sealed: counted into its parent, so it may not grow any more
            info[0] = max(info[0], node[0] + 1)
            info[1] += node[1]
        if info[0] > MAX_DEPTH:
            raise _Refused(f"it nests deeper than {MAX_DEPTH} levels")
        if info[1] > MAX_NODES:
            raise _Refused(
                f"an object holds more than {MAX_NODES} items (shared parts counted each time)"
            )

    def _new(self, obj: Any, children: list[object]) -> Any:
        self._made(obj, 1, 1)
        self._add(obj, children)
        return obj

    def _target(self, kind: type) -> Any:
        target = self.stack[-1] if self.stack else None
        if type(target) is not kind or id(target) not in self._info:
            raise _Refused(f"it fills a {type(target).__name__} as if it were a {kind.__name__}")
        return target

    # ------------------------------------------------------------------ the main loop
    def load(self) -> Any:
        """:meth:`pickle._Unpickler.load` with the opcode and CPU-time budgets."""
        self._unframer = pickle._Unframer(self._file_read, self._file_readline)  # type: ignore[attr-defined]
        self.read = self._unframer.read
        self.readinto = self._unframer.readinto
        self.readline = self._unframer.readline
        self.metastack: list[list[Any]] = []
        self.stack: list[Any] = []
        self.append = self.stack.append
        self.proto = 0
        read, dispatch = self.read, self.dispatch
        start, ops = time.process_time(), 0
        try:
            while True:
                key = read(1)
                if not key:
                    raise EOFError
                dispatch[key[0]](self)
                ops += 1
                if ops % _CHECK_EVERY_OPS == 0:
                    if len(self.stack) > MAX_STACK or len(self.metastack) > MAX_STACK:
                        raise _Refused(f"it stacks more than {MAX_STACK} objects at once")
                    if ops > MAX_OPS:
                        raise _Refused(f"it holds more than {MAX_OPS} opcodes")
                    if time.process_time() - start > self._budget_s:
                        raise _Refused(f"reading it takes more than {self._budget_s:.1f} s")
        except pickle._Stop as stop:  # type: ignore[attr-defined]
            return stop.value

    def find_class(self, module: str, name: str) -> Any:
        if self.proto < 3 and module == "__builtin__":  # protocols 0-2 name Python 2's
            module, name = "builtins", {"long": "int"}.get(name, name)
        for old in ("numpy.core.", "numpy._core."):  # numpy 1 and 2 name the same functions
            if module.startswith(old):
                module = "numpy._core." + module[len(old) :]
        try:
            return self._globals[(module, name)]
        except (KeyError, TypeError):
            raise RefusedGlobal(f"{module}.{name}") from None

    def persistent_load(self, pid: object) -> Any:
        raise _Refused("persistent ids are not used by ScenarioNet files")

    # ------------------------------------------------------------------ containers
    def load_empty_list(self) -> None:
        self.append(self._made([]))

    def load_empty_dict(self) -> None:
        self.append(self._made({}))

    def load_empty_set(self) -> None:
        self.append(self._made(set()))

    def load_list(self) -> None:
        items = self.pop_mark()
        self.append(self._new(list(items), items))

    def load_tuple(self) -> None:
        items = self.pop_mark()
        self.append(self._new(tuple(items), items))

    def _tuple_of(self, n: int) -> None:
        items = self.stack[-n:]
        del self.stack[-n:]
        self.append(self._new(tuple(items), items))

    def load_tuple1(self) -> None:
        self._tuple_of(1)

    def load_tuple2(self) -> None:
        self._tuple_of(2)

    def load_tuple3(self) -> None:
        self._tuple_of(3)

    def load_empty_tuple(self) -> None:
        self.append(())

    def load_append(self) -> None:
        value = self.stack.pop()
        target = self._target(list)
        self._add(target, [value])
        target.append(value)

    def load_appends(self) -> None:
        items = self.pop_mark()
        target = self._target(list)
        self._add(target, items)
        target.extend(items)

    def _set_items(self, target: dict, items: list[Any]) -> None:
        if len(items) % 2:
            raise _Refused("a dict item without a value")
        keys = items[0::2]
        for key in keys:
            _check_key(key)
        self._add(target, items)
        for k in range(0, len(items), 2):
            target[items[k]] = items[k + 1]

    def load_setitem(self) -> None:
        value = self.stack.pop()
        key = self.stack.pop()
        self._set_items(self._target(dict), [key, value])

    def load_setitems(self) -> None:
        items = self.pop_mark()
        self._set_items(self._target(dict), items)

    def load_dict(self) -> None:
        items = self.pop_mark()
        target = self._made({})
        self._set_items(target, items)
        self.append(target)

    def load_additems(self) -> None:
        items = self.pop_mark()
        target = self._target(set)
        for item in items:
            _check_key(item)
        self._add(target, items)
        target.update(items)

    def load_frozenset(self) -> None:
        items = self.pop_mark()
        for item in items:
            _check_key(item)
        self.append(self._new(frozenset(items), items))

    def load_bytearray8(self) -> None:
        # The stock loader allocates the claimed length before reading: check it first.
        (n,) = struct.unpack("<Q", self.read(8))
        data = self.read(n)
        if len(data) != n:
            raise pickle.UnpicklingError("pickle data was truncated")
        self.append(bytearray(data))

    # ------------------------------------------------------------------ calls
    def load_reduce(self) -> None:
        args = self.stack.pop()
        func = self.stack[-1]
        if not isinstance(func, _Global) or func.call is None or type(args) is not tuple:
            raise _Refused(f"it calls {func!r:.40}, which a scenario file never calls")
        self.stack[-1] = func.call(*args)

    def load_build(self) -> None:
        state = self.stack.pop()
        target = self.stack[-1]
        what = self._unbuilt.pop(id(target), None)
        if what == "dtype":
            self._build_dtype(target, state)
        elif what == "array":
            self._build_array(target, state)
        else:
            raise _Refused(f"it sets the state of a {type(target).__name__}")

    def _refuse_op(self) -> None:
        raise _Refused("it instantiates a class or uses an extension code")

    def _build_dtype(self, dtype: np.dtype, state: object) -> None:
        """Only the state numpy writes for this type string (either byte order)."""
        if type(state) is not tuple or not all(
            isinstance(v, (str, int, type(None))) for v in state
        ):
            raise _Refused("a dtype with an unexpected state")
        if state not in _canonical_states(dtype):
            raise _Refused(f"a dtype {dtype} with an unexpected state")
        dtype.__setstate__(state)  # type: ignore[attr-defined]

    def _build_array(self, seed: np.ndarray, state: object) -> None:
        """``ndarray.__setstate__((1, shape, dtype, fortran, raw))``, checked before numpy
        sees it: the raw data must hold exactly what the shape claims."""
        if type(state) is not tuple or len(state) != 5 or state[0] != 1:
            raise _Refused("an array with an unexpected state")
        _, shape, dtype, fortran, raw = state
        shape, dtype = _shape(shape), _plain_dtype(dtype)
        if type(fortran) is not bool:
            raise _Refused("an array with an unexpected state")
        count = math.prod(shape)
        if dtype.kind == "O":
            if type(raw) is not list or len(raw) != count:
                raise _Refused(
                    f"an object array of shape {shape} whose state holds"
                    f" {len(raw) if type(raw) is list else 'no list of'} items"
                )
            self._made(seed)
            self._add(seed, raw)
        elif not isinstance(raw, (bytes, bytearray)) or len(raw) != count * dtype.itemsize:
            size = len(raw) if isinstance(raw, (bytes, bytearray)) else "no"
            raise _Refused(f"an array of shape {shape} and dtype {dtype} given {size} bytes")
        seed.__setstate__(state)

    # the globals' checked calls ------------------------------------------------
    def _reconstruct(self, subtype: object, shape: object, dtype: object) -> np.ndarray:
        """numpy's ``_reconstruct(ndarray, (0,), b'b')``: the empty seed array that the
        pickle's BUILD then fills (:meth:`_build_array`)."""
        if not (isinstance(subtype, _Global) and subtype.name == "numpy.ndarray"):
            raise _Refused("array reconstruction with unexpected arguments")
        if shape != (0,) or dtype not in (b"b", "b"):
            raise _Refused("array reconstruction with unexpected arguments")
        seed = np.empty((0,), dtype=np.int8)
        self._unbuilt[id(seed)] = "array"
        self._keep.append(seed)
        return seed

    def _frombuffer(self, buf: object, dtype: object, shape: object, order: object) -> np.ndarray:
        """numpy's protocol-5 ``_frombuffer(buffer, dtype, shape, order)``: the buffer must
        hold exactly ``shape`` items of a plain, non-object dtype."""
        dtype, shape = _plain_dtype(dtype), _shape(shape)
        if dtype.kind == "O" or order not in ("C", "F"):
            raise _Refused("an array from a buffer with an unexpected dtype or order")
        if not isinstance(buf, (bytes, bytearray)) or len(buf) != math.prod(shape) * dtype.itemsize:
            raise _Refused(
                f"an array of shape {shape} and dtype {dtype} from a buffer of another size"
            )
        return np.frombuffer(buf, dtype=dtype).reshape(shape, order=order)

    def _dtype(self, spec: object, align: object = False, copy: object = True) -> np.dtype:
        """``numpy.dtype('f8', False, True)`` as numpy pickles it: a short type string of
        a plain kind; always a new dtype object (BUILD then sets its byte order)."""
        if not isinstance(spec, str) or len(spec) > 16 or type(align) is not bool:
            raise _Refused(f"unexpected dtype argument {spec!r:.40}")
        try:
            dtype = np.dtype(spec, align=False, copy=True)
        except (TypeError, ValueError):
            raise _Refused(f"unexpected dtype argument {spec!r:.40}") from None
        _plain_dtype(dtype)
        self._unbuilt[id(dtype)] = "dtype"
        self._keep.append(dtype)
        return dtype

    def _set(self, items: object = (), *, frozen: bool = False) -> Any:
        if not isinstance(items, (list, tuple)):
            raise _Refused("a set made from something other than a list")
        for item in items:
            _check_key(item)
        made = frozenset(items) if frozen else set(items)
        return self._new(made, list(items))

    def _encode(self, text: object, encoding: object = "latin1") -> bytes:
        """``_codecs.encode(text, 'latin1')``: how protocols 0-2 write bytes."""
        if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
            raise _Refused("_codecs.encode with unexpected arguments")
        return text.encode("latin1")

    def _bytearray(self, data: object = b"", encoding: object = None) -> bytearray:
        if isinstance(data, (bytes, bytearray)) and encoding is None:
            return bytearray(data)
        if isinstance(data, str) and encoding in ("latin1", "latin-1"):
            return bytearray(data.encode("latin1"))
        raise _Refused("bytearray with unexpected arguments")

    def _complex(self, real: object = 0.0, imag: object = 0.0) -> complex:
        if not (isinstance(real, (int, float)) and isinstance(imag, (int, float))):
            raise _Refused("complex with unexpected arguments")
        return complex(real, imag)

    def _defaultdict(self, factory: object = None, *rest: object) -> dict:
        """``defaultdict(int)`` as a plain dict (no factory survives): its items follow."""
        if rest:
            raise _Refused("defaultdict with unexpected arguments")
        return self._made({})


for _code, _method in {
    pickle.EMPTY_LIST: "load_empty_list", pickle.EMPTY_DICT: "load_empty_dict",
    pickle.EMPTY_SET: "load_empty_set", pickle.EMPTY_TUPLE: "load_empty_tuple",
    pickle.LIST: "load_list", pickle.TUPLE: "load_tuple", pickle.TUPLE1: "load_tuple1",
    pickle.TUPLE2: "load_tuple2", pickle.TUPLE3: "load_tuple3", pickle.APPEND: "load_append",
    pickle.APPENDS: "load_appends", pickle.SETITEM: "load_setitem",
    pickle.SETITEMS: "load_setitems", pickle.DICT: "load_dict",
    pickle.ADDITEMS: "load_additems", pickle.FROZENSET: "load_frozenset",
    pickle.BYTEARRAY8: "load_bytearray8", pickle.REDUCE: "load_reduce",
    pickle.BUILD: "load_build",
    **dict.fromkeys(
        (pickle.NEWOBJ, pickle.NEWOBJ_EX, pickle.OBJ, pickle.INST, pickle.EXT1, pickle.EXT2,
         pickle.EXT4, pickle.NEXT_BUFFER, pickle.READONLY_BUFFER, pickle.PERSID, pickle.BINPERSID),
        "_refuse_op",
    ),
}.items():  # fmt: skip
    ScenarioUnpickler.dispatch[_code[0]] = getattr(ScenarioUnpickler, _method)


def _allowed_globals(u: ScenarioUnpickler) -> dict[tuple[str, str], _Global]:
    """(module, name) -> the checked stand-in: the only globals a scenario file may name.
    Names that are passed but never called (``int`` as a defaultdict's factory, ``ndarray``
    as ``_reconstruct``'s argument) have no call."""

    def called(name: str, call: Callable[..., Any] | None = None) -> _Global:
        return _Global(name, call)

    allowed = {
        ("numpy._core.multiarray", "_reconstruct"): called("_reconstruct", u._reconstruct),
        ("numpy._core.numeric", "_frombuffer"): called("_frombuffer", u._frombuffer),
        ("numpy", "ndarray"): called("numpy.ndarray"),
        ("numpy", "dtype"): called("numpy.dtype", u._dtype),
        ("collections", "defaultdict"): called("defaultdict", u._defaultdict),
        ("_codecs", "encode"): called("_codecs.encode", u._encode),
        ("builtins", "set"): called("set", u._set),
        ("builtins", "frozenset"): called("frozenset", lambda *a: u._set(*a, frozen=True)),
        ("builtins", "bytearray"): called("bytearray", u._bytearray),
        ("builtins", "complex"): called("complex", u._complex),
    }
    for name in ("int", "float", "bool", "str", "list", "dict", "tuple"):
        allowed[("builtins", name)] = called(name)  # a factory's name, never called
    return allowed


def load(path: str | os.PathLike, *, what: str = "ScenarioNet scenario") -> Any:
    """The object in the pickle file ``path``, loaded safely.

    Raises ConversionError (one line naming the file) for a file too large, a global
    outside the allowed ones (named, nothing called), a truncated or damaged pickle, or one
    beyond the loader's bounds (named). ``what`` names the expected content in messages.
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


def load_isolated(path: str | os.PathLike, *, what: str = "ScenarioNet scenario") -> Any:
    """:func:`load` in a forked child process: should a file still crash the loader (a
    bug in it, numpy or Python), that child dies, not the process converting the other
    scenarios (issue 36: in ``batch`` a crash lost the good scenario beside the bad one).

    The child sends the object back pickled; its bytes are read with :func:`loads` again
    (a child that went wrong is not trusted either). A child killed by a signal is one
    ConversionError naming the file. Without ``os.fork`` (Windows): :func:`load`."""
    if not hasattr(os, "fork"):
        return load(path, what=what)
    budget_s = TIME_BUDGET_S + SECONDS_PER_MB * _size(path) / 1e6
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: load, send, and leave without running the parent's exit code
        status = 1
        try:
            os.close(read_end)
            signal.alarm(int(10 * budget_s) + 10)  # a wall-clock stop beside the CPU budget
            try:
                payload: tuple[bool, Any] = (True, load(path, what=what))
            except ConversionError as exc:
                payload = (False, str(exc))
            with os.fdopen(write_end, "wb") as pipe:
                pipe.write(pickle.dumps(payload, protocol=5))
            status = 0
        finally:
            os._exit(status)
    os.close(write_end)
    with os.fdopen(read_end, "rb") as pipe:
        data = pipe.read()
    _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) or os.WEXITSTATUS(status) != 0:
        how = (
            f"signal {signal.Signals(os.WTERMSIG(status)).name}"
            if os.WIFSIGNALED(status)
            else f"status {os.WEXITSTATUS(status)}"
        )
        raise ConversionError(
            f"{path}: reading it stopped the loader's process ({how}); the file is damaged or"
            f" hostile (nothing else was affected; report it if it is a real {what})"
        )
    ok, value = loads(data, where=str(path), what=what)
    if not ok:
        raise ConversionError(value)
    return value


def _size(path: str | os.PathLike) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return 0


def loads(data: bytes, *, where: str = "input", what: str = "ScenarioNet scenario") -> Any:
    """:func:`load` of bytes already read; ``where`` names them in messages."""
    budget = TIME_BUDGET_S + SECONDS_PER_MB * len(data) / 1e6
    truncated = f"{where}: the pickle ends early (truncated or incomplete file); copy it again"
    stream = io.BytesIO(data)
    try:
        return ScenarioUnpickler(stream, budget_s=budget).load()
    except RefusedGlobal as exc:
        raise ConversionError(
            f"{where}: refused to load: the pickle names the global {exc}; this file is not "
            f"a plain {what} (nothing in it was run)"
        ) from None
    except _Refused as exc:
        raise ConversionError(
            f"{where}: refused to load: {exc}; this file is not a plain {what}"
        ) from None
    except EOFError:
        raise ConversionError(truncated) from None
    except pickle.UnpicklingError as exc:
        if "truncated" in str(exc) or "exhausted" in str(exc):  # (the pure-Python wording)
            raise ConversionError(truncated) from None
        raise ConversionError(f"{where}: not a readable pickle ({exc})") from None
    except RecursionError:
        raise ConversionError(f"{where}: the pickle nests too deeply to be a {what}") from None
    except MemoryError:
        raise ConversionError(f"{where}: the pickle needs more memory than is free") from None
    except Exception as exc:  # damaged bytes: IndexError, ValueError, ... (nothing ran)
        reason = " ".join(f"{type(exc).__name__}: {exc}".split())[:120]
        raise ConversionError(
            f"{where}: not a readable pickle (damaged before byte {stream.tell()}: {reason})"
        ) from None
