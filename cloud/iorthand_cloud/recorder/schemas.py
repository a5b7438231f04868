"""MCAP schemas for our msgpack messages: a JSON Schema generated from each :mod:`iorthand.protocol` class.

Messages are stored exactly as received (msgpack bytes); the schema documents them for any reader, with the
field bounds the decoder enforces. The MCAP message encoding is ``msgpack`` (not one Foxglove decodes: the
bytes on the wire are the truth, and no conversion can corrupt them).
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from typing import Any

from iorthand.protocol import Message, Struct

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "msgpack"
RAW_ENCODING = "raw"  # keys without a message type, and payloads that failed to decode


def _type_schema(hint: Any, meta: dict[str, Any]) -> dict[str, Any]:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        inner = _type_schema(args[0], meta)
        return {"anyOf": [inner, {"type": "null"}]}
    if origin is list:
        (item,) = typing.get_args(hint)
        out: dict[str, Any] = {"type": "array"}
        if dataclasses.is_dataclass(item):
            out["items"] = struct_schema(item)
        else:
            out["items"] = _type_schema(item, {"lo": meta.get("lo"), "hi": meta.get("hi")})
        if meta.get("length") is not None:
            out["minItems"] = out["maxItems"] = meta["length"]
        elif meta.get("max_len") is not None:
            out["maxItems"] = meta["max_len"]
        return out
    if dataclasses.is_dataclass(hint):
        return struct_schema(hint)
    names = {bool: "boolean", int: "integer", float: "number", str: "string", bytes: "string"}
    out = {"type": names.get(hint, "string")}
    if hint is bytes:
        out["contentEncoding"] = "binary (msgpack bin)"
    if hint in (int, float):
        if meta.get("lo") is not None:
            out["minimum"] = meta["lo"]
        if meta.get("hi") is not None:
            out["maximum"] = meta["hi"]
    if hint in (str, bytes) and meta.get("max_len") is not None:
        out["maxLength"] = meta["max_len"]
    return out


def struct_schema(cls: type[Struct]) -> dict[str, Any]:
    props = {name: _type_schema(hint, meta) for name, hint, meta in cls._fields()}
    return {"type": "object", "properties": props, "required": list(props)}


def message_schema(cls: type[Message]) -> dict[str, Any]:
    schema = struct_schema(cls)
    schema["properties"]["v"] = {"const": cls.VERSION}
    schema["required"].append("v")
    schema.update({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": cls.__name__,
        "description": (cls.__doc__ or "").strip(),
        "x-wire-encoding": MESSAGE_ENCODING,
        "x-key-suffix": cls.KEY,
        "x-version": cls.VERSION,
    })
    return schema


def schema_bytes(cls: type[Message]) -> bytes:
    return json.dumps(message_schema(cls), sort_keys=True).encode()
