"""TFRecord framing, read and written without TensorFlow.

A TFRecord file is a sequence of records, each::

    uint64  length              (little endian)
    uint32  masked_crc32c(length bytes)
    bytes   payload[length]
    uint32  masked_crc32c(payload)

with ``masked_crc(x) = ((crc >> 15 | crc << 17) + 0xA282EAD8) mod 2**32`` over the
CRC-32C (Castagnoli) of the bytes. The CRC itself comes from ``google-crc32c`` (a
maintained C implementation, Apache-2.0).
"""

from __future__ import annotations

import os
import pathlib
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import google_crc32c

from converters.errors import ConversionError
from outputs.atomic import atomic_output

_MASK_DELTA = 0xA282EAD8
_HEADER = struct.Struct("<QI")
_FOOTER = struct.Struct("<I")


def masked_crc32c(data: bytes) -> int:
    """The TFRecord masked CRC-32C of ``data``."""
    crc = google_crc32c.value(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


@dataclass(frozen=True)
class Record:
    """One record: its position in the file (0-based index, byte offset) and payload."""

    index: int
    offset: int
    payload: bytes


class RecordError(ConversionError):
    """A record is corrupt. ``resumable`` says whether the records after it can still be
    found (a bad payload CRC: yes; a bad length or a truncated file: no)."""

    def __init__(self, message: str, *, index: int, offset: int, resumable: bool) -> None:
        super().__init__(message)
        self.index = index
        self.offset = offset
        self.resumable = resumable


def read_records(path: str | os.PathLike, *, verify: bool = True) -> Iterator[Record | RecordError]:
    """Yield every record of a TFRecord file, in order.

    A corrupt record is yielded as a :class:`RecordError` (not raised), so that the caller
    decides whether to stop or skip it; after a non-resumable error nothing more is
    yielded. Records are read one at a time, so a large file is never in memory whole.
    """
    path = pathlib.Path(path)
    with path.open("rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        index = 0
        offset = 0
        while offset < size:
            header = fh.read(_HEADER.size)
            if len(header) < _HEADER.size:
                yield _error(path, index, offset, "truncated record header", resumable=False)
                return
            length, length_crc = _HEADER.unpack(header)
            if verify and masked_crc32c(header[:8]) != length_crc:
                yield _error(path, index, offset, "length CRC mismatch", resumable=False)
                return
            if offset + _HEADER.size + length + _FOOTER.size > size:
                yield _error(
                    path,
                    index,
                    offset,
                    f"truncated (needs {length} payload bytes)",
                    resumable=False,
                )
                return
            payload = fh.read(length)
            (payload_crc,) = _FOOTER.unpack(fh.read(_FOOTER.size))
            if verify and masked_crc32c(payload) != payload_crc:
                yield _error(path, index, offset, "payload CRC mismatch", resumable=True)
            else:
                yield Record(index, offset, payload)
            offset += _HEADER.size + length + _FOOTER.size
            index += 1


def _error(path: pathlib.Path, index: int, offset: int, what: str, *, resumable: bool):
    return RecordError(
        f"{path}: record {index} (byte {offset}): {what}",
        index=index,
        offset=offset,
        resumable=resumable,
    )


def encode_record(payload: bytes) -> bytes:
    """One framed record (used by tests and tools that write TFRecord files)."""
    length = struct.pack("<Q", len(payload))
    return (
        length
        + _FOOTER.pack(masked_crc32c(length))
        + payload
        + _FOOTER.pack(masked_crc32c(payload))
    )


def write_records(path: str | os.PathLike, payloads: Iterable[bytes]) -> pathlib.Path:
    """Write a TFRecord file atomically (temporary file in the same folder, then rename)."""
    path = pathlib.Path(path)
    with atomic_output(path) as tmp, tmp.open("wb") as fh:
        for payload in payloads:
            fh.write(encode_record(payload))
    return path
