"""RealSense driver through the real pyrealsense2 library, on an SDK ``software_device``
whose sensors we feed from a thread (no camera needed). Skipped where pyrealsense2 is not
installed (it is an optional extra: pip install 'respecd[realsense]')."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from respecd.clock import MonotonicClock
from respecd.drivers.realsense import RealSenseConfig, RealSenseDriver
from respecd.messages import Frame, SensorConfig

rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 (optional extra 'realsense') is not installed")

DEPTH_MODES = [(848, 480, 30), (640, 480, 15), (640, 480, 30), (640, 360, 6)]
COLOR_MODES = [(640, 480, 30)]


class SoftwareD435:
    """A software D435-like device: depth (z16, 1 mm units) and colour (rgb8) sensors."""

    def __init__(self) -> None:
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, "Intel RealSense D435I (software)")
        self.device.register_info(rs.camera_info.serial_number, "000000000001")
        self.depth = self.device.add_sensor("Stereo Module")
        self.color = self.device.add_sensor("RGB Camera")
        self.profiles: dict[tuple[str, int, int, int], object] = {}
        for uid, (w, h, fps) in enumerate(DEPTH_MODES):
            self._add(self.depth, rs.stream.depth, rs.format.z16, 2, w, h, fps, uid)
        for uid, (w, h, fps) in enumerate(COLOR_MODES, start=10):
            self._add(self.color, rs.stream.color, rs.format.rgb8, 3, w, h, fps, uid)
        self.depth.add_read_only_option(rs.option.depth_units, 0.001)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.pushed = 0

    def _add(self, sensor, stream, fmt, bpp, w, h, fps, uid) -> None:
        vs = rs.video_stream()
        vs.type, vs.fmt, vs.width, vs.height, vs.fps, vs.bpp, vs.index, vs.uid = stream, fmt, w, h, fps, bpp, 0, uid
        intrinsics = rs.intrinsics()
        intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy = w, h, 400.0, 400.0
        intrinsics.ppx, intrinsics.ppy = w / 2, h / 2
        vs.intrinsics = intrinsics
        key = (stream.name, w, h, fps)
        self.profiles[key] = sensor.add_video_stream(vs)

    def feed(self, driver: RealSenseDriver, stream: str) -> None:
        """Push frames of whatever mode the driver has open, at that mode's rate."""
        self._thread = threading.Thread(target=self._run, args=(driver, stream), daemon=True)
        self._thread.start()

    def _run(self, driver: RealSenseDriver, stream: str) -> None:
        sensor = self.depth if stream == "depth" else self.color
        while not self._stop.is_set():
            source = driver._source
            opened = source.opened if source is not None else ()
            if not opened:
                time.sleep(0.005)
                continue
            mode = opened[0]
            profile = self.profiles[(mode.stream, mode.width, mode.height, mode.fps)]
            frame = rs.software_video_frame()
            if stream == "depth":
                pixels = np.full((mode.height, mode.width), 1000 + self.pushed % 100, np.uint16)
            else:
                pixels = np.zeros((mode.height, mode.width, 3), np.uint8)
                pixels[..., 0] = 200  # red in RGB order
            frame.pixels = pixels
            frame.bpp = pixels.itemsize * (3 if pixels.ndim == 3 else 1)
            frame.stride = mode.width * frame.bpp
            frame.timestamp = self.pushed * 1000.0 / mode.fps
            frame.domain = rs.timestamp_domain.hardware_clock
            frame.frame_number = self.pushed
            frame.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
            self.pushed += 1
            self._stop.wait(1.0 / mode.fps)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)


async def take(driver: RealSenseDriver, count: int) -> list[Frame]:
    frames: list[Frame] = []
    async with asyncio.timeout(15):
        async for frame in driver.frames():
            frames.append(frame)
            if len(frames) >= count:
                break
    return frames


async def test_depth_modes_from_the_sensor_and_a_mode_switch() -> None:
    device = SoftwareD435()
    cfg = RealSenseConfig(name="depth", resolution=(640, 480), rate_hz=10.0)
    driver = RealSenseDriver(cfg, MonotonicClock(), device=device.device)
    await driver.start()
    device.feed(driver, "depth")
    try:
        caps = driver.capabilities
        assert caps.resolutions == ((848, 480), (640, 480), (640, 360))
        assert driver.applied.resolution == (640, 480)
        assert driver._source.opened[0].fps == 15  # slowest mode still >= 10 Hz
        assert "device at 15 fps, decimated to 10 Hz" in driver.applied.notes
        frames = await take(driver, 3)
        assert frames[0].modality == "depth" and frames[0].data.shape == (480, 640)
        assert frames[0].data.dtype == np.uint16 and 1000 <= int(frames[0].data[0, 0]) < 1100
        applied = await driver.apply(SensorConfig("depth", rate_hz=5.0, resolution=(640, 360)))
        assert applied.resolution == (640, 360) and driver._source.opened[0].fps == 6
        frames = await take(driver, 6)
        assert frames[-1].data.shape == (360, 640)
        assert frames[-1].meta["time_domain"] == "hardware_clock"
    finally:
        await driver.stop()
        device.close()


async def test_old_mode_frames_after_a_switch_are_dropped() -> None:
    """Frames taken with the previous mode can still arrive after a switch (issue 21, item 10)."""
    device = SoftwareD435()
    driver = RealSenseDriver(RealSenseConfig(name="depth", resolution=(640, 480), rate_hz=10.0), MonotonicClock(),
                             device=device.device)
    await driver.start()
    device.feed(driver, "depth")
    try:
        await take(driver, 2)
        await driver.apply(SensorConfig("depth", rate_hz=5.0, resolution=(640, 360)))
        old = device.profiles[("depth", 640, 480, 15)].as_video_stream_profile()
        for number in (90_001, 90_002):  # late frames of the old mode, as a camera delivers them
            frame = rs.software_video_frame()
            frame.pixels = np.full((480, 640), 7, np.uint16)
            frame.bpp, frame.stride, frame.timestamp, frame.frame_number = 2, 640 * 2, 0.0, number
            frame.domain, frame.profile = rs.timestamp_domain.hardware_clock, old
            device.depth.on_video_frame(frame)
        frames = await take(driver, 4)
        assert all(f.data.shape == (360, 640) for f in frames) and driver._source.stale_frames >= 2
    finally:
        await driver.stop()
        device.close()


async def test_colour_stream_is_bgr() -> None:
    device = SoftwareD435()
    cfg = RealSenseConfig(name="colour", stream="color", modality="rgb")
    driver = RealSenseDriver(cfg, MonotonicClock(), device=device.device)
    await driver.start()
    device.feed(driver, "color")
    try:
        (frame,) = await take(driver, 1)
        assert frame.data.shape == (480, 640, 3)
        assert frame.data[0, 0].tolist() == [0, 0, 200]  # rgb8 red arrives as BGR red
    finally:
        await driver.stop()
        device.close()


class SoftwareIMU:
    """A software motion module: accel at 62 Hz and gyro at 200 Hz, fed from a thread."""

    def __init__(self) -> None:
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, "Intel RealSense T265 (software)")
        self.sensor = self.device.add_sensor("Motion Module")
        self.profiles = {}
        for uid, (stream, fps) in enumerate(((rs.stream.accel, 62), (rs.stream.gyro, 200))):
            ms = rs.motion_stream()
            ms.type, ms.fmt, ms.fps, ms.index, ms.uid = stream, rs.format.motion_xyz32f, fps, 0, uid
            self.profiles[stream.name] = self.sensor.add_motion_stream(ms)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def feed(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        n = 0
        while not self._stop.wait(0.005):  # ~200 Hz gyro, every 3rd tick an accel sample
            for name, value in (("gyro", (0.01, 0.02, 0.03)), ("accel", (0.0, -9.81, 0.1))):
                if name == "accel" and n % 3:
                    continue
                frame = rs.software_motion_frame()
                vector = rs.vector()
                vector.x, vector.y, vector.z = value
                frame.data, frame.timestamp, frame.frame_number = vector, n * 5.0, n
                frame.domain = rs.timestamp_domain.hardware_clock
                frame.profile = self.profiles[name].as_motion_stream_profile()
                self.sensor.on_motion_frame(frame)
            n += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2)


async def test_imu_combines_accel_and_gyro_and_decimates() -> None:
    imu = SoftwareIMU()
    cfg = RealSenseConfig(name="imu", stream="imu", modality="imu", rate_hz=10.0)
    driver = RealSenseDriver(cfg, MonotonicClock(), device=imu.device)
    await driver.start()
    imu.feed()
    try:
        assert [m.stream for m in driver._source.opened] == ["accel", "gyro"]
        frames = await take(driver, 4)
    finally:
        await driver.stop()
        imu.close()
    assert all(f.modality == "imu" and f.data.dtype == np.float32 and f.data.shape == (6,) for f in frames)
    assert np.allclose(frames[-1].data, [0.0, -9.81, 0.1, 0.01, 0.02, 0.03])
    assert np.diff([f.t for f in frames]).min() >= 0.75 / 10.0  # 200 Hz gyro decimated to 10 Hz
