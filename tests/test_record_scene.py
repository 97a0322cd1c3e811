"""Calibration and frame transforms from the profile: a radar return straight ahead of the
radar lands in front of the camera in Foxglove's 3D view; K follows the delivered size."""

from __future__ import annotations

import foxglove.messages as fox
import numpy as np
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory

from respecd.record.scene import BASE_FRAME, Scene

INTRINSICS = {"fx": 914.0, "fy": 914.0, "cx": 640.0, "cy": 360.0, "width": 1280, "height": 720}
PROFILE = {
    "name": "rig",
    "sensors": [
        {"name": "cam", "modality": "rgb", "calibration": {"intrinsics": INTRINSICS}},
        {"name": "radar", "modality": "radar",
         "calibration": {"extrinsics": {"rotation_rpy_deg": [0.0, 0.0, 0.0], "translation_m": [0.0, 0.12, 0.0]}}},
        {"name": "ir", "modality": "thermal",
         "calibration": {"extrinsics": {"rotation_rpy_deg": [0.0, 0.0, 90.0], "translation_m": [0.05, 0.0, 0.0]}}},
        {"name": "imu", "modality": "imu"},
    ],
}


def _decode(name: str, data: bytes):
    schema = getattr(fox, name).get_schema()
    record = Schema(id=1, name=schema.name, encoding=schema.encoding, data=bytes(schema.data))
    return DecoderFactory().decoder_for("protobuf", record)(data)


def _matrix(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _to_base(transforms, frame: str, point: np.ndarray) -> np.ndarray:
    by_child = {t.child_frame_id: t for t in transforms}
    while frame != BASE_FRAME:
        t = by_child[frame]
        point = _matrix(t.rotation) @ point + np.array([t.translation.x, t.translation.y, t.translation.z])
        frame = t.parent_frame_id
    return point


def test_a_radar_return_on_boresight_lands_in_front_of_the_camera() -> None:
    message = Scene(PROFILE).transforms(1_000_000_000)
    tf = _decode("FrameTransforms", message.payload).transforms
    assert {t.child_frame_id for t in tf} == {"cam", "radar", "ir", "imu"}
    ahead = _to_base(tf, "radar", np.array([0.0, 5.0, 0.0]))  # TI frame: y is the boresight
    np.testing.assert_allclose(ahead, [5.0, 0.0, -0.12], atol=1e-9)  # base_link: 5 m ahead, 12 cm lower
    camera_axis = _to_base(tf, "cam", np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(camera_axis, [1.0, 0.0, 0.0], atol=1e-9)  # the optical axis looks forward
    turned = _to_base(tf, "ir", np.array([0.0, 0.0, 1.0]))  # yaw 90: the thermal camera looks right
    np.testing.assert_allclose(turned, [0.0, -1.05, 0.0], atol=1e-9)  # ... from 5 cm right of the camera


def test_the_imu_at_rest_reads_gravity_upward_in_base_link() -> None:
    """The IMU sits in the camera's frame (the D435i's, y down): its resting reading, the
    reaction to gravity, must point up (+z) in base_link as REP 145 expects."""
    tf = _decode("FrameTransforms", Scene(PROFILE).transforms(0).payload).transforms
    by_child = {t.child_frame_id: t for t in tf}
    assert by_child["imu"].parent_frame_id == "cam"
    rotation = _matrix(by_child["imu"].rotation)
    up = _to_base(tf, "cam", rotation @ np.array([0.0, -9.81, 0.0])) - _to_base(tf, "cam", np.zeros(3))
    np.testing.assert_allclose(up, [0.0, 0.0, 9.81], atol=1e-9)


def test_camera_calibration_is_scaled_to_the_frame_size() -> None:
    scene = Scene(PROFILE)
    assert scene.calibration("radar", 10, 10, 0) is None
    message = scene.calibration("cam", 640, 360, 5)
    assert message is not None and message.topic == "/sensors/cam/calibration"
    cal = _decode("CameraCalibration", message.payload)
    assert (cal.width, cal.height, cal.frame_id) == (640, 360, "cam")
    assert list(cal.K) == [457.0, 0.0, 320.0, 0.0, 457.0, 180.0, 0.0, 0.0, 1.0]
    assert list(cal.P)[:3] == [457.0, 0.0, 320.0]
