"""Schemas of every channel in a respecd log.

Foxglove's well-known types (images, point clouds, image annotations, camera calibrations,
frame transforms) come from Foxglove's own library, ``foxglove-sdk``: protobuf schemas
(a ``FileDescriptorSet``) with binary payloads, so a log opens in Foxglove and validates
against the official schemas; nothing is copied by hand. respecd's own channels stay JSON
with the small JSON Schemas below.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache
from typing import Any

import foxglove.messages as fox


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
    return SchemaDef(name, "jsonschema", json.dumps(SCHEMAS[name], separators=(",", ":")).encode(), "json")


def schema_def(name: str) -> SchemaDef:
    return foxglove_schema(name) if name.startswith("foxglove.") else own_schema(name)


_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
    "description": "Timestamp of the sample",
}
_FRAME_ID = {"type": "string", "description": "Frame of reference"}
_BYTES = {"type": "string", "contentEncoding": "base64"}
_NUMBER = {"type": "number"}
_VECTOR3 = {"type": "object", "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER}}

IMU: dict[str, Any] = {
    "title": "respecd.Imu",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": _FRAME_ID,
        "linear_acceleration": {**_VECTOR3, "description": "m/s^2"},
        "angular_velocity": {**_VECTOR3, "description": "rad/s"},
    },
}

RAW_BYTES: dict[str, Any] = {
    "title": "respecd.RawBytes",
    "description": "Bytes exactly as the device sent them (radar UART data port), for the live parser",
    "type": "object",
    "properties": {"timestamp": _TIME, "frame_id": _FRAME_ID, "data": _BYTES},
}

_CONFIG_PROPS = {
    "modality": {"type": "string"},
    "enabled": {"type": "boolean"},
    "rate_hz": _NUMBER,
    "resolution": {"type": ["array", "null"], "items": {"type": "integer"}},
    "mode": {"type": ["string", "null"]},
    "notes": {"type": "array", "items": {"type": "string"}},
}

SENSOR_CONFIG: dict[str, Any] = {
    "title": "respecd.SensorConfig",
    "description": "What a driver really applied",
    "type": "object",
    "properties": {"t": _NUMBER, "sensor": {"type": "string"}, **_CONFIG_PROPS},
}

PERCEPT: dict[str, Any] = {
    "title": "respecd.Percept",
    "description": "Detections, ConfAgg and per-modality contribution scores of one bundle",
    "type": "object",
    "properties": {
        "t": _NUMBER,
        "conf_agg": _NUMBER,
        "latency_s": _NUMBER,
        "contributions": {"type": ["object", "null"], "additionalProperties": _NUMBER,
                          "description": "Per modality, normalized to sum 1: what the controller reads"},
        "dependence": {"type": ["object", "null"], "additionalProperties": _NUMBER,
                       "description": "Per modality, 0..1: share of the detections' confidence lost with it off"},
        "sufficiency": {"type": ["object", "null"], "additionalProperties": _NUMBER,
                        "description": "Per modality, 0..1: share of the detections' confidence kept with only it on"},
        "detections": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "box": {"type": "array", "items": _NUMBER},
                    "confidence": _NUMBER,
                    "label": {"type": "string"},
                },
            },
        },
        "pixels": {"type": "integer", "description": "RGB pixels in the bundle (compute proxy)"},
    },
}

DECISION: dict[str, Any] = {
    "title": "respecd.Decision",
    "description": "One controller step: state bins, action, reward and its terms, applied configs",
    "type": "object",
    "properties": {
        "t": _NUMBER,
        "state": {"type": "array", "items": {"type": "integer"}},
        "action": {"type": "integer"},
        "reward": _NUMBER,
        "epsilon": _NUMBER,
        "q_values": {"type": "array", "items": _NUMBER},
        "terms": {"type": "object", "additionalProperties": _NUMBER},
        "configs": {"type": "array", "items": {"type": "object", "properties": _CONFIG_PROPS}},
    },
}

SYNC: dict[str, Any] = {
    "title": "respecd.Sync",
    "description": "Synchronizer health at one tick and which frames it paired",
    "type": "object",
    "properties": {
        "t": _NUMBER,
        "seq": {"type": "integer"},
        "rate_hz": _NUMBER,
        "jitter_ms": _NUMBER,
        "stale_ratio": _NUMBER,
        "health": {"type": "string", "enum": ["good", "fair", "poor"]},
        "frames": {"type": "object", "description": "modality -> [frame t, frame seq]"},
    },
}

FRAME_META: dict[str, Any] = {
    "title": "respecd.FrameMeta",
    "description": (
        "What a Foxglove sensor message cannot carry: the frame's exact session time, sequence number, modality "
        "and the driver's metadata (the simulator's ground truth 'gt'); written just before the frame, same log time"
    ),
    "type": "object",
    "properties": {
        "t": _NUMBER,
        "seq": {"type": "integer"},
        "modality": {"type": "string"},
        "meta": {"type": "object"},
    },
}

SCHEMAS: dict[str, dict[str, Any]] = {
    s["title"]: s for s in (IMU, RAW_BYTES, FRAME_META, SENSOR_CONFIG, PERCEPT, DECISION, SYNC)
}
