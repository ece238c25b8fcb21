"""Protobuf message classes built at run time from a ``.proto`` file, without protoc.

Supports the subset the project's schemas use: ``syntax = "proto3"``, ``package``, top-level ``enum`` and
``message`` blocks, scalar/enum/message fields, ``repeated`` and ``oneof``; ``//`` comments. Anything else is a
ValueError naming the line, so a schema change cannot be silently misread. The file is parsed into a
``FileDescriptorProto`` and loaded into a private descriptor pool.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

_F = descriptor_pb2.FieldDescriptorProto
_SCALARS = {
    "double": _F.TYPE_DOUBLE, "float": _F.TYPE_FLOAT, "int32": _F.TYPE_INT32, "int64": _F.TYPE_INT64,
    "uint32": _F.TYPE_UINT32, "uint64": _F.TYPE_UINT64, "sint32": _F.TYPE_SINT32, "sint64": _F.TYPE_SINT64,
    "fixed32": _F.TYPE_FIXED32, "fixed64": _F.TYPE_FIXED64, "sfixed32": _F.TYPE_SFIXED32,
    "sfixed64": _F.TYPE_SFIXED64, "bool": _F.TYPE_BOOL, "string": _F.TYPE_STRING, "bytes": _F.TYPE_BYTES,
}
_TOKENS = re.compile(r'"[^"]*"|[A-Za-z_][\w.]*|\d+|[{}=;]')
_FIELD = re.compile(r"^(repeated\s+)?([\w.]+)\s+(\w+)\s*=\s*(\d+)\s*;$")
_ENUM_VALUE = re.compile(r"^(\w+)\s*=\s*(\d+)\s*;$")


def parse_proto(text: str, name: str = "schema.proto") -> descriptor_pb2.FileDescriptorProto:
    """Parse the supported proto3 subset into a FileDescriptorProto (see the module docstring)."""
    fdp = descriptor_pb2.FileDescriptorProto(name=name, syntax="proto3")
    enums: set[str] = set()
    stack: list[tuple[str, object]] = []  # ("message", DescriptorProto) | ("enum", ...) | ("oneof", (msg, index))
    pending: list[tuple[descriptor_pb2.FieldDescriptorProto, str]] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split("//", 1)[0].strip()
        if not line:
            continue
        where = f"{name}:{lineno}: {raw.strip()!r}"
        if m := re.match(r'^syntax\s*=\s*"(\w+)"\s*;$', line):
            if m.group(1) != "proto3":
                raise ValueError(f"{where}: only proto3 is supported")
        elif m := re.match(r"^package\s+([\w.]+)\s*;$", line):
            fdp.package = m.group(1)
        elif m := re.match(r"^(message|enum|oneof)\s+(\w+)\s*\{$", line):
            kind, ident = m.groups()
            if kind == "message":
                if stack:
                    raise ValueError(f"{where}: nested messages are not supported")
                stack.append(("message", fdp.message_type.add(name=ident)))
            elif kind == "enum":
                if stack:
                    raise ValueError(f"{where}: nested enums are not supported")
                enums.add(ident)
                stack.append(("enum", fdp.enum_type.add(name=ident)))
            else:
                if not stack or stack[-1][0] != "message":
                    raise ValueError(f"{where}: oneof outside a message")
                msg = stack[-1][1]
                msg.oneof_decl.add(name=ident)  # type: ignore[attr-defined]
                stack.append(("oneof", (msg, len(msg.oneof_decl) - 1)))  # type: ignore[attr-defined]
        elif line == "}":
            if not stack:
                raise ValueError(f"{where}: unbalanced brace")
            stack.pop()
        elif stack and stack[-1][0] == "enum" and (m := _ENUM_VALUE.match(line)):
            stack[-1][1].value.add(name=m.group(1), number=int(m.group(2)))  # type: ignore[attr-defined]
        elif stack and stack[-1][0] in ("message", "oneof") and (m := _FIELD.match(line)):
            repeated, type_name, ident, number = m.groups()
            msg, oneof = (stack[-1][1], None) if stack[-1][0] == "message" else stack[-1][1]  # type: ignore[misc]
            if oneof is not None and repeated:
                raise ValueError(f"{where}: repeated field inside oneof")
            field = msg.field.add(name=ident, number=int(number), json_name=_camel(ident),  # type: ignore[attr-defined]
                                  label=_F.LABEL_REPEATED if repeated else _F.LABEL_OPTIONAL)
            if oneof is not None:
                field.oneof_index = oneof
            if type_name in _SCALARS:
                field.type = _SCALARS[type_name]
            else:
                pending.append((field, type_name))
        else:
            raise ValueError(f"{where}: unsupported proto syntax")
    if stack:
        raise ValueError(f"{name}: unclosed block {stack[-1][0]}")
    messages = {m.name for m in fdp.message_type}
    for field, type_name in pending:
        if type_name in enums:
            field.type = _F.TYPE_ENUM
        elif type_name in messages:
            field.type = _F.TYPE_MESSAGE
        else:
            raise ValueError(f"{name}: unknown type {type_name!r} of field {field.name!r}")
        field.type_name = f".{fdp.package}.{type_name}" if fdp.package else f".{type_name}"
    return fdp


def _camel(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(part.title() for part in rest)


@cache
def load_proto(path: str) -> dict[str, type]:
    """Message classes of a ``.proto`` file: ``{"MessageName": class}`` (cached per path)."""
    p = Path(path)
    fdp = parse_proto(p.read_text(), name=p.name)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    prefix = f"{fdp.package}." if fdp.package else ""
    return {m.name: message_factory.GetMessageClass(pool.FindMessageTypeByName(prefix + m.name))
            for m in fdp.message_type}


def enum_values(path: str, enum: str) -> dict[str, int]:
    """Name -> number of a top-level enum of a ``.proto`` file."""
    fdp = parse_proto(Path(path).read_text(), name=Path(path).name)
    for e in fdp.enum_type:
        if e.name == enum:
            return {v.name: v.number for v in e.value}
    raise ValueError(f"{path}: no enum {enum!r}")
