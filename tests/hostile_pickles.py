"""Hostile pickles for the safe loader (issue 36), built opcode by opcode.

:func:`measured` holds the cases the issue measured (each crashed, hung or flooded a
plain unpickler using only names the loader allows); :func:`generated` makes
``count`` more of the same kinds with varied sizes and seeds, plus byte-level damage of
a small valid scenario in every protocol. Each entry is ``(name, bytes)``.
"""

from __future__ import annotations

import pickle
import random
import struct

import numpy as np

PROTO4 = b"\x80\x04"
BINPUT0, BINGET0, POP = b"q\x00", b"h\x00", b"0"
MARK, STOP, NONE = b"(", b".", b"N"
RECONSTRUCT = b"cnumpy.core.multiarray\n_reconstruct\n"
FROMBUFFER = b"cnumpy._core.numeric\n_frombuffer\n"
NDARRAY = b"cnumpy\nndarray\n"
DTYPE = b"cnumpy\ndtype\n"


def _int(n: int) -> bytes:
    return b"J" + struct.pack("<i", n) if -(2**31) <= n < 2**31 else b"L%dL\n" % n


def _str(s: str) -> bytes:
    raw = s.encode()
    return b"X" + struct.pack("<I", len(raw)) + raw


def _bytes(raw: bytes) -> bytes:
    return b"B" + struct.pack("<I", len(raw)) + raw


def _dtype(spec: str) -> bytes:
    return DTYPE + MARK + _str(spec) + b"\x89\x88t" + b"R"  # dtype(spec, False, True)


def _tuple(*parts: bytes) -> bytes:
    return MARK + b"".join(parts) + b"t"


def object_array(claimed: int, held: int) -> bytes:
    """_reconstruct + BUILD with state (1, (claimed,), dtype('O8'), False, [held items])."""
    items = MARK + b"".join(_int(k) for k in range(held)) + b"l"
    state = _tuple(_int(1), _tuple(_int(claimed)), _dtype("O8"), b"\x89", items)
    seed = RECONSTRUCT + _tuple(NDARRAY, _tuple(_int(0)), b"C\x01b") + b"R"
    return PROTO4 + seed + state + b"b" + STOP


def number_array(claimed: int, nbytes: int, spec: str = "f8") -> bytes:
    state = _tuple(_int(1), _tuple(_int(claimed)), _dtype(spec), b"\x89", _bytes(bytes(nbytes)))
    seed = RECONSTRUCT + _tuple(NDARRAY, _tuple(_int(0)), b"C\x01b") + b"R"
    return PROTO4 + seed + state + b"b" + STOP


def frombuffer_array(claimed: int, nbytes: int, spec: str = "f8") -> bytes:
    args = _tuple(_bytes(bytes(nbytes)), _dtype(spec), _tuple(_int(claimed)), _str("C"))
    return PROTO4 + FROMBUFFER + args + b"R" + STOP


def nested_tuple_key(depth: int) -> bytes:
    """{((((...),),),): None}: hashing the key recurses ``depth`` levels in C."""
    return PROTO4 + b"}" + b")" + b"\x85" * depth + NONE + b"s" + STOP


def nested_list(depth: int) -> bytes:
    return PROTO4 + b"]" * depth + b"a" * (depth - 1) + STOP


def shared_tuple_key(levels: int, container: bytes = b"frozenset") -> bytes:
    """A set, frozenset or dict keyed by t_k = (t_{k-1}, t_{k-1}): 2**levels hash calls."""
    tower = b")" + (BINPUT0 + POP + BINGET0 + BINGET0 + b"\x86") * levels
    if container == b"frozenset":
        return PROTO4 + MARK + tower + b"\x91" + STOP
    if container == b"set":
        return PROTO4 + b"\x8f" + MARK + tower + b"\x90" + STOP
    return PROTO4 + b"}" + tower + NONE + b"s" + STOP


def shared_list(levels: int) -> bytes:
    """l_k = [l_{k-1}, l_{k-1}]: 2**levels items when printed or walked."""
    tower = b"]" + (BINPUT0 + POP + MARK + BINGET0 + BINGET0 + b"l") * levels
    return PROTO4 + tower + STOP


def shared_dict_values(levels: int) -> bytes:
    tower = b"}" + (BINPUT0 + POP + b"}" + _str("a") + BINGET0 + _str("b") + BINGET0
                    + b"u") * levels  # fmt: skip
    return PROTO4 + tower + STOP


def grows_after_use() -> bytes:
    """A list appended to after it was placed in another (its size was already counted)."""
    return PROTO4 + b"]" + BINPUT0 + b"]" + BINGET0 + b"a" + BINGET0 + NONE + b"a" + POP + STOP


def self_holding_list() -> bytes:
    return PROTO4 + b"]" + BINPUT0 + BINGET0 + b"a" + STOP


def huge_bytearray8(claimed: int) -> bytes:
    return b"\x80\x05\x96" + struct.pack("<Q", claimed) + b"x" + STOP


def dict_keyed_by_list() -> bytes:
    return PROTO4 + b"}" + b"]" + NONE + b"s" + STOP


def build_on_dict() -> bytes:
    return PROTO4 + b"}" + b"}" + _str("a") + _int(1) + b"s" + b"b" + STOP


def dtype_state(state: bytes) -> bytes:
    return PROTO4 + _dtype("f8") + state + b"b" + STOP


def reconstruct_big_seed() -> bytes:
    return PROTO4 + RECONSTRUCT + _tuple(NDARRAY, _tuple(_int(10**9)), b"C\x01b") + b"R" + STOP


def codecs_encode(text: bytes, encoding: str) -> bytes:
    return (
        PROTO4 + b"c_codecs\nencode\n" + _tuple(_str(text.decode()), _str(encoding)) + b"R" + STOP
    )


def measured() -> list[tuple[str, bytes]]:
    """The issue's cases: a 158-byte object array (segfault), a deeply nested tuple key
    (segfault), a 64-level shared tuple key (hang), a 40-level shared list (memory)."""
    return [
        ("object-array-claims-1e6-holds-3", object_array(10**6, 3)),
        ("dict-key-tuple-nested-100000", nested_tuple_key(100_000)),
        ("frozenset-key-shared-tuple-64", shared_tuple_key(64)),
        ("dict-key-shared-tuple-64", shared_tuple_key(64, b"dict")),
        ("list-shared-40", shared_list(40)),
        ("list-nested-1000000", nested_list(1_000_000)),
        ("bytearray8-claims-2^40", huge_bytearray8(2**40)),
        ("array-bytes-short", number_array(10**6, 24)),
        ("frombuffer-claims-more", frombuffer_array(10**6, 24)),
        ("reconstruct-1e9-seed", reconstruct_big_seed()),
        ("list-grows-after-use", grows_after_use()),
        ("list-holds-itself", self_holding_list()),
        ("dict-keyed-by-list", dict_keyed_by_list()),
        ("build-on-a-dict", build_on_dict()),
        (
            "dtype-foreign-state",
            dtype_state(_tuple(_int(3), _str("<"), NONE, NONE, NONE, _int(99), _int(-1), _int(0))),
        ),
        ("codecs-encode-utf-7", codecs_encode(b"abc", "utf-7")),
    ]


def small_scenario() -> dict:
    """A small dict shaped like a ScenarioNet scenario (for byte-level damage)."""
    steps = 5
    track = {
        "type": "VEHICLE",
        "state": {
            "position": np.zeros((steps, 3)),
            "heading": np.zeros(steps),
            "velocity": np.zeros((steps, 2)),
            "length": np.full(steps, 4.0),
            "width": np.full(steps, 2.0),
            "valid": np.ones(steps, dtype=bool),
        },
        "metadata": {"type": "car"},
    }
    return {
        "id": "s",
        "version": "1",
        "length": steps,
        "metadata": {"sdc_id": "0", "ts": np.arange(steps) / 10.0, "dataset": "x"},
        "tracks": {"0": track, "1": dict(track)},
        "map_features": {"L": {"type": "LANE_SURFACE_STREET", "polyline": [[0, 0], [10, 0]]}},
        "dynamic_map_states": {},
    }


def generated(count: int = 300, seed: int = 36) -> list[tuple[str, bytes]]:
    """``count`` hostile pickles of the measured kinds, sizes and seeds varied."""
    rng = random.Random(seed)
    kinds = [
        lambda: (f"object-array-{(c := rng.randint(4, 10**7))}-holds-{(h := rng.randint(0, 3))}",
                 object_array(c, h)),
        lambda: (f"tuple-key-depth-{(d := rng.randint(65, 300_000))}", nested_tuple_key(d)),
        lambda: (f"shared-key-{(n := rng.randint(24, 80))}-{(c := rng.choice([b'frozenset', b'set', b'dict']).decode())}",
                 shared_tuple_key(n, c.encode())),
        lambda: (f"shared-list-{(n := rng.randint(24, 80))}", shared_list(n)),
        lambda: (f"shared-dict-{(n := rng.randint(24, 80))}", shared_dict_values(n)),
        lambda: (f"nested-list-{(d := rng.randint(65, 500_000))}", nested_list(d)),
        lambda: (f"bytearray8-{(n := rng.randint(2**20, 2**62))}", huge_bytearray8(n)),
        lambda: (f"array-{(c := rng.randint(2, 10**9))}-bytes-{(b := rng.randint(0, 64))}",
                 number_array(c, b if b != c * 8 else b + 1)),
        lambda: (f"frombuffer-{(c := rng.randint(2, 10**9))}-bytes-{(b := rng.randint(0, 64))}",
                 frombuffer_array(c, b if b != c * 8 else b + 1)),
    ]  # fmt: skip
    out: list[tuple[str, bytes]] = []
    n_damaged = count // 3
    for k in range(count - n_damaged):
        name, data = kinds[k % len(kinds)]()
        out.append((f"{k:03d}-{name}", data))
    base = [pickle.dumps(small_scenario(), protocol=p) for p in range(6)]
    for k in range(n_damaged):
        data = bytearray(base[k % 6])
        for _ in range(rng.randint(1, 8)):  # flip, insert or cut bytes
            at = rng.randrange(len(data))
            how = rng.random()
            if how < 0.6:
                data[at] = rng.randrange(256)
            elif how < 0.8:
                data[at:at] = bytes([rng.randrange(256)])
            else:
                del data[at : at + rng.randint(1, 16)]
        out.append((f"{count - n_damaged + k:03d}-damaged-protocol-{k % 6}", bytes(data)))
    return out
