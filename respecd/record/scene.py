"""Where each sensor is, for Foxglove's 3D and Image panels: one ``foxglove.CameraCalibration``
per calibrated camera (intrinsics scaled to the frame size actually delivered) and
``foxglove.FrameTransforms`` from the profile's extrinsics.

Frames: ``base_link`` (x forward, y left, z up, ROS REP 103) holds the RGB camera's optical
frame (x right, y down, z forward), the profile's reference; every other sensor is placed in
it by its extrinsics (``p_rgb = R p_sensor + t``, R from roll/pitch/yaw as perception's
alignment uses it). A radar's points are in TI's frame (x right, y boresight, z up), so its
transform also turns those axes into the camera convention: the points land in 3D in front
of the camera. Both are re-sent every ``PERIOD_S`` so a live viewer that connects late, or a
log segment read on its own, has them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import foxglove.messages as fox
import numpy as np

from respecd.record.codec import Message, timestamp
from respecd.record.topics import TOPIC_TF, calibration_topic
from respecd.sensors import rotation_rpy

BASE_FRAME = "base_link"
PERIOD_S = 1.0
# camera optical frame in base_link: z forward -> x, x right -> -y, y down -> -z
OPTICAL_IN_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
TI_TO_CAMERA = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # (x, y, z)_ti -> camera axes


def quaternion(rot: np.ndarray) -> fox.Quaternion:
    """Unit quaternion of a rotation matrix (Shepperd's method, numerically safe)."""
    m = rot
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    return fox.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


class Scene:
    """The profile's calibration, turned into Foxglove messages on demand."""

    def __init__(self, profile: Mapping[str, Any]) -> None:
        """``profile``: the profile's JSON form (``writer.profile_document``)."""
        sensors = [dict(s) for s in profile.get("sensors", [])]
        rgb = next((s for s in sensors if s.get("modality") == "rgb"), None)
        self.reference = str(rgb["name"]) if rgb else None
        self.intrinsics = {
            str(s["name"]): s["calibration"]["intrinsics"]
            for s in sensors
            if (s.get("calibration") or {}).get("intrinsics") and s.get("modality") in ("rgb", "thermal", "depth")
        }
        self.poses = {str(s["name"]): self._pose(s) for s in sensors}

    def _pose(self, sensor: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of the sensor's data frame in its parent frame."""
        extrinsics = (sensor.get("calibration") or {}).get("extrinsics") or {}
        rot = rotation_rpy(*extrinsics.get("rotation_rpy_deg", (0.0, 0.0, 0.0)))
        trans = np.asarray(extrinsics.get("translation_m", (0.0, 0.0, 0.0)), dtype=np.float64)
        if sensor.get("modality") == "radar":
            rot = rot @ TI_TO_CAMERA
        if sensor["name"] == self.reference or self.reference is None:
            return OPTICAL_IN_BASE @ rot, OPTICAL_IN_BASE @ trans  # in base_link
        return rot, trans  # in the reference camera's frame

    def transforms(self, log_ns: int) -> Message:
        ts = timestamp(log_ns)
        items = []
        for name, (rot, trans) in self.poses.items():
            parent = BASE_FRAME if name == self.reference or self.reference is None else self.reference
            items.append(fox.FrameTransform(
                timestamp=ts, parent_frame_id=parent, child_frame_id=name,
                translation=fox.Vector3(x=float(trans[0]), y=float(trans[1]), z=float(trans[2])),
                rotation=quaternion(rot)))
        return Message(TOPIC_TF, "foxglove.FrameTransforms", fox.FrameTransforms(transforms=items).encode(), {})

    def calibration(self, sensor: str, width: int, height: int, log_ns: int) -> Message | None:
        """Pinhole model of ``sensor`` at ``width`` x ``height`` pixels (None: not calibrated)."""
        intr = self.intrinsics.get(sensor)
        if intr is None:
            return None
        sx, sy = width / intr["width"], height / intr["height"]
        fx, fy, cx, cy = intr["fx"] * sx, intr["fy"] * sy, intr["cx"] * sx, intr["cy"] * sy
        msg = fox.CameraCalibration(
            timestamp=timestamp(log_ns), frame_id=sensor, width=width, height=height, distortion_model="plumb_bob",
            D=[0.0] * 5, K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0], R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        return Message(calibration_topic(sensor), "foxglove.CameraCalibration", msg.encode(), {"sensor": sensor})
