"""Turn pipeline messages into JSON channel payloads and logged frames back into ``Frame``s.

Runs in the recorder's writer thread (encode) and in replay (decode), never on the event
loop: JPEG/PNG coding is the costly part. Encoding is exact for 16-bit and float images
(RawImage or PNG) and for radar points (float32 in a PointCloud); RGB is JPEG by default,
so a replayed RGB frame differs from the live one by JPEG loss only.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from respecd.messages import Bundle, Decision, Frame, Modality, Percept, SensorConfig
from respecd.record.schemas import NUMERIC_FLOAT32

RADAR_FIELDS = ("x", "y", "z", "v", "snr")  # Frame.data columns for radar, float32 each
RADAR_STRIDE = 4 * len(RADAR_FIELDS)
_IDENTITY_POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


@dataclass(frozen=True)
class ImageFormats:
    """The recording choices that matter to the encoder (a slice of RecordingConfig)."""

    rgb: str = "jpeg"
    jpeg_quality: int = 90
    wide: str = "png"  # 16-bit thermal/depth: "png" or "raw"


def stamp(log_ns: int) -> dict[str, int]:
    return {"sec": log_ns // 1_000_000_000, "nsec": log_ns % 1_000_000_000}


def dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), default=_json_default).encode()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (bytes, bytearray)):
        return base64.b64encode(value).decode()
    if hasattr(value, "value"):  # enums
        return value.value
    return str(value)


def with_data(fields: dict[str, Any], data: bytes | np.ndarray, extra: dict[str, Any] | None) -> bytes:
    """``fields`` + ``"data"`` (base64) + ``"respecd"``, as one JSON object, in that order.

    The base64 text is spliced in as bytes: it needs no escaping, and letting ``json`` scan
    a megabyte string costs more than the rest of the encoding (about 2 ms per depth frame).
    """
    raw = data if isinstance(data, bytes) else np.ascontiguousarray(data).tobytes()
    head = dumps(fields)[:-1] + (b',"data":"' if fields else b'"data":"')
    tail = b'"}' if extra is None else b'","respecd":' + dumps(extra) + b"}"
    return head + base64.b64encode(raw) + tail


def b64decode(text: str) -> bytes:
    return base64.b64decode(text)


def frame_extra(payload: bytes) -> dict[str, Any]:
    """The ``respecd`` object of a sensor message (time, seq, meta) without parsing the image.

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


def _respecd_extra(frame: Frame) -> dict[str, Any]:
    meta = {k: v for k, v in frame.meta.items() if k != "raw"}  # raw bytes have their own channel
    return {"t": frame.t, "seq": frame.seq, "modality": frame.modality, "meta": meta}


def encode_frame(frame: Frame, sensor: str, log_ns: int, formats: ImageFormats) -> tuple[str, bytes]:
    """(schema name, JSON payload) for one sensor frame."""
    head = {"timestamp": stamp(log_ns), "frame_id": sensor}
    data = frame.data
    if frame.modality == "radar":
        points = np.ascontiguousarray(data, dtype="<f4").reshape(-1, len(RADAR_FIELDS))
        body = {
            "pose": _IDENTITY_POSE,
            "point_stride": RADAR_STRIDE,
            "fields": [{"name": n, "offset": 4 * i, "type": NUMERIC_FLOAT32} for i, n in enumerate(RADAR_FIELDS)],
        }
        return "foxglove.PointCloud", with_data({**head, **body}, points.tobytes(), _respecd_extra(frame))
    if frame.modality == "imu":
        a = [float(x) for x in np.asarray(data, dtype=np.float64).reshape(-1)[:6]]
        body = {
            "linear_acceleration": {"x": a[0], "y": a[1], "z": a[2]},
            "angular_velocity": {"x": a[3], "y": a[4], "z": a[5]},
        }
        return "respecd.Imu", dumps({**head, **body, "respecd": _respecd_extra(frame)})
    return _encode_image(frame, head, formats)


def _encode_image(frame: Frame, head: dict[str, Any], formats: ImageFormats) -> tuple[str, bytes]:
    data = frame.data
    extra = _respecd_extra(frame)
    if data.dtype == np.uint8 and formats.rgb in ("jpeg", "png"):
        jpeg = formats.rgb == "jpeg"
        ext, params = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, formats.jpeg_quality]) if jpeg else (".png", [])
        ok, buf = cv2.imencode(ext, data, params)
        if ok:
            body = {"format": "jpeg" if ext == ".jpg" else "png"}
            return "foxglove.CompressedImage", with_data({**head, **body}, buf.tobytes(), extra)
    if data.dtype == np.uint16 and formats.wide == "png":
        ok, buf = cv2.imencode(".png", data, [cv2.IMWRITE_PNG_COMPRESSION, 1])  # level 1: fast, still lossless
        if ok:
            return "foxglove.CompressedImage", with_data({**head, "format": "png"}, buf.tobytes(), extra)
    encoding = _raw_encoding(frame.modality, data)
    height, width = data.shape[:2]
    body = {
        "width": int(width),
        "height": int(height),
        "encoding": encoding,
        "step": int(width * data.itemsize * (data.shape[2] if data.ndim == 3 else 1)),
    }
    pixels = np.ascontiguousarray(data.astype(data.dtype.newbyteorder("<"), copy=False))
    return "foxglove.RawImage", with_data({**head, **body}, pixels.tobytes(), extra)


_RAW_ENCODINGS = {  # Foxglove RawImage encodings; data is little-endian
    ("uint8", 3): "bgr8",
    ("uint8", 1): "mono8",
    ("uint16", 1): "mono16",
    ("float32", 1): "32FC1",
}
_RAW_DTYPES = {"bgr8": (np.uint8, 3), "rgb8": (np.uint8, 3), "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1),
               "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}


def _raw_encoding(modality: Modality, data: np.ndarray) -> str:
    channels = data.shape[2] if data.ndim == 3 else 1
    encoding = _RAW_ENCODINGS.get((data.dtype.name, channels))
    if encoding is None:
        raise ValueError(f"cannot record {modality} frames of dtype {data.dtype} with {channels} channel(s)")
    return "16UC1" if encoding == "mono16" and modality == "depth" else encoding


def decode_frame(schema: str, payload: bytes, fallback_modality: Modality, log_ns: int = 0) -> Frame:
    """The ``Frame`` a logged sensor message stands for (time and seq from the ``respecd`` object)."""
    msg = json.loads(payload)
    extra = msg.get("respecd") or {}
    modality = extra.get("modality", fallback_modality)
    if schema == "foxglove.PointCloud":
        data = _decode_points(msg)
    elif schema == "respecd.Imu":
        a, g = msg["linear_acceleration"], msg["angular_velocity"]
        data = np.array([a["x"], a["y"], a["z"], g["x"], g["y"], g["z"]], dtype=np.float32)
    elif schema == "foxglove.CompressedImage":
        raw = np.frombuffer(base64.b64decode(msg["data"]), dtype=np.uint8)
        data = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
        if data is None:
            raise ValueError(f"undecodable {msg.get('format')} image")
    elif schema == "foxglove.RawImage":
        data = _decode_raw_image(msg)
    else:
        raise ValueError(f"unknown sensor schema {schema!r}")
    t = float(extra.get("t", log_ns / 1e9))
    return Frame(modality=modality, t=t, seq=int(extra.get("seq", 0)), data=data, meta=dict(extra.get("meta") or {}))


def _decode_points(msg: dict[str, Any]) -> np.ndarray:
    stride = int(msg["point_stride"])
    raw = base64.b64decode(msg["data"])
    n = len(raw) // stride if stride else 0
    offsets = {f["name"]: int(f["offset"]) for f in msg["fields"]}
    rows = np.frombuffer(raw, dtype=np.uint8)[: n * stride].reshape(n, stride)
    cols = []
    for name in RADAR_FIELDS:
        off = offsets.get(name)
        if off is None:
            cols.append(np.zeros(n, dtype=np.float32))
        else:
            cols.append(rows[:, off : off + 4].copy().view("<f4").reshape(n))
    return np.stack(cols, axis=1).astype(np.float32) if n else np.zeros((0, len(RADAR_FIELDS)), np.float32)


def _decode_raw_image(msg: dict[str, Any]) -> np.ndarray:
    dtype, channels = _RAW_DTYPES[msg["encoding"]]
    width, height, step = int(msg["width"]), int(msg["height"]), int(msg["step"])
    raw = np.frombuffer(base64.b64decode(msg["data"]), dtype=np.uint8).reshape(height, step)
    row_bytes = width * channels * np.dtype(dtype).itemsize
    pixels = raw[:, :row_bytes].copy().view(np.dtype(dtype).newbyteorder("<")).astype(dtype)
    return pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)


def config_dict(config: SensorConfig) -> dict[str, Any]:
    return {
        "modality": config.modality,
        "enabled": config.enabled,
        "rate_hz": config.rate_hz,
        "resolution": list(config.resolution) if config.resolution else None,
        "mode": config.mode,
        "notes": list(config.notes),
    }


def config_from_dict(d: dict[str, Any]) -> SensorConfig:
    res = d.get("resolution")
    return SensorConfig(
        modality=d["modality"],
        enabled=bool(d.get("enabled", True)),
        rate_hz=float(d.get("rate_hz", 30.0)),
        resolution=(int(res[0]), int(res[1])) if res else None,
        mode=d.get("mode"),
        notes=tuple(d.get("notes") or ()),
    )


def encode_config(sensor: str, t: float, config: SensorConfig) -> bytes:
    return dumps({"t": t, "sensor": sensor, **config_dict(config)})


def encode_percept(p: Percept) -> bytes:
    rgb = p.bundle.frames.get("rgb") if p.bundle is not None else None
    return dumps({
        "t": p.t,
        "conf_agg": p.conf_agg,
        "latency_s": p.latency,
        "contributions": p.contributions,
        "detections": [
            {"box": list(d.box), "confidence": d.confidence, "label": d.label} for d in p.detections
        ],
        "pixels": int(rgb.data.shape[0] * rgb.data.shape[1]) if rgb is not None else 0,
    })


_BOX_COLOR = {"r": 0.1, "g": 0.9, "b": 0.2, "a": 1.0}
_TEXT_BG = {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.6}
_WHITE = {"r": 1.0, "g": 1.0, "b": 1.0, "a": 1.0}


def encode_annotations(p: Percept, log_ns: int) -> bytes:
    """Detections as a ``foxglove.ImageAnnotations`` overlay, stamped like the RGB frame."""
    ts = stamp(log_ns)
    points, labels = [], []
    for d in p.detections:
        x1, y1, x2, y2 = (float(v) for v in d.box)
        corners = [{"x": x1, "y": y1}, {"x": x2, "y": y1}, {"x": x2, "y": y2}, {"x": x1, "y": y2}]
        points.append({"timestamp": ts, "type": 2, "points": corners, "outline_color": _BOX_COLOR,
                       "outline_colors": [], "fill_color": {"r": 0, "g": 0, "b": 0, "a": 0}, "thickness": 2.0})
        labels.append({"timestamp": ts, "position": {"x": x1, "y": max(0.0, y1 - 14)},
                       "text": f"{d.label} {d.confidence:.2f}", "font_size": 12.0, "text_color": _WHITE,
                       "background_color": _TEXT_BG})
    return dumps({"circles": [], "points": points, "labels": labels})


def encode_decision(d: Decision) -> bytes:
    return dumps({
        "t": d.t,
        "state": list(d.state),
        "action": d.action,
        "reward": d.reward,
        "epsilon": d.epsilon,
        "q_values": list(d.q_values),
        "terms": d.terms,
        "configs": [config_dict(c) for c in d.configs],
    })


def encode_bundle(b: Bundle) -> bytes:
    return dumps({
        "t": b.t,
        "seq": b.seq,
        "rate_hz": b.sync.rate_hz,
        "jitter_ms": b.sync.jitter_ms,
        "stale_ratio": b.sync.stale_ratio,
        "health": b.sync.health.value,
        "frames": {m: [f.t, f.seq] for m, f in b.frames.items()},
    })
