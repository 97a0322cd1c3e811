"""``respecd log export LOG --to rosbag2 OUT``: a recorded session as a ROS 2 bag.

rosbag2 layout (``metadata.yaml`` + one MCAP storage file, cdr) written by ``rosbags``,
which follows what rosbag2 itself writes (metadata version 8). Every channel of the log
becomes one topic with the same name and the same message count, in standard messages:

* ``foxglove.CompressedImage`` -> ``sensor_msgs/msg/CompressedImage`` (the JPEG/PNG bytes, not re-encoded)
* ``foxglove.RawImage`` -> ``sensor_msgs/msg/Image`` (exact pixels)
* ``foxglove.PointCloud`` -> ``sensor_msgs/msg/PointCloud2`` (float32 x, y, z, v, snr)
* ``respecd.Imu`` -> ``sensor_msgs/msg/Imu`` (orientation_covariance[0] = -1: no orientation)
* ``foxglove.CameraCalibration`` -> ``sensor_msgs/msg/CameraInfo``
* ``foxglove.FrameTransforms`` -> ``tf2_msgs/msg/TFMessage``
* ``foxglove.ImageAnnotations`` (detections) -> ``vision_msgs/msg/Detection2DArray``: box
  from the drawn corners, class and score from the "person 0.87" text
* respecd's own JSON channels (percepts, decisions, configs, sync, frame meta, raw radar
  bytes) -> ``std_msgs/msg/String`` holding the same JSON
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from respecd.errors import InputError
from respecd.record import codec
from respecd.record.reader import SessionLog
from respecd.record.ros_types import typestore

ROSBAG2_VERSION = 8  # metadata.yaml version rosbag2 writes since Iron (rosbags writes 8 or 9)
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32

MSGTYPES = {
    "foxglove.CompressedImage": "sensor_msgs/msg/CompressedImage",
    "foxglove.RawImage": "sensor_msgs/msg/Image",
    "foxglove.PointCloud": "sensor_msgs/msg/PointCloud2",
    "respecd.Imu": "sensor_msgs/msg/Imu",
    "foxglove.CameraCalibration": "sensor_msgs/msg/CameraInfo",
    "foxglove.FrameTransforms": "tf2_msgs/msg/TFMessage",
    "foxglove.ImageAnnotations": "vision_msgs/msg/Detection2DArray",
}
STRING = "std_msgs/msg/String"


def export_rosbag2(session: SessionLog, out: Path) -> dict[str, int]:
    """Write ``session`` to the bag directory ``out`` (must not exist); messages per topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    if out.exists():
        raise InputError(f"{out}: already exists (rosbag2 output must be a new directory)")
    if int(session.metadata.get("respecd.session", {}).get("format", "1")) < 2:
        raise InputError(f"{session.path}: written by respecd 0.1.0 (format 1, JSON/base64); export reads format 2 "
                         "logs. Replay it with --record to get one: respecd --replay LOG --speed max --record NEW.mcap")
    store = typestore()
    converter = _Converter(store)
    counts: dict[str, int] = {}
    with Writer(out, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:  # type: ignore[arg-type]
        connections: dict[str, Any] = {}
        for topic, schema, log_ns, payload in session.messages():
            msgtype = MSGTYPES.get(schema.name, STRING)
            connection = connections.get(topic)
            if connection is None:
                connection = connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            message = converter.convert(schema, payload)
            writer.write(connection, log_ns, store.serialize_cdr(message, msgtype))
            counts[topic] = counts.get(topic, 0) + 1
    return counts


class _Converter:
    """Foxglove / respecd messages -> rosbags message objects."""

    def __init__(self, store: Any) -> None:
        self.t = store.types
        self._by_schema: dict[str, Callable[[Any], Any]] = {
            "foxglove.CompressedImage": self._compressed,
            "foxglove.RawImage": self._raw,
            "foxglove.PointCloud": self._points,
            "respecd.Imu": self._imu,
            "foxglove.CameraCalibration": self._camera_info,
            "foxglove.FrameTransforms": self._tf,
            "foxglove.ImageAnnotations": self._detections,
        }

    def convert(self, schema: codec.LoggedSchema, payload: bytes) -> Any:
        convert = self._by_schema.get(schema.name)
        if convert is None:
            return self.t[STRING](data=payload.decode("utf-8"))
        return convert(codec.decode_message(schema, payload))

    def _header(self, stamp: Any, frame_id: str) -> Any:
        time = self.t["builtin_interfaces/msg/Time"]
        if isinstance(stamp, dict):  # respecd.Imu: JSON {"sec", "nsec"}
            return self.t["std_msgs/msg/Header"](stamp=time(sec=stamp["sec"], nanosec=stamp["nsec"]), frame_id=frame_id)
        return self.t["std_msgs/msg/Header"](stamp=time(sec=stamp.seconds, nanosec=stamp.nanos), frame_id=frame_id)

    def _compressed(self, m: Any) -> Any:
        return self.t["sensor_msgs/msg/CompressedImage"](
            header=self._header(m.timestamp, m.frame_id), format=m.format, data=np.frombuffer(m.data, np.uint8))

    def _raw(self, m: Any) -> Any:
        return self.t["sensor_msgs/msg/Image"](
            header=self._header(m.timestamp, m.frame_id), height=m.height, width=m.width, encoding=m.encoding,
            is_bigendian=0, step=m.step, data=np.frombuffer(m.data, np.uint8))

    def _points(self, m: Any) -> Any:
        field = self.t["sensor_msgs/msg/PointField"]
        n = len(m.data) // m.point_stride if m.point_stride else 0
        return self.t["sensor_msgs/msg/PointCloud2"](
            header=self._header(m.timestamp, m.frame_id), height=1, width=n,
            fields=[field(name=f.name, offset=f.offset, datatype=FLOAT32, count=1) for f in m.fields],
            is_bigendian=False, point_step=m.point_stride, row_step=m.point_stride * n,
            data=np.frombuffer(m.data, np.uint8), is_dense=True)

    def _imu(self, m: dict[str, Any]) -> Any:
        vec, quat = self.t["geometry_msgs/msg/Vector3"], self.t["geometry_msgs/msg/Quaternion"]
        unknown = np.zeros(9)
        unknown[0] = -1.0  # REP 145: orientation not estimated
        a, g = m["linear_acceleration"], m["angular_velocity"]
        return self.t["sensor_msgs/msg/Imu"](
            header=self._header(m["timestamp"], m.get("frame_id", "")),
            orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=unknown,
            angular_velocity=vec(x=g["x"], y=g["y"], z=g["z"]), angular_velocity_covariance=np.zeros(9),
            linear_acceleration=vec(x=a["x"], y=a["y"], z=a["z"]), linear_acceleration_covariance=np.zeros(9))

    def _camera_info(self, m: Any) -> Any:
        roi = self.t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t["sensor_msgs/msg/CameraInfo"](
            header=self._header(m.timestamp, m.frame_id), height=m.height, width=m.width,
            distortion_model=m.distortion_model, d=np.asarray(m.D, np.float64), k=np.asarray(m.K, np.float64),
            r=np.asarray(m.R, np.float64), p=np.asarray(m.P, np.float64), binning_x=0, binning_y=0, roi=roi)

    def _tf(self, m: Any) -> Any:
        t = self.t
        stamped = [
            t["geometry_msgs/msg/TransformStamped"](
                header=self._header(tr.timestamp, tr.parent_frame_id), child_frame_id=tr.child_frame_id,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=tr.translation.x, y=tr.translation.y,
                                                               z=tr.translation.z),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=tr.rotation.x, y=tr.rotation.y, z=tr.rotation.z,
                                                               w=tr.rotation.w)))
            for tr in m.transforms
        ]
        return t["tf2_msgs/msg/TFMessage"](transforms=stamped)

    def _detections(self, m: Any) -> Any:
        t = self.t
        header = self._header(m.timestamp, "")
        detections = []
        for box, text in zip(m.points, m.texts, strict=False):
            xs, ys = [p.x for p in box.points], [p.y for p in box.points]
            label, _, score = text.text.rpartition(" ")
            hypothesis = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](class_id=label, score=float(score)),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=_identity_pose(t), covariance=np.zeros(36)))
            center = t["vision_msgs/msg/Pose2D"](
                position=t["vision_msgs/msg/Point2D"](x=(min(xs) + max(xs)) / 2, y=(min(ys) + max(ys)) / 2), theta=0.0)
            detections.append(t["vision_msgs/msg/Detection2D"](
                header=header, results=[hypothesis], id="",
                bbox=t["vision_msgs/msg/BoundingBox2D"](center=center, size_x=max(xs) - min(xs),
                                                        size_y=max(ys) - min(ys))))
        return t["vision_msgs/msg/Detection2DArray"](header=header, detections=detections)


def _identity_pose(t: Any) -> Any:
    return t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                       orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
