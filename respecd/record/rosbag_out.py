"""``respecd log export LOG --to rosbag2 OUT``: a recorded session as a ROS 2 bag.

rosbag2 layout (``metadata.yaml`` + one MCAP storage file, cdr, zstd-compressed chunks) written
by ``rosbags``, which follows what rosbag2 itself writes (metadata version 8); ``ros_distro``
names the distribution whose message definitions are written (Humble). Every channel of the
log becomes one topic with the same name and the same message count, in standard messages,
except the transforms: the profile's sensor frames are fixed, so they go once on
``/tf_static`` with the transient-local QoS ROS 2 latches them with (REP 105), not
periodically on ``/tf`` as the log repeats them for late-joining viewers:

* ``foxglove.CompressedImage`` -> ``sensor_msgs/msg/CompressedImage`` (the JPEG/PNG bytes, not re-encoded)
* ``foxglove.RawImage`` -> ``sensor_msgs/msg/Image`` (exact pixels)
* ``foxglove.PointCloud`` -> ``sensor_msgs/msg/PointCloud2`` (float32 x, y, z, v, snr)
* ``respecd.Imu`` -> ``sensor_msgs/msg/Imu`` (orientation_covariance[0] = -1: no orientation)
* ``foxglove.CameraCalibration`` -> ``sensor_msgs/msg/CameraInfo``
* ``foxglove.FrameTransforms`` -> ``tf2_msgs/msg/TFMessage`` (the first, once, on ``/tf_static``)
* ``foxglove.ImageAnnotations`` (detections) -> ``vision_msgs/msg/Detection2DArray``: box
  from the drawn corners, class and score from the "person 0.87" text, ``frame_id`` the
  camera the boxes are in
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
from respecd.record.topics import TOPIC_DETECTIONS

ROSBAG2_VERSION = 8  # metadata.yaml version rosbag2 writes since Iron (rosbags writes 8 or 9)
ROS_DISTRO = "humble"  # the message definitions written are ros_types.typestore()'s: Humble's
FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32
TF_STATIC = "/tf_static"

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
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin

    if out.exists():
        raise InputError(f"{out}: already exists (rosbag2 output must be a new directory)")
    if int(session.metadata.get("respecd.session", {}).get("format", "1")) < 2:
        raise InputError(f"{session.path}: written by respecd 0.1.0 (format 1, JSON/base64); export reads format 2 "
                         "logs. Replay it with --record to get one: respecd --replay LOG --speed max --record NEW.mcap")
    store = typestore()
    converter = _Converter(store, session)
    counts: dict[str, int] = {}
    writer = _writer_class()(out, version=ROSBAG2_VERSION, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)  # zstd chunks, as ros2 bag -s mcap can
    with writer:
        connections: dict[str, Any] = {}
        for topic, schema, log_ns, payload in session.messages():
            if schema.name == "foxglove.FrameTransforms":
                if TF_STATIC in connections:
                    continue  # fixed frames: once
                topic = TF_STATIC
            msgtype = MSGTYPES.get(schema.name, STRING)
            connection = connections.get(topic)
            if connection is None:
                qos = [_latched()] if topic == TF_STATIC else []
                connection = connections[topic] = writer.add_connection(topic, msgtype, typestore=store,
                                                                        offered_qos_profiles=qos)
            message = converter.convert(schema, payload)
            writer.write(connection, log_ns, store.serialize_cdr(message, msgtype))
            counts[topic] = counts.get(topic, 0) + 1
    _name_distro(out / "metadata.yaml")
    return counts


def _latched() -> Any:
    """The QoS rosbag2 records ``/tf_static`` with: reliable, transient local, keep last 1."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    never = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)  # rmw's "infinite" duration as rosbag2 writes it
    return Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL, deadline=never, lifespan=never,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=never,
               avoid_ros_namespace_conventions=False)


def _with_distro(metadata_yaml: str) -> str:
    """rosbag2 metadata (YAML text) naming ROS_DISTRO where rosbags writes its own name."""
    import yaml

    data = yaml.safe_load(metadata_yaml)
    info = data.get("rosbag2_bagfile_information", data)
    info["ros_distro"] = ROS_DISTRO
    return yaml.safe_dump(data, sort_keys=False)


def _name_distro(path: Path) -> None:
    path.write_text(_with_distro(path.read_text()))


def _writer_class() -> Any:
    """rosbags' rosbag2 writer whose MCAP storage names the distribution in its embedded
    metadata too (``ros2 bag info`` on a lone .mcap reads that copy)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.storage_mcap import McapWriter

    class _McapStorage(McapWriter):
        def close(self, version: int, metadata: str) -> None:
            super().close(version, _with_distro(metadata).strip())

    class _Writer(Writer):
        STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _McapStorage}

    return _Writer


class _Converter:
    """Foxglove / respecd messages -> rosbags message objects."""

    def __init__(self, store: Any, session: SessionLog) -> None:
        self.t = store.types
        # the camera whose pixels detection boxes are in: what its images' frame_id is
        drawn = session.channels.get(TOPIC_DETECTIONS)
        image_topic = drawn.metadata.get("image_topic", "") if drawn is not None else ""
        rgb = next((name for name, modality in session.sensors.items() if modality == "rgb"), "")
        self.image_frame = image_topic.removeprefix("/sensors/") or rgb
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
        header = self._header(m.timestamp, self.image_frame)
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
