"""``respecd log export LOG --to rosbag2 OUT``: the bag reads back with rosbags, topic by
topic with the log's message counts, in standard ROS 2 messages with the exact payloads."""

from __future__ import annotations

import asyncio
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from respecd.cli import main
from respecd.clock import ManualClock
from respecd.messages import Bundle, Detection, Frame, Health, Percept, SyncStats
from respecd.record.config import RecordingConfig
from respecd.record.reader import open_log
from respecd.record.recorder import Recorder
from respecd.record.ros_types import typestore

INTRINSICS = {"fx": 457.0, "fy": 457.0, "cx": 320.0, "cy": 180.0, "width": 640, "height": 360}
PROFILE = {"name": "bag-rig", "sensors": [
    {"name": "cam", "modality": "rgb", "calibration": {"intrinsics": INTRINSICS}},
    {"name": "radar", "modality": "radar"}, {"name": "ir", "modality": "thermal"}, {"name": "imu", "modality": "imu"}]}
LEGACY = Path(__file__).parent / "data" / "legacy-v1.mcap"


async def _record(path: Path, n: int = 30) -> list[dict[str, Frame]]:
    recorder = Recorder(RecordingConfig(enabled=True, path=str(path)), PROFILE, clock := ManualClock())
    recorder.start()
    rng, sent = np.random.default_rng(3), []
    for i in range(n):
        clock.set(i / 30)
        rgb = np.full((360, 640, 3), 90, np.uint8)
        frames = {"cam": Frame("rgb", i / 30, i, rgb),
                  "ir": Frame("thermal", i / 30, i, rng.integers(29000, 31000, (120, 160), dtype=np.uint16)),
                  "radar": Frame("radar", i / 30, i, rng.normal(size=(4, 5)).astype(np.float32)),
                  "imu": Frame("imu", i / 30, i, np.arange(6, dtype=np.float32))}
        for name, frame in frames.items():
            recorder.on_frame(name, frame)
        if i % 10 == 0:
            bundle = Bundle(i / 30, {"rgb": frames["cam"]}, SyncStats(30.0, 0.1, 0.0, Health.GOOD), i)
            recorder.on_percept(Percept(i / 30, (Detection((10, 20, 110, 220), 0.75),), 0.7, None, 0.02, bundle))
        sent.append(frames)
        await asyncio.sleep(0.002)
    await recorder.close()
    return sent


async def test_exported_bag_has_the_logs_topics_counts_and_payloads(tmp_path: Path) -> None:
    sent = await _record(tmp_path / "s.mcap")
    bag = tmp_path / "bag"
    assert main(["log", "export", str(tmp_path / "s.mcap"), "--to", "rosbag2", str(bag)]) == 0
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == "mcap" and meta["version"] == 8
    log = open_log(tmp_path / "s.mcap")
    store = typestore()
    with AnyReader([bag], default_typestore=store) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        types = {c.topic: c.msgtype for c in reader.connections}
        expected = {topic: c.count for topic, c in log.channels.items() if topic != "/tf"}
        assert log.channels["/tf"].count >= 1 and counts == {**expected, "/tf_static": 1}
        assert types["/sensors/cam"] == "sensor_msgs/msg/CompressedImage"
        assert types["/sensors/ir"] == "sensor_msgs/msg/CompressedImage"  # lossless 16-bit PNG
        assert types["/sensors/ir/colormap"] == "sensor_msgs/msg/CompressedImage"
        assert types["/sensors/radar"] == "sensor_msgs/msg/PointCloud2"
        assert types["/sensors/imu"] == "sensor_msgs/msg/Imu"
        assert types["/sensors/cam/calibration"] == "sensor_msgs/msg/CameraInfo"
        assert types["/tf_static"] == "tf2_msgs/msg/TFMessage"
        assert types["/respecd/detections"] == "vision_msgs/msg/Detection2DArray"
        assert types["/respecd/percept"] == "std_msgs/msg/String"
        seen: dict[str, list] = {}
        for connection, _, raw in reader.messages():
            seen.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    ir = seen["/sensors/ir"][5]
    assert ir.format == "png" and ir.header.frame_id == "ir"
    np.testing.assert_array_equal(cv2.imdecode(ir.data, cv2.IMREAD_UNCHANGED), sent[5]["ir"].data)
    cloud = seen["/sensors/radar"][7]
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "v", "snr"] and cloud.point_step == 20
    np.testing.assert_array_equal(cloud.data.view("<f4").reshape(-1, 5), sent[7]["radar"].data)
    image = cv2.imdecode(seen["/sensors/cam"][0].data, cv2.IMREAD_COLOR)
    assert image.shape == (360, 640, 3)
    detections = seen["/respecd/detections"][1]
    assert detections.header.frame_id == "cam"  # the camera whose pixels the boxes are in
    detection = detections.detections[0]
    assert detection.results[0].hypothesis.class_id == "person" and detection.results[0].hypothesis.score == 0.75
    assert (detection.bbox.center.position.x, detection.bbox.size_x, detection.bbox.size_y) == (60.0, 100.0, 200.0)
    assert seen["/sensors/imu"][0].linear_acceleration.z == 2.0
    assert list(seen["/sensors/cam/calibration"][0].k)[:3] == [457.0, 0.0, 320.0]
    frames = {t.child_frame_id: t.header.frame_id for t in seen["/tf_static"][0].transforms}
    assert frames == {"cam": "base_link", "radar": "cam", "ir": "cam", "imu": "cam"}  # every sensor, the IMU too


async def test_the_bag_follows_ros_2_conventions_and_is_compressed(tmp_path: Path) -> None:
    await _record(tmp_path / "s.mcap")
    bag = tmp_path / "bag"
    assert main(["log", "export", str(tmp_path / "s.mcap"), "--to", "rosbag2", str(bag)]) == 0
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["ros_distro"] == "humble"  # whose message definitions the bag holds
    topics = {t["topic_metadata"]["name"]: t["topic_metadata"] for t in meta["topics_with_message_count"]}
    latched = yaml.safe_load(topics["/tf_static"]["offered_qos_profiles"])
    assert [(q["durability"], q["reliability"], q["depth"]) for q in latched] == [(1, 1, 1)]  # transient local
    assert "/tf" not in topics
    storage = next(bag.glob("*.mcap"))
    with open(storage, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and {c.compression for c in summary.chunk_indexes} == {"zstd"}
        embedded = {m.name: m.metadata for m in reader.iter_metadata()}["rosbag2"]
    assert yaml.safe_load(embedded["serialized_metadata"])["ros_distro"] == "humble"  # the .mcap alone says so
    assert sum(p.stat().st_size for p in bag.iterdir()) <= (tmp_path / "s.mcap").stat().st_size


def test_export_refuses_an_existing_dir_and_first_format_logs(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["log", "export", str(LEGACY), "--to", "rosbag2", str(tmp_path)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["log", "export", str(LEGACY), "--to", "rosbag2", str(tmp_path / "bag")]) == 2
    assert "format 1" in capsys.readouterr().err


async def test_the_bags_mcap_copied_alone_is_still_a_bag(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """What ``ros2 bag record -s mcap`` leaves, often copied without metadata.yaml, reads as a bag."""
    await _record(tmp_path / "s.mcap")
    assert main(["log", "export", str(tmp_path / "s.mcap"), "--to", "rosbag2", str(tmp_path / "bag")]) == 0
    alone = tmp_path / "alone" / "ros2.mcap"
    alone.parent.mkdir()
    shutil.copy(next((tmp_path / "bag").glob("*.mcap")), alone)
    capsys.readouterr()
    assert main(["log", "info", str(alone)]) == 0
    out = capsys.readouterr().out
    assert "rosbag2" in out and "/tf_static" in out and "format 1" not in out
    assert main(["log", "info", str(tmp_path / "s.mcap")]) == 0  # respecd's own log is still one
    assert "format 2" in capsys.readouterr().out
