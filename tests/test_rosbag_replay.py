"""A robot's bag as a replay source: rosbag2 (MCAP and sqlite3, written here with rosbags)
and the real ROS 1 bag in ../shared run through the same pipeline with a topic map; without
one the map is guessed and printed; ``log info`` describes foreign bags."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from respecd.cli import main
from respecd.record.rosbag_in import guess_topics, open_bag

T0 = 1_700_000_000 * 10**9
STORE = get_typestore(Stores.ROS2_HUMBLE)


def _header(ns: int, frame: str):
    t = STORE.types
    return t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame)


def _write_bag(path: Path, storage: StoragePlugin, seconds: float = 2.0) -> dict[str, list]:
    """rgb8 Image at 10 Hz, 16-bit thermal CompressedImage (PNG) at 9 Hz, PointCloud2 radar
    at 10 Hz (REP 103 frame, with a doppler field), Imu at 50 Hz."""
    t = STORE.types
    rng = np.random.default_rng(4)
    sent: dict[str, list] = {"rgb": [], "thermal": [], "radar": []}
    with Writer(path, version=8, storage_plugin=storage) as w:
        cam = w.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=STORE)
        ir = w.add_connection("/thermal/image/compressed", "sensor_msgs/msg/CompressedImage", typestore=STORE)
        radar = w.add_connection("/radar/points", "sensor_msgs/msg/PointCloud2", typestore=STORE)
        imu = w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=STORE)
        fields = [t["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1)
                  for i, n in enumerate(("x", "y", "z", "doppler"))]
        for k in range(int(seconds * 50)):
            ns = T0 + k * 20_000_000
            vec, zero = t["geometry_msgs/msg/Vector3"], np.zeros(9)
            w.write(imu, ns, STORE.serialize_cdr(t["sensor_msgs/msg/Imu"](
                header=_header(ns, "imu"), orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=zero, angular_velocity=vec(x=0.1, y=0.0, z=0.0),
                angular_velocity_covariance=zero,
                linear_acceleration=vec(x=0.0, y=0.0, z=9.8), linear_acceleration_covariance=zero),
                "sensor_msgs/msg/Imu"))
            if k % 5 == 0:
                rgb = rng.integers(0, 255, (180, 320, 3), dtype=np.uint8)
                sent["rgb"].append(rgb)
                w.write(cam, ns, STORE.serialize_cdr(t["sensor_msgs/msg/Image"](
                    header=_header(ns, "cam"), height=180, width=320, encoding="rgb8", is_bigendian=0, step=960,
                    data=rgb.reshape(-1)), "sensor_msgs/msg/Image"))
                points = rng.normal(size=(6, 4)).astype("<f4")
                sent["radar"].append(points)
                w.write(radar, ns, STORE.serialize_cdr(t["sensor_msgs/msg/PointCloud2"](
                    header=_header(ns, "radar"), height=1, width=6, fields=fields, is_bigendian=False, point_step=16,
                    row_step=96, data=points.view(np.uint8).reshape(-1), is_dense=True), "sensor_msgs/msg/PointCloud2"))
            if k % 6 == 1:
                kelvin = rng.integers(29000, 31000, (120, 160), dtype=np.uint16)
                sent["thermal"].append(kelvin)
                png = cv2.imencode(".png", kelvin)[1].reshape(-1)
                w.write(ir, ns, STORE.serialize_cdr(t["sensor_msgs/msg/CompressedImage"](
                    header=_header(ns, "ir"), format="png", data=png), "sensor_msgs/msg/CompressedImage"))
    return sent


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_bag_frames_convert_to_respecd_conventions(tmp_path: Path, storage: StoragePlugin) -> None:
    sent = _write_bag(tmp_path / "bag", storage)
    bag = open_bag(tmp_path / "bag", None)
    assert bag.topic_map == {"rgb": "/camera/color/image_raw", "thermal": "/thermal/image/compressed",
                             "radar": "/radar/points", "imu": "/imu/data"}  # guessed from types and names
    rgb = list(bag.frames("rgb"))
    assert len(rgb) == 20 and rgb[0].t == 0.0 and rgb[1].t == pytest.approx(0.1)
    np.testing.assert_array_equal(rgb[3].data, sent["rgb"][3][:, :, ::-1])  # rgb8 -> BGR
    np.testing.assert_array_equal(next(iter(bag.frames("thermal"))).data, sent["thermal"][0])  # 16-bit exact
    radar = list(bag.frames("radar"))[2].data
    p = sent["radar"][2]
    np.testing.assert_array_equal(radar[:, :4], np.stack([-p[:, 1], p[:, 0], p[:, 2], p[:, 3]], 1))  # -> TI axes
    assert not radar[:, 4].any()  # no SNR field in this cloud
    imu = next(iter(bag.frames("imu"))).data
    np.testing.assert_allclose(imu, [0.0, 0.0, 9.8, 0.1, 0.0, 0.0], rtol=1e-6)


def test_frames_parked_in_the_shared_pass_decode_after_the_bag_is_closed(tmp_path: Path) -> None:
    """Replay drivers share one pass over the bag; the sensor that reads to the end closes the
    reader while another sensor's messages still wait in their queue to be converted."""
    _write_bag(tmp_path / "bag", StoragePlugin.MCAP)
    bag = open_bag(tmp_path / "bag", None)
    demux = bag.shared_demux()
    assert len(list(bag.frames("imu", demux))) == 100  # the whole bag read: the reader closed
    radar = list(bag.frames("radar", demux))
    assert len(radar) == 20 and radar[0].data.shape == (6, 5)


@pytest.mark.slow
def test_replay_of_a_rosbag2_with_a_topic_map_runs_the_pipeline(tmp_path: Path) -> None:
    _write_bag(tmp_path / "bag", StoragePlugin.MCAP)
    report = tmp_path / "r.json"
    assert main(["--replay", str(tmp_path / "bag"), "--topics", "rgb=/camera/color/image_raw,imu=/imu/data,"
                 "radar=/radar/points", "--speed", "max", "--policy", "static", "--report", str(report),
                 "--log-level", "warning", "--log-format", "json"]) == 0
    entry = json.loads(report.read_text())["policies"]["static"]
    assert entry["compute"]["frames"]["rgb"] >= 18 and entry["compute"]["frames"]["radar"] >= 18
    assert entry["timeline"]  # the detector ran on the bag's frames


def test_topic_map_errors_name_the_topic(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    _write_bag(tmp_path / "bag", StoragePlugin.MCAP, seconds=0.2)
    assert main(["--replay", str(tmp_path / "bag"), "--topics", "rgb=/nope", "--speed", "max"]) == 2
    assert "--topics rgb=/nope: no such topic" in capsys.readouterr().err
    assert main(["--replay", str(tmp_path / "bag"), "--topics", "imu=/radar/points", "--speed", "max"]) == 2
    assert "sensor_msgs/msg/PointCloud2 cannot be a imu sensor" in capsys.readouterr().err
    assert main(["--replay", str(tmp_path / "bag"), "--topics", "lidar=/radar/points"]) == 2
    assert "expected one of rgb, thermal" in capsys.readouterr().err


@pytest.mark.slow
def test_the_real_ros1_bag_replays_with_the_guess_printed(shared_data: Path, capsys: pytest.CaptureFixture) -> None:
    bag = shared_data / "rosbags" / "kapture_t265_ros1" / "trimmed_locoffice.bag"
    assert main(["--replay", str(bag), "--speed", "max", "--log-level", "warning", "--log-format", "json"]) == 0
    err = capsys.readouterr().err
    assert "guessed from message types: --topics imu=/camera/accel/sample,rgb=/camera/fisheye1/image_raw" in err
    frames = list(open_bag(bag, None).frames("rgb"))
    assert len(frames) == 3 and frames[0].data.shape == (800, 848, 3)  # mono8 fisheye, replicated to BGR


def test_log_info_describes_foreign_bags(shared_data: Path, capsys: pytest.CaptureFixture) -> None:
    fixtures = shared_data / "rosbags" / "rosbag2_fixtures" / "rosbag2_py" / "test" / "resources"
    for storage in ("mcap", "sqlite3"):
        assert main(["log", "info", str(fixtures / storage / "talker"), "--json"]) == 0
        info = json.loads(capsys.readouterr().out)
        assert info["kind"] == "rosbag2" and info["messages"] == 20 and info["guessed_topics"] == {}
        assert {t["topic"]: t["messages"] for t in info["topics"]}["/topic"] == 10
    assert main(["--replay", str(fixtures / "mcap" / "talker"), "--speed", "max"]) == 2
    assert "no sensor_msgs Image/CompressedImage/PointCloud2/Imu topic" in capsys.readouterr().err
    assert main(["log", "info", str(fixtures / "mcap" / "wbag")]) == 0  # five split files
    assert "6074 in 8 topics" in capsys.readouterr().out


def test_guess_prefers_a_colour_camera_and_reads_depth_by_name() -> None:
    from respecd.record.reader import ChannelInfo

    channels = {t: ChannelInfo(t, kind, {}) for t, kind in [
        ("/cam/left/image_raw", "sensor_msgs/msg/Image"), ("/camera/color/image_raw", "sensor_msgs/msg/Image"),
        ("/camera/depth/image_rect_raw", "sensor_msgs/msg/Image"), ("/odom", "nav_msgs/msg/Odometry")]}
    assert guess_topics(channels) == {"rgb": "/camera/color/image_raw", "depth": "/camera/depth/image_rect_raw"}


@pytest.mark.parametrize(("content", "offset", "found"), [
    (np.random.default_rng(5).bytes(20_000), 0, "unrecognised binary data"),
    (b"#ROSBAG V1.2\n" + bytes(100), 9, "unrecognised binary data"),
    (b"hello\n", 0, "text"),
])
def test_a_bag_with_a_wrong_header_says_what_a_bag_starts_with(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                              content: bytes, offset: int, found: str) -> None:
    path = tmp_path / "garbage.bag"
    path.write_bytes(content)
    for argv in (["log", "info", str(path)], ["--replay", str(path), "--speed", "max"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{path}: not a ROS 1 bag: byte {offset} is " in err and "utf-8" not in err
        assert "starts with b'#ROSBAG V2.0\\n'" in err and "rosbag2 is a folder with metadata.yaml" in err


def test_a_cut_ros1_bag_names_where_its_index_should_be(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from rosbags.rosbag1 import Writer as Writer1

    whole = tmp_path / "whole.bag"
    with Writer1(whole) as w:
        conn = w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=STORE)
        msg = STORE.types["sensor_msgs/msg/Imu"](
            header=_header(0, "imu"), orientation=STORE.types["geometry_msgs/msg/Quaternion"](x=0, y=0, z=0, w=1),
            orientation_covariance=np.zeros(9),
            angular_velocity=STORE.types["geometry_msgs/msg/Vector3"](x=0, y=0, z=0),
            angular_velocity_covariance=np.zeros(9),
            linear_acceleration=STORE.types["geometry_msgs/msg/Vector3"](x=0, y=0, z=9.8),
            linear_acceleration_covariance=np.zeros(9))
        for i in range(50):
            w.write(conn, i * 10_000_000, STORE.serialize_ros1(msg, "sensor_msgs/msg/Imu"))
    cut = tmp_path / "cut.bag"
    cut.write_bytes(whole.read_bytes()[:3000])
    assert main(["log", "info", str(cut)]) == 2
    err = capsys.readouterr().err
    assert f"{cut}: ROS 1 bag is cut: its index is at byte " in err and "past the end of the file (3000 bytes)" in err


def test_rosbag2_metadata_of_the_wrong_shape_names_file_line_and_field(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    bag = tmp_path / "r2w"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: 5\n")
    assert main(["log", "info", str(bag)]) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"respecd: {bag / 'metadata.yaml'}:1: rosbag2_bagfile_information: expected a mapping, "
                           "got 5 (an integer)")
    _write_bag(tmp_path / "good", StoragePlugin.MCAP, seconds=0.5)
    meta = yaml.safe_load((tmp_path / "good" / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["message_count"] = []
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    assert main(["log", "info", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "metadata.yaml:" in err and "rosbag2_bagfile_information.message_count: expected an integer, got a list" \
        in err and "subscriptable" not in err
