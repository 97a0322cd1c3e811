"""Pipeline frames to Foxglove messages (protobuf, binary payloads) and back.

Runs in the recorder's writer thread (encode) and in replay (decode), never on the event
loop: JPEG/PNG coding is the costly part. The messages are ``foxglove-sdk``'s own types,
so they validate against Foxglove's schemas by construction. What a Foxglove message has no
field for (the exact session time, sequence number, driver meta such as ground truth) goes
into a ``respecd.FrameMeta`` JSON message on ``/sensors/<name>/meta``, written just before
the frame with the same log time. Camera frames are lossless by default (PNG
CompressedImage, 16-bit kept) unless the profile asks for JPEG (RGB) or RawImage; radar
points are exact (float32 PointCloud).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from typing import Any, NamedTuple

import cv2
import foxglove.messages as fox
import numpy as np

from respecd.messages import Frame, Modality
from respecd.record import lazy as lazy_frames
from respecd.record import legacy, png
from respecd.record.topics import colormap_topic, meta_topic, raw_topic, sensor_topic

RADAR_FIELDS = legacy.RADAR_FIELDS
RADAR_STRIDE = 4 * len(RADAR_FIELDS)
_RAW_ENCODINGS = {  # Foxglove RawImage encodings; data is little-endian
    ("uint8", 3): "bgr8",
    ("uint8", 1): "mono8",
    ("uint16", 1): "mono16",
    ("float32", 1): "32FC1",
}


@dataclass(frozen=True)
class ImageFormats:
    """The recording choices that matter to the encoder (a slice of RecordingConfig + profile)."""

    rgb: str = "png"  # "png" | "jpeg" | "raw"
    jpeg_quality: int = 80
    thermal: str = "png"  # "png" | "raw"
    depth: str = "png"  # "png" | "raw"
    thermal_colormap: str = "inferno"  # or "none": no display image beside the raw thermal one
    thermal_range_k: tuple[float, float] = (273.0, 313.0)  # kelvin spread over the colormap
    thermal_counts_per_k: float = 100.0  # raw uint16 counts per kelvin (centikelvin)

    def of(self, modality: str) -> str:
        """The encoding of ``modality``'s frames."""
        return {"rgb": self.rgb, "thermal": self.thermal, "depth": self.depth}.get(modality, "raw")


class Message(NamedTuple):
    """One message for a sink: topic, schema name, payload, channel metadata."""

    topic: str
    schema: str
    payload: bytes
    channel_meta: dict[str, str]


@dataclass(frozen=True)
class LoggedSchema:
    """A channel's schema as the log stores it (reader side)."""

    name: str
    message_encoding: str = "json"
    data: bytes = field(default=b"", repr=False)


def timestamp(log_ns: int) -> fox.Timestamp:
    return fox.Timestamp(log_ns // 1_000_000_000, log_ns % 1_000_000_000)


def dumps(obj: Any) -> bytes:
    return _ENCODER.encode(obj).encode()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "value"):  # enums
        return value.value
    return str(value)


_ENCODER = json.JSONEncoder(separators=(",", ":"), default=_json_default)  # one, not one per message


# -- encode -------------------------------------------------------------------------------
def encode_frame(frame: Frame, sensor: str, log_ns: int, formats: ImageFormats) -> list[Message]:
    """The messages one sensor frame becomes: its FrameMeta, then the frame (and, for a
    thermal camera, its colormapped display image)."""
    base = {"sensor": sensor, "modality": frame.modality}
    meta = {k: v for k, v in frame.meta.items() if k != "raw"}  # raw bytes have their own channel
    out = [Message(meta_topic(sensor), "respecd.FrameMeta",
                   dumps({"t": frame.t, "seq": frame.seq, "modality": frame.modality, "meta": meta}), base)]
    ts = timestamp(log_ns)
    if frame.modality == "radar":
        out.append(Message(sensor_topic(sensor), "foxglove.PointCloud", _points(frame.data, sensor, ts), base))
    elif frame.modality == "imu":
        a = [float(x) for x in np.asarray(frame.data, dtype=np.float64).reshape(-1)[:6]]
        body = {"timestamp": {"sec": ts.sec, "nsec": ts.nsec}, "frame_id": sensor,
                "linear_acceleration": {"x": a[0], "y": a[1], "z": a[2]},
                "angular_velocity": {"x": a[3], "y": a[4], "z": a[5]}}
        out.append(Message(sensor_topic(sensor), "respecd.Imu", dumps(body), base))
    else:
        schema, payload = _image(frame, sensor, ts, formats)
        out.append(Message(sensor_topic(sensor), schema, payload, base))
        if frame.modality == "thermal" and formats.thermal_colormap != "none":
            out.append(_thermal_display(frame, sensor, ts, formats))
    return out


def encode_raw(frame: Frame, sensor: str, log_ns: int) -> Message:
    """A radar frame's UART bytes (``respecd.RawBytes``, JSON as in the first format)."""
    import base64

    head = {"timestamp": {"sec": log_ns // 1_000_000_000, "nsec": log_ns % 1_000_000_000}, "frame_id": sensor,
            "data": base64.b64encode(bytes(frame.meta["raw"])).decode(), "respecd": {"t": frame.t, "seq": frame.seq}}
    meta = {"sensor": sensor, "modality": frame.modality, "format": "ti-mmwave-uart"}
    return Message(raw_topic(sensor), "respecd.RawBytes", dumps(head), meta)


def _points(data: np.ndarray, sensor: str, ts: fox.Timestamp) -> bytes:
    points = np.ascontiguousarray(data, dtype="<f4").reshape(-1, len(RADAR_FIELDS))
    float32 = fox.PackedElementFieldNumericType.Float32
    fields = [fox.PackedElementField(name=n, offset=4 * i, type=float32) for i, n in enumerate(RADAR_FIELDS)]
    pose = fox.Pose(position=fox.Vector3(x=0.0, y=0.0, z=0.0), orientation=fox.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    return fox.PointCloud(timestamp=ts, frame_id=sensor, pose=pose, point_stride=RADAR_STRIDE, fields=fields,
                          data=points.tobytes()).encode()


def _image(frame: Frame, sensor: str, ts: fox.Timestamp, formats: ImageFormats) -> tuple[str, bytes]:
    data = frame.data
    compressed = _compress(data, formats.of(frame.modality), formats.jpeg_quality)
    if compressed is not None:
        fmt, buf = compressed
        return "foxglove.CompressedImage", fox.CompressedImage(timestamp=ts, frame_id=sensor, data=buf,
                                                               format=fmt).encode()
    channels = data.shape[2] if data.ndim == 3 else 1
    encoding = _RAW_ENCODINGS.get((data.dtype.name, channels))
    if encoding is None:
        raise ValueError(f"cannot record {frame.modality} frames of dtype {data.dtype} with {channels} channel(s)")
    if encoding == "mono16" and frame.modality == "depth":
        encoding = "16UC1"  # millimetres, as ROS depth images
    height, width = data.shape[:2]
    pixels = np.ascontiguousarray(data.astype(data.dtype.newbyteorder("<"), copy=False))
    raw = fox.RawImage(timestamp=ts, frame_id=sensor, width=int(width), height=int(height), encoding=encoding,
                       step=int(width * data.itemsize * channels), data=pixels.tobytes())
    return "foxglove.RawImage", raw.encode()


def _compress(data: np.ndarray, fmt: str, jpeg_quality: int) -> tuple[str, bytes] | None:
    """(format, bytes) of ``data`` as a PNG or JPEG; None where it stays raw: asked so, or pixels
    the format cannot hold exactly (float, JPEG of anything but 8-bit colour or grey)."""
    channels = data.shape[2] if data.ndim == 3 else 1
    if fmt == "png" and data.dtype in (np.uint8, np.uint16) and channels in (1, 3, 4):
        return fmt, png.encode(data)
    if fmt != "jpeg" or data.dtype != np.uint8 or channels not in (1, 3):
        return None
    ok, buf = cv2.imencode(".jpg", data, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        raise ValueError(f"jpeg encoding of a {data.shape} {data.dtype} image failed")
    return fmt, buf.tobytes()


_COLORMAPS = {"inferno": cv2.COLORMAP_INFERNO}


@cache
def _colormap_lut(name: str) -> np.ndarray:
    """(256, 3) BGR of OpenCV's colormap: indexing it is cheaper than applyColorMap per frame."""
    ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
    return cv2.applyColorMap(ramp, _COLORMAPS[name]).reshape(256, 3)


def thermal_kelvin(data: np.ndarray, meta: dict[str, Any], counts_per_k: float) -> np.ndarray:
    """float32 kelvin of thermal pixels (raw counts, or already kelvin when ``meta["units"] == "K"``)."""
    kelvin = data.astype(np.float32)
    return kelvin if meta.get("units") == "K" else kelvin / counts_per_k


def _thermal_display(frame: Frame, sensor: str, ts: fox.Timestamp, formats: ImageFormats) -> Message:
    low, high = formats.thermal_range_k
    data = frame.data[:, :, 0] if frame.data.ndim == 3 else frame.data
    if data.dtype == np.uint8:
        scaled = data
    else:
        kelvin = thermal_kelvin(data, frame.meta, formats.thermal_counts_per_k)
        scaled = np.clip((kelvin - low) * (255.0 / (high - low)), 0, 255).astype(np.uint8)
    coloured = np.take(_colormap_lut(formats.thermal_colormap), scaled, axis=0)  # (H, W, 3) BGR
    ok, buf = cv2.imencode(".jpg", coloured, [cv2.IMWRITE_JPEG_QUALITY, formats.jpeg_quality])
    if not ok:
        raise ValueError("thermal display image: JPEG encoding failed")
    return Message(colormap_topic(sensor), "foxglove.CompressedImage",
                   fox.CompressedImage(timestamp=ts, frame_id=sensor, data=buf.tobytes(), format="jpeg").encode(),
                   thermal_scale(sensor, formats))


def thermal_scale(sensor: str, formats: ImageFormats) -> dict[str, str]:
    """Channel metadata of the display image: what its colours mean."""
    low, high = formats.thermal_range_k
    return {"sensor": sensor, "modality": "thermal", "display": "true", "colormap": formats.thermal_colormap,
            "source_topic": sensor_topic(sensor), "min_k": f"{low:g}", "max_k": f"{high:g}",
            "min_c": f"{low - 273.15:.2f}", "max_c": f"{high - 273.15:.2f}",
            "scale": f"{formats.thermal_colormap} from {low - 273.15:.1f} °C (dark) to {high - 273.15:.1f} °C (bright)"}


# -- decode -------------------------------------------------------------------------------
@cache
def _decoder(name: str, data: bytes) -> Callable[[bytes], Any]:
    from mcap.records import Schema
    from mcap_protobuf.decoder import DecoderFactory

    decoder = DecoderFactory().decoder_for("protobuf", Schema(id=1, name=name, encoding="protobuf", data=data))
    if decoder is None:
        raise ValueError(f"cannot build a protobuf decoder for {name!r}")
    return decoder


def decode_message(schema: LoggedSchema, payload: bytes) -> Any:
    """A protobuf message object (by the log's own schema) or, for JSON channels, a dict."""
    if schema.message_encoding == "protobuf":
        return _decoder(schema.name, schema.data)(payload)
    return json.loads(payload)


def decode_frame(schema: LoggedSchema, payload: bytes, fallback_modality: Modality, log_ns: int = 0,
                 meta: dict[str, Any] | None = None, lazy: bool = False) -> Frame:
    """The ``Frame`` a logged sensor message stands for; ``meta`` is its FrameMeta (new
    format). First-format logs (JSON, inline ``respecd`` object) decode as they always did.
    ``lazy``: a JPEG or PNG becomes a ``LazyFrame``, decoded when its pixels are first read."""
    if schema.message_encoding == "json" and meta is None:
        return legacy.decode_frame(schema.name, payload, fallback_modality, log_ns)
    meta = meta or {}
    modality = meta.get("modality", fallback_modality)
    msg = decode_message(schema, payload)
    t = float(meta.get("t", log_ns / 1e9))
    if lazy and schema.name == "foxglove.CompressedImage" and (shape := lazy_frames.encoded_shape(msg.data)):
        encoded, fmt = msg.data, msg.format
        return lazy_frames.LazyFrame(modality, t, int(meta.get("seq", 0)), meta=dict(meta.get("meta") or {}),
                                     decode=lambda: legacy.decode_compressed(encoded, fmt), shape=shape)
    if schema.name == "foxglove.PointCloud":
        data = legacy.points_array(msg.data, msg.point_stride, {f.name: f.offset for f in msg.fields})
    elif schema.name == "respecd.Imu":
        data = legacy.imu_array(msg)
    elif schema.name == "foxglove.CompressedImage":
        data = legacy.decode_compressed(msg.data, msg.format)
    elif schema.name == "foxglove.RawImage":
        data = legacy.decode_raw(msg.data, msg.encoding, msg.width, msg.height, msg.step)
    else:
        raise ValueError(f"unknown sensor schema {schema.name!r}")
    return Frame(modality=modality, t=t, seq=int(meta.get("seq", 0)), data=data, meta=dict(meta.get("meta") or {}))
