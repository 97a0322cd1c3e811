"""Schemas of every channel in a respecd log.

Foxglove's well-known types (images, point clouds, image annotations, camera calibrations,
frame transforms) come from Foxglove's own library, ``foxglove-sdk``: protobuf schemas
(a ``FileDescriptorSet``) with binary payloads, so a log opens in Foxglove and validates
against the official schemas; nothing is copied by hand. respecd's own channels are JSON,
their JSON Schemas generated from the typed message models in ``respecd.record.channels``
(pydantic), flattened to the plain subset Foxglove reads (no ``$ref``, nullable as a type list).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from typing import Any

import foxglove.messages as fox

from respecd.record.channels import MODELS


@dataclass(frozen=True)
class SchemaDef:
    """What an MCAP schema record and its channels need: name, schema encoding and data,
    and the message encoding of the channels that use it."""

    name: str
    encoding: str  # schema encoding: "protobuf" | "jsonschema"
    data: bytes
    message_encoding: str  # "protobuf" | "json"


@cache
def foxglove_schema(name: str) -> SchemaDef:
    """``foxglove.RawImage`` etc., as foxglove-sdk publishes it (protobuf)."""
    schema = getattr(fox, name.removeprefix("foxglove.")).get_schema()
    return SchemaDef(schema.name, schema.encoding, bytes(schema.data), "protobuf")


@cache
def own_schema(name: str) -> SchemaDef:
    """One of respecd's own JSON channels (``respecd.Percept`` ...)."""
    return SchemaDef(name, "jsonschema", json.dumps(json_schema(name), separators=(",", ":")).encode(), "json")


def json_schema(name: str) -> dict[str, Any]:
    """The JSON Schema of channel ``name``, from its message model."""
    model = MODELS[name]
    schema = model.model_json_schema()
    return {**_plain(schema, schema.get("$defs", {})), "title": name}


def _plain(node: Any, defs: dict[str, Any]) -> Any:
    """``node`` with every ``$ref`` inlined, ``anyOf [X, null]`` written as X with a type list
    and pydantic's generated titles dropped: the JSON Schema subset Foxglove's panels read."""
    if isinstance(node, list):
        return [_plain(item, defs) for item in node]
    if not isinstance(node, dict):
        return node
    if "$ref" in node:
        return _plain({**defs[node["$ref"].rsplit("/", 1)[-1]], **{k: v for k, v in node.items() if k != "$ref"}},
                      defs)
    options = node.get("anyOf")
    if options and len(options) == 2 and {"type": "null"} in options:
        other = _plain(next(o for o in options if o != {"type": "null"}), defs)
        kinds = other.get("type", [])
        node = {**other, **{k: v for k, v in node.items() if k not in ("anyOf", "default")},
                "type": [*(kinds if isinstance(kinds, list) else [kinds]), "null"]}
    return {k: _plain(v, defs) for k, v in node.items() if k not in ("$defs", "default", "title")}


def schema_def(name: str) -> SchemaDef:
    return foxglove_schema(name) if name.startswith("foxglove.") else own_schema(name)
