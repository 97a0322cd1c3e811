"""Decoding logs in respecd's first recording format (0.1.0): JSON messages with base64
payloads and an inline ``respecd`` object (exact time, sequence, driver meta).

Only reading is kept: ``log info`` and replay still open such logs. New logs are written by
``respecd.record.codec`` (Foxglove protobuf, binary payloads).
"""

from __future__ import annotations

import base64
import json
from typing import Any

import cv2
import numpy as np

from respecd.errors import UndecodableImageError
from respecd.messages import Frame, Modality

RADAR_FIELDS = ("x", "y", "z", "v", "snr")  # Frame.data columns for radar, float32 each

RAW_DTYPES = {"bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3), "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1),
              "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}


def frame_extra(payload: bytes) -> dict[str, Any]:
    """The ``respecd`` object of a first-format sensor message without parsing the image.

    It follows the base64 ``data`` string, which cannot contain a quote, so it is found by
    searching past that string; anything unexpected falls back to a full parse.
    """
    start = payload.find(b'"data":"')
    end = payload.find(b'"', start + 8) if start >= 0 else -1
    key = payload.find(b'"respecd":', end) if end >= 0 else -1
    if key >= 0 and payload.endswith(b"}"):
        try:
            return json.loads(payload[key + 10 : -1])
        except ValueError:
            pass
    return json.loads(payload).get("respecd") or {}


def raw_bytes(payload: bytes) -> tuple[int, bytes]:
    """(seq, bytes) of a ``respecd.RawBytes`` message (the same JSON in both formats)."""
    msg = json.loads(payload)
    return int((msg.get("respecd") or {}).get("seq", -1)), base64.b64decode(msg["data"])


def decode_frame(schema: str, payload: bytes, fallback_modality: Modality, log_ns: int = 0) -> Frame:
    """The ``Frame`` a first-format sensor message stands for."""
    msg = json.loads(payload)
    extra = msg.get("respecd") or {}
    modality = extra.get("modality", fallback_modality)
    if schema == "foxglove.PointCloud":
        data = _decode_points(msg)
    elif schema == "respecd.Imu":
        data = imu_array(msg)
    elif schema == "foxglove.CompressedImage":
        data = decode_compressed(base64.b64decode(msg["data"]), msg.get("format", ""))
    elif schema == "foxglove.RawImage":
        raw = base64.b64decode(msg["data"])
        data = decode_raw(raw, msg["encoding"], int(msg["width"]), int(msg["height"]), int(msg["step"]))
    else:
        raise ValueError(f"unknown sensor schema {schema!r}")
    t = float(extra.get("t", log_ns / 1e9))
    return Frame(modality=modality, t=t, seq=int(extra.get("seq", 0)), data=data, meta=dict(extra.get("meta") or {}))


def imu_array(msg: dict[str, Any]) -> np.ndarray:
    a, g = msg["linear_acceleration"], msg["angular_velocity"]
    return np.array([a["x"], a["y"], a["z"], g["x"], g["y"], g["z"]], dtype=np.float32)


def decode_compressed(raw: bytes, fmt: str) -> np.ndarray:
    data = cv2.imdecode(np.frombuffer(raw, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise UndecodableImageError(f"undecodable {fmt} image")
    return data


def _decode_points(msg: dict[str, Any]) -> np.ndarray:
    offsets = {f["name"]: int(f["offset"]) for f in msg["fields"]}
    return points_array(base64.b64decode(msg["data"]), int(msg["point_stride"]), offsets)


def points_array(raw: bytes, stride: int, offsets: dict[str, int]) -> np.ndarray:
    """(N, 5) float32 x, y, z, v, snr from packed float32 point data (missing fields are 0)."""
    n = len(raw) // stride if stride else 0
    if n == 0:
        return np.zeros((0, len(RADAR_FIELDS)), np.float32)
    rows = np.frombuffer(raw, dtype=np.uint8)[: n * stride].reshape(n, stride)
    cols = []
    for name in RADAR_FIELDS:
        off = offsets.get(name)
        if off is None:
            cols.append(np.zeros(n, dtype=np.float32))
        else:
            cols.append(rows[:, off : off + 4].copy().view("<f4").reshape(n))
    return np.stack(cols, axis=1).astype(np.float32)


def decode_raw(raw: bytes, encoding: str, width: int, height: int, step: int) -> np.ndarray:
    """A raw image's pixels (little-endian rows of ``step`` bytes) as an (H, W[, C]) array."""
    dtype, channels = RAW_DTYPES[encoding]
    rows = np.frombuffer(raw, dtype=np.uint8)[: height * step].reshape(height, step)
    row_bytes = width * channels * np.dtype(dtype).itemsize
    pixels = rows[:, :row_bytes].copy().view(np.dtype(dtype).newbyteorder("<")).astype(dtype)
    return pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)
