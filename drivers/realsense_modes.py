"""Pure helpers of the RealSense driver: stream-mode choice and frame conversion.

No pyrealsense2 here, so profile selection and conversions are tested on any machine.
A ``StreamMode`` is one stream profile a sensor offers (what
``sensor.get_stream_profiles()`` lists); the driver turns SDK profiles into these, asks
``select_video_mode`` which one to open, and converts the frames it gets with the
functions below.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from respecd.drivers.base import MAX_RATE_HZ, Capabilities
from respecd.messages import Modality, Resolution

# preferred pixel formats per stream, best first (bgr8 needs no conversion for OpenCV order)
FORMATS = {"depth": ("z16",), "color": ("bgr8", "rgb8", "yuyv"), "infrared": ("y8",)}
MOTION_STREAMS = ("accel", "gyro", "pose")


@dataclass(frozen=True, order=True, slots=True)
class StreamMode:
    """One stream profile: stream type, pixel format, size (0 for motion) and frame rate."""

    stream: str
    fmt: str
    width: int
    height: int
    fps: int

    @property
    def size(self) -> Resolution:
        return (self.width, self.height)


def video_modes(modes: list[StreamMode], stream: str) -> list[StreamMode]:
    """The modes of ``stream`` in its most preferred format that the device offers."""
    of_stream = [m for m in modes if m.stream == stream]
    for fmt in FORMATS.get(stream, ()):
        chosen = [m for m in of_stream if m.fmt == fmt]
        if chosen:
            return chosen
    return []


def video_capabilities(modes: list[StreamMode], modality: Modality) -> Capabilities:
    """Sizes largest first; the rate range is what the fastest mode gives, capped at 30 Hz."""
    sizes = sorted({m.size for m in modes}, key=lambda r: r[0] * r[1], reverse=True)
    top = max((m.fps for m in modes), default=MAX_RATE_HZ)
    return Capabilities(modality, tuple(sizes), max_rate_hz=float(min(MAX_RATE_HZ, top)))


def select_video_mode(
    modes: list[StreamMode], resolution: Resolution | None, rate_hz: float
) -> tuple[StreamMode, list[str]]:
    """The mode to open for a (clamped) request, and notes on what differs from it.

    Size: the exact one, else the nearest in area. Rate: the slowest mode at that size that
    is still at least ``rate_hz`` (the driver decimates the rest), else the fastest there is.
    """
    if not modes:
        raise ValueError("the sensor offers no mode for this stream")
    notes: list[str] = []
    sizes = {m.size for m in modes}
    size = resolution if resolution in sizes else None
    if size is None:
        wanted = resolution or max(sizes, key=lambda r: r[0] * r[1])
        size = min(sizes, key=lambda r: (abs(r[0] * r[1] - wanted[0] * wanted[1]), -r[0]))
        if resolution is not None:
            notes.append(f"{resolution[0]}x{resolution[1]} not offered, using {size[0]}x{size[1]}")
    at_size = sorted((m for m in modes if m.size == size), key=lambda m: m.fps)
    fast_enough = [m for m in at_size if m.fps >= rate_hz - 1e-6]
    mode = fast_enough[0] if fast_enough else at_size[-1]
    if mode.fps < rate_hz - 1e-6:
        notes.append(f"{size[0]}x{size[1]} runs at most {mode.fps} fps")
    elif mode.fps > rate_hz + 1e-6:
        notes.append(f"device at {mode.fps} fps, decimated to {rate_hz:g} Hz")
    return mode, notes


def select_motion_modes(modes: list[StreamMode]) -> list[StreamMode]:
    """One mode per motion stream present (accel, gyro, pose): the slowest, all are > 30 Hz."""
    chosen = []
    for stream in MOTION_STREAMS:
        of_stream = sorted((m for m in modes if m.stream == stream), key=lambda m: m.fps)
        if of_stream:
            chosen.append(of_stream[0])
    return chosen


def depth_to_mm(z16: np.ndarray, depth_units_m: float) -> np.ndarray:
    """uint16 depth in millimetres from raw z16 counts of ``depth_units_m`` metres each."""
    if abs(depth_units_m - 0.001) < 1e-9:  # the D4xx default: counts already are millimetres
        return np.array(z16, dtype=np.uint16, copy=True)
    mm = np.rint(z16.astype(np.float32) * np.float32(depth_units_m * 1000.0))
    return np.clip(mm, 0, 65535).astype(np.uint16)


def color_to_bgr(pixels: np.ndarray, fmt: str) -> np.ndarray:
    """uint8 (H, W, 3) BGR from a colour frame's pixels (copied: the SDK reuses its buffers)."""
    if fmt == "bgr8":
        return np.array(pixels, dtype=np.uint8, copy=True)
    if fmt == "rgb8":
        return np.ascontiguousarray(pixels[:, :, ::-1])
    if fmt == "yuyv":
        import cv2

        return cv2.cvtColor(np.ascontiguousarray(pixels).reshape(pixels.shape[0], -1, 2), cv2.COLOR_YUV2BGR_YUYV)
    raise ValueError(f"unsupported colour format {fmt}")


def imu_vector(accel: tuple[float, float, float], gyro: tuple[float, float, float]) -> np.ndarray:
    """float32 (6,): ax, ay, az (m/s^2), gx, gy, gz (rad/s), the Frame layout for imu."""
    return np.array([*accel, *gyro], dtype=np.float32)


def pose_meta(pose: Any) -> dict[str, Any]:
    """A T265 pose as plain numbers: translation (m), rotation quaternion (w, x, y, z), velocity (m/s)."""
    t, r, v = pose.translation, pose.rotation, pose.velocity
    return {
        "translation_m": (t.x, t.y, t.z),
        "rotation_wxyz": (r.w, r.x, r.y, r.z),
        "velocity_mps": (v.x, v.y, v.z),
        "tracker_confidence": int(pose.tracker_confidence),  # 0 failed, 1 low, 2 medium, 3 high
    }


def version_tuple(version: str) -> tuple[int, ...]:
    """'2.53.1.4623' -> (2, 53, 1, 4623); non-numeric parts end the tuple."""
    parts = []
    for piece in version.split("."):
        if not piece.isdigit():
            break
        parts.append(int(piece))
    return tuple(parts)
