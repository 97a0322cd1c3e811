"""Real camera recordings for the replay tests, built from the LLVIP visible photos in ../shared:
a ROS 2 camera bag written by rosbags (what a robot the project never saw would bring) and a
respecd log written by the recorder under a profile of the test's choosing."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
LLVIP = SHARED / "llvip_pairs" / "visible"
T0_NS = 1_700_000_000 * 10**9
STORE = get_typestore(Stores.ROS2_HUMBLE)
TOPIC = "/camera/color/image_raw/compressed"


def photos(n: int, size: tuple[int, int] = (640, 512)) -> list[np.ndarray]:
    """The first ``n`` LLVIP visible photos (BGR, people in street scenes), resized to ``size``."""
    paths = sorted(LLVIP.glob("*.jpg"))[:n]
    return [cv2.resize(cv2.imread(str(p)), size, interpolation=cv2.INTER_AREA) for p in paths]


def write_camera_bag(path: Path, images: list[np.ndarray], hz: float) -> Path:
    """A rosbag2 (MCAP storage, with metadata.yaml) of JPEG ``sensor_msgs/CompressedImage`` at ``hz``."""
    t = STORE.types
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        cam = w.add_connection(TOPIC, "sensor_msgs/msg/CompressedImage", typestore=STORE)
        for i, image in enumerate(images):
            ns = T0_NS + round(i * 1e9 / hz)
            stamp = t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
            jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].reshape(-1)
            msg = t["sensor_msgs/msg/CompressedImage"](header=t["std_msgs/msg/Header"](stamp=stamp, frame_id="camera"),
                                                       format="jpeg", data=jpeg)
            w.write(cam, ns, STORE.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))
    return path


def write_log(path: Path, profile: dict[str, Any], images: list[np.ndarray], hz: float) -> Path:
    """A respecd log of ``images`` as the profile's first sensor (RGB), recorded under ``profile``."""
    from respecd.clock import ManualClock
    from respecd.messages import Frame
    from respecd.record.config import RecordingConfig
    from respecd.record.recorder import Recorder

    async def record() -> None:
        # drain_s None: close encodes every queued frame (the default gives a robot's SIGTERM budget)
        recorder = Recorder(RecordingConfig(enabled=True, path=str(path)), profile, clock := ManualClock(),
                            drain_s=None)
        recorder.start()
        name = profile["sensors"][0]["name"]
        for i, image in enumerate(images):
            clock.set(i / hz)
            recorder.on_frame(name, Frame("rgb", i / hz, i, image))
            await asyncio.sleep(0.002)
        await recorder.close()

    asyncio.run(record())
    return path
