"""The scene format's constants and protobuf message classes, built from ``scene.proto``.

The message classes are made at import time from the ``.proto`` file shipped beside this
module, through a protobuf descriptor, instead of committing ``protoc`` output: generated
``*_pb2.py`` files pin the protobuf runtime to at least the generating ``protoc``'s
version, while descriptors built at run time work with every protobuf from 4.25 to 7.
The ``.proto`` stays the single source of truth (the file embedded in every MCAP).

Only the subset of proto3 that ``scene.proto`` uses is parsed: ``syntax``, ``package``,
top-level ``enum`` and ``message`` blocks, scalar / enum / message fields with an optional
``repeated`` label, and comments. Anything else is rejected with the line number, so the
parser can never silently drop part of the schema.
"""

from __future__ import annotations

import pathlib
import re
from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from converters.scene.errors import ProtoSyntaxError

FORMAT_VERSION = 2
"""Integer version of the format; readers refuse files with a newer version and read
every older one (version 1 lacks ``Map.lines``, which then reads as empty)."""

MAP_LINE_KINDS: tuple[str, ...] = ("lane_boundary", "road_edge", "crosswalk", "stop_line", "other")
"""The values of ``MapLine.kind`` (version 2). Readers treat an unknown kind as ``other``."""

PROTO_PATH = pathlib.Path(__file__).with_name("scene.proto")

TOPIC_MAP = "/map"
TOPIC_AGENTS = "/agents"
TOPIC_PATHS = "/paths"
TOPIC_LABELS = "/labels"
REQUIRED_TOPICS: tuple[str, ...] = (TOPIC_MAP, TOPIC_AGENTS, TOPIC_PATHS)

METADATA_NAME = "scene"
"""Name of the MCAP metadata record holding the scene's string facts."""

# Quantisation steps: a stored integer k means k * step in SI units.
MM_PER_M = 1000.0  # positions, path and lane points, lengths, widths
MMPS_PER_MPS = 1000.0  # speeds
URAD_PER_RAD = 1_000_000.0  # headings

_SCALARS = {
    "double": descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE,
    "float": descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT,
    "int32": descriptor_pb2.FieldDescriptorProto.TYPE_INT32,
    "int64": descriptor_pb2.FieldDescriptorProto.TYPE_INT64,
    "uint32": descriptor_pb2.FieldDescriptorProto.TYPE_UINT32,
    "uint64": descriptor_pb2.FieldDescriptorProto.TYPE_UINT64,
    "sint32": descriptor_pb2.FieldDescriptorProto.TYPE_SINT32,
    "sint64": descriptor_pb2.FieldDescriptorProto.TYPE_SINT64,
    "bool": descriptor_pb2.FieldDescriptorProto.TYPE_BOOL,
    "string": descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
    "bytes": descriptor_pb2.FieldDescriptorProto.TYPE_BYTES,
}

_COMMENT = re.compile(r"//[^\n]*|/\*.*?\*/", re.DOTALL)
_STATEMENTS = (
    ("syntax", re.compile(r'syntax\s*=\s*"(proto3)"\s*;')),
    ("package", re.compile(r"package\s+([A-Za-z_][\w.]*)\s*;")),
    ("block", re.compile(r"(message|enum)\s+([A-Za-z_]\w*)\s*\{([^{}]*)\}")),
)
_FIELD = re.compile(r"(repeated\s+)?([A-Za-z_][\w.]*)\s+([A-Za-z_]\w*)\s*=\s*(\d+)\s*;")
_ENUM_VALUE = re.compile(r"([A-Za-z_]\w*)\s*=\s*(-?\d+)\s*;")


def parse_proto(text: str, filename: str = "scene.proto") -> descriptor_pb2.FileDescriptorProto:
    """Parse the supported proto3 subset into a ``FileDescriptorProto``."""
    # Blank out comments but keep newlines, so that error line numbers stay right.
    body = _COMMENT.sub(lambda m: re.sub(r"[^\n]", " ", m.group()), text)
    fdp = descriptor_pb2.FileDescriptorProto(name=filename)
    blocks: list[tuple[str, str, str, int]] = []
    pos = 0
    while True:
        while pos < len(body) and body[pos].isspace():
            pos += 1
        if pos >= len(body):
            break
        kind, m = _statement(body, pos, filename)
        if kind == "syntax":
            fdp.syntax = m.group(1)
        elif kind == "package":
            fdp.package = m.group(1)
        else:
            blocks.append((m.group(1), m.group(2), m.group(3), body.count("\n", 0, m.start(3))))
        pos = m.end()
    if fdp.syntax != "proto3":
        raise ProtoSyntaxError(f'{filename}: expected syntax = "proto3"')
    enums = {name for kind, name, _, _ in blocks if kind == "enum"}
    messages = {name for kind, name, _, _ in blocks if kind == "message"}
    for kind, name, inner, first_line in blocks:
        if kind == "enum":
            _parse_enum(fdp.enum_type.add(name=name), inner, filename, first_line)
        else:
            message = fdp.message_type.add(name=name)
            _parse_message(message, inner, fdp.package, enums, messages, filename, first_line)
    return fdp


def _statement(body: str, pos: int, filename: str) -> tuple[str, re.Match[str]]:
    """The top-level statement starting at ``pos``: its kind and match."""
    for kind, pattern in _STATEMENTS:
        m = pattern.match(body, pos)
        if m:
            return kind, m
    line = body.count("\n", 0, pos) + 1
    raise ProtoSyntaxError(f"{filename}:{line}: unsupported statement")


def _items(inner: str, pattern: re.Pattern[str], filename: str, first_line: int):
    """Yield the matches of ``pattern`` that together cover ``inner`` (else raise)."""
    pos = 0
    while True:
        while pos < len(inner) and inner[pos].isspace():
            pos += 1
        if pos >= len(inner):
            return
        m = pattern.match(inner, pos)
        if not m:
            line = first_line + inner.count("\n", 0, pos) + 1
            raise ProtoSyntaxError(f"{filename}:{line}: unsupported declaration")
        yield m
        pos = m.end()


def _parse_enum(enum: Any, inner: str, filename: str, first_line: int) -> None:
    for m in _items(inner, _ENUM_VALUE, filename, first_line):
        enum.value.add(name=m.group(1), number=int(m.group(2)))


def _parse_message(
    message: Any,
    inner: str,
    package: str,
    enums: set[str],
    messages: set[str],
    filename: str,
    first_line: int,
) -> None:
    label = descriptor_pb2.FieldDescriptorProto
    for m in _items(inner, _FIELD, filename, first_line):
        repeated, type_name, name, number = m.group(1), m.group(2), m.group(3), int(m.group(4))
        field = message.field.add(name=name, number=number, json_name=_json_name(name))
        field.label = label.LABEL_REPEATED if repeated else label.LABEL_OPTIONAL
        if type_name in _SCALARS:
            field.type = _SCALARS[type_name]
        elif type_name in enums or type_name in messages:
            field.type = label.TYPE_ENUM if type_name in enums else label.TYPE_MESSAGE
            field.type_name = f".{package}.{type_name}"
        else:
            line = first_line + inner.count("\n", 0, m.start()) + 1
            raise ProtoSyntaxError(f"{filename}:{line}: unknown type {type_name!r}")


def _json_name(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(part[:1].upper() + part[1:] for part in rest)


def _build() -> tuple[descriptor_pb2.FileDescriptorProto, dict[str, Any]]:
    fdp = parse_proto(PROTO_PATH.read_text(encoding="utf-8"))
    # A private pool: importing this module twice (or another package defining the same
    # names) can never clash with protobuf's default pool.
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    classes = {
        m.name: message_factory.GetMessageClass(
            pool.FindMessageTypeByName(f"{fdp.package}.{m.name}")
        )
        for m in fdp.message_type
    }
    return fdp, classes


FILE_DESCRIPTOR, _CLASSES = _build()
PACKAGE: str = FILE_DESCRIPTOR.package

Agents = _CLASSES["Agents"]
Paths = _CLASSES["Paths"]
Lane = _CLASSES["Lane"]
Map = _CLASSES["Map"]
MapLine = _CLASSES["MapLine"]
Label = _CLASSES["Label"]
Labels = _CLASSES["Labels"]

TOPIC_SCHEMAS: dict[str, str] = {
    TOPIC_MAP: f"{PACKAGE}.Map",
    TOPIC_AGENTS: f"{PACKAGE}.Agents",
    TOPIC_PATHS: f"{PACKAGE}.Paths",
    TOPIC_LABELS: f"{PACKAGE}.Labels",
}
"""Topic -> fully qualified protobuf message name (the MCAP schema name)."""


def file_descriptor_set() -> bytes:
    """The serialised ``FileDescriptorSet`` that MCAP embeds as each channel's schema."""
    fds = descriptor_pb2.FileDescriptorSet()
    fds.file.add().CopyFrom(FILE_DESCRIPTOR)
    return fds.SerializeToString()
