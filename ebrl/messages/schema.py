"""The JSON Schema of each message type, as it appears after msgpack decoding; ``schemas/`` is written from here
(``ebrl schemas``, ``make schemas``)."""

from __future__ import annotations

import dataclasses
import json
import os
import types
import typing
from typing import Annotated, Any, Literal, get_args, get_origin

from ebrl.messages.common import SCHEMA_VERSION
from ebrl.messages.wire import MESSAGES, type_hints
from ebrl.typecheck import Array


def json_schema(cls: type) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of one message type, as it appears after msgpack decoding."""
    hints = type_hints(cls)
    props: dict[str, Any] = {"v": {"const": SCHEMA_VERSION, "description": "schema version"}}
    required = ["v"]
    for f in dataclasses.fields(cls):
        prop = _schema_of(hints[f.name])
        prop["description"] = f.metadata.get("doc", "")
        props[f.name] = prop
        if f.default is dataclasses.MISSING:
            required.append(f.name)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": f"ebrl/{cls.__name__}.json",
        "title": cls.__name__,
        "description": (cls.__doc__ or "").strip(),
        "x-ebrl-key": cls.KEY,
        "x-ebrl-max-bytes": cls.MAX_BYTES,
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }


def _schema_of(tp: Any) -> dict[str, Any]:
    origin = get_origin(tp)
    if origin is Annotated:
        base, *extra = get_args(tp)
        spec = next((e for e in extra if isinstance(e, Array)), None)
        if spec is not None:
            return {
                "x-ebrl-ndarray": {"dtype": spec.dtype or "numeric", "ndim": spec.ndim},
                "description": "numpy array (msgpack extension type 1, see ebrl/codec.py)",
            }
        return _schema_of(base)
    if origin in (types.UnionType, typing.Union):
        return {"anyOf": [_schema_of(a) for a in get_args(tp)]}
    if origin is Literal:
        return {"enum": list(get_args(tp))}
    if origin is list:
        return {"type": "array", "items": _schema_of(get_args(tp)[0])}
    if origin is dict:
        return {"type": "object", "additionalProperties": _schema_of(get_args(tp)[1])}
    names = {float: "number", int: "integer", bool: "boolean", str: "string", type(None): "null"}
    return {"type": names[tp]}


def write_schemas(directory: str) -> list[str]:
    """Write one ``<Message>.json`` per message type into ``directory``; return the paths."""
    os.makedirs(directory, exist_ok=True)
    paths = []
    for cls in MESSAGES:
        path = os.path.join(directory, f"{cls.__name__}.json")
        with open(path, "w") as fh:
            fh.write(json.dumps(json_schema(cls), indent=2) + "\n")
        paths.append(path)
    return paths
