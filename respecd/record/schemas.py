"""JSON Schemas of every channel in a respecd log.

Sensor channels use Foxglove's well-known schemas (field names and types as published in
github.com/foxglove/schemas, ``schemas/jsonschema``) so a log opens in Foxglove with images
and radar points visible. JSON message encoding carries bytes as base64 strings, as those
schemas say (``contentEncoding: base64``). respecd's own channels have small schemas of
their own. Messages may carry an extra ``respecd`` object (exact time, sequence, driver
meta); JSON Schema allows extra properties, and Foxglove ignores them.
"""

from __future__ import annotations

import json
from typing import Any

NUMERIC_FLOAT32 = 7  # foxglove.NumericType.FLOAT32

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

COMPRESSED_IMAGE: dict[str, Any] = {
    "title": "foxglove.CompressedImage",
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": _FRAME_ID,
        "data": {**_BYTES, "description": "Compressed image data"},
        "format": {"type": "string", "description": "Image format (jpeg, png, webp, avif)"},
    },
}

RAW_IMAGE: dict[str, Any] = {
    "title": "foxglove.RawImage",
    "description": "A raw image",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": _FRAME_ID,
        "width": {"type": "integer", "minimum": 0, "description": "Image width"},
        "height": {"type": "integer", "minimum": 0, "description": "Image height"},
        "encoding": {"type": "string", "description": "Encoding of the raw image data (mono16, 16UC1, 32FC1, ...)"},
        "step": {"type": "integer", "minimum": 0, "description": "Byte length of a single row"},
        "data": {**_BYTES, "description": "Raw image data"},
    },
}

_NUMERIC_TYPE = {
    "title": "foxglove.NumericType",
    "oneOf": [
        {"title": title, "const": i}
        for i, title in enumerate(
            ["UNKNOWN", "UINT8", "INT8", "UINT16", "INT16", "UINT32", "INT32", "FLOAT32", "FLOAT64"]
        )
    ],
}

POINT_CLOUD: dict[str, Any] = {
    "title": "foxglove.PointCloud",
    "description": "A collection of N-dimensional points",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": _FRAME_ID,
        "pose": {
            "title": "foxglove.Pose",
            "type": "object",
            "properties": {
                "position": {"title": "foxglove.Vector3", **_VECTOR3},
                "orientation": {
                    "title": "foxglove.Quaternion",
                    "type": "object",
                    "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER},
                },
            },
        },
        "point_stride": {"type": "integer", "minimum": 0, "description": "Number of bytes between points in `data`"},
        "fields": {
            "type": "array",
            "items": {
                "title": "foxglove.PackedElementField",
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "offset": {"type": "integer", "minimum": 0},
                    "type": _NUMERIC_TYPE,
                },
            },
        },
        "data": {**_BYTES, "description": "Point data, interpreted using `fields`"},
    },
}

_COLOR = {"title": "foxglove.Color", "type": "object", "properties": {k: _NUMBER for k in "rgba"}}
_POINT2 = {"title": "foxglove.Point2", "type": "object", "properties": {"x": _NUMBER, "y": _NUMBER}}
_POINTS_TYPE = {
    "title": "foxglove.PointsAnnotationType",
    "oneOf": [
        {"title": title, "const": i}
        for i, title in enumerate(["UNKNOWN", "POINTS", "LINE_LOOP", "LINE_STRIP", "LINE_LIST"])
    ],
}

IMAGE_ANNOTATIONS: dict[str, Any] = {
    "title": "foxglove.ImageAnnotations",
    "description": "Array of annotations for a 2D image",
    "type": "object",
    "properties": {
        "circles": {"type": "array", "items": {"title": "foxglove.CircleAnnotation", "type": "object"}},
        "points": {
            "type": "array",
            "items": {
                "title": "foxglove.PointsAnnotation",
                "type": "object",
                "properties": {
                    "timestamp": _TIME,
                    "type": _POINTS_TYPE,
                    "points": {"type": "array", "items": _POINT2},
                    "outline_color": _COLOR,
                    "outline_colors": {"type": "array", "items": _COLOR},
                    "fill_color": _COLOR,
                    "thickness": _NUMBER,
                },
            },
        },
        "labels": {
            "type": "array",
            "items": {
                "title": "foxglove.TextAnnotation",
                "type": "object",
                "properties": {
                    "timestamp": _TIME,
                    "position": _POINT2,
                    "text": {"type": "string"},
                    "font_size": _NUMBER,
                    "text_color": _COLOR,
                    "background_color": _COLOR,
                },
            },
        },
    },
}

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
        "contributions": {"type": ["object", "null"], "additionalProperties": _NUMBER},
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

SCHEMAS: dict[str, dict[str, Any]] = {
    s["title"]: s
    for s in (COMPRESSED_IMAGE, RAW_IMAGE, POINT_CLOUD, IMAGE_ANNOTATIONS, IMU, RAW_BYTES, SENSOR_CONFIG, PERCEPT,
              DECISION, SYNC)
}


def schema_bytes(name: str) -> bytes:
    """The schema record's data: the JSON Schema document, UTF-8."""
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode()
