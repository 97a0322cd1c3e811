"""UVC/OpenCV driver on a real video file written here with cv2.VideoWriter (MJPG/AVI):
playback timing, resolution and rate changes, looping, pacing on a ManualClock, failures."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import cv2
import numpy as np
import pydantic
import pytest

from respecd.clock import ManualClock, MonotonicClock
from respecd.drivers import DRIVERS, driver_class
from respecd.drivers.uvc import UVCConfig, UVCDriver
from respecd.errors import DriverUnavailableError
from respecd.messages import Frame, SensorConfig

FPS = 20
FRAMES = 30
SIZE = (320, 240)


@pytest.fixture(scope="module")
def video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """30 frames at 20 fps; frame i is grey level 4*i with a white bar at x = 10*i."""
    path = tmp_path_factory.mktemp("uvc") / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, SIZE)
    assert writer.isOpened()
    for i in range(FRAMES):
        image = np.full((SIZE[1], SIZE[0], 3), 4 * i, np.uint8)
        image[:, 10 * i : 10 * i + 6] = 255
        writer.write(image)
    writer.release()
    return path


def config(video: Path, **kw) -> UVCConfig:
    kw.setdefault("realtime", False)
    kw.setdefault("resolutions", [(640, 480), (320, 240), (160, 120)])
    return UVCConfig(name="rgb", device=str(video), **kw)


def grey_level(frame: Frame) -> float:
    return float(np.median(frame.data))


def bar_x(frame: Frame) -> int:
    """Column of the white bar, in the original 320-pixel frame."""
    row = frame.data[frame.data.shape[0] // 2, :, 1].astype(int)
    return int(np.argmax(row > 200) * SIZE[0] / frame.data.shape[1])


async def collect(driver: UVCDriver, limit: int = 1000, on_frame=None) -> list[Frame]:
    frames: list[Frame] = []
    await driver.start()
    try:
        async with asyncio.timeout(20):
            async for frame in driver.frames():
                frames.append(frame)
                if on_frame is not None:
                    await on_frame(driver, frames)
                if len(frames) >= limit:
                    break
    finally:
        await driver.stop()
    return frames


def worker_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("respecd-driver-")]


def test_registered() -> None:
    assert DRIVERS["uvc"][0] == "uvc" and driver_class("uvc") is UVCDriver


async def test_plays_every_frame_of_the_file(video: Path) -> None:
    driver = UVCDriver(config(video, resolution=SIZE), MonotonicClock())
    frames = await collect(driver)
    assert len(frames) == FRAMES  # the stream ends with the file (loop: false)
    assert all(f.data.shape == (240, 320, 3) and f.data.dtype == np.uint8 for f in frames)
    assert [f.meta["file_frame"] for f in frames] == list(range(FRAMES))
    assert np.allclose(np.diff([f.t for f in frames]), 1 / FPS)  # the file's own frame rate
    assert all(abs(bar_x(f) - 10 * i) <= 2 for i, f in enumerate(frames))  # MJPG blurs the edge
    assert abs(grey_level(frames[10]) - 40) < 4  # MJPG is lossy
    caps = driver.capabilities
    assert caps.max_rate_hz == FPS and caps.upscaled == ((640, 480),)
    assert driver.applied.rate_hz == FPS and "rate 30 Hz capped at 20 Hz" in driver.applied.notes
    assert worker_threads() == []


async def test_resolution_change_resizes_and_says_so(video: Path) -> None:
    async def shrink(driver: UVCDriver, frames: list[Frame]) -> None:
        if len(frames) == 5:
            applied = await driver.apply(SensorConfig("rgb", rate_hz=FPS, resolution=(160, 120)))
            assert applied.resolution == (160, 120)
            assert "resized from 320x240 by cv2.resize" in applied.notes

    frames = await collect(UVCDriver(config(video), MonotonicClock()), on_frame=shrink)
    assert frames[0].data.shape == (240, 320, 3)
    # up to three were read before the change: two in the handoff, one waiting for room
    assert all(f.data.shape == (120, 160, 3) for f in frames[5 + 3 :])
    assert frames[-1].meta["resized_from"] == SIZE
    assert all(abs(bar_x(f) - 10 * f.meta["file_frame"]) <= 2 for f in frames)


async def test_upscale_request_is_reported(video: Path) -> None:
    driver = UVCDriver(config(video, resolution=(640, 480)), MonotonicClock())
    frames = await collect(driver, limit=2)
    assert frames[0].data.shape == (480, 640, 3)
    assert "640x480 is upscaled from the native resolution" in driver.applied.notes


async def test_rate_change_decimates_on_media_time(video: Path) -> None:
    async def slow_down(driver: UVCDriver, frames: list[Frame]) -> None:
        if len(frames) == 4:
            applied = await driver.apply(SensorConfig("rgb", rate_hz=5.0, resolution=SIZE))
            assert applied.rate_hz == 5.0 and "file runs at 20 fps, decimated to 5 Hz" in applied.notes

    frames = await collect(UVCDriver(config(video), MonotonicClock()), on_frame=slow_down)
    late = np.diff([f.t for f in frames[4 + 3 :]])  # up to three were read before the change
    assert np.allclose(late, 0.2)  # every 4th frame of a 20 fps file
    assert 4 + 5 <= len(frames) <= 4 + 3 + 7


async def test_loop_continues_time_across_passes(video: Path) -> None:
    frames = await collect(UVCDriver(config(video, loop=True), MonotonicClock()), limit=FRAMES + 15)
    times = [f.t for f in frames]
    assert np.allclose(np.diff(times), 1 / FPS)
    assert frames[FRAMES].meta["loop"] == 1 and frames[FRAMES].meta["file_frame"] == 0
    assert abs(bar_x(frames[FRAMES + 3]) - 30) <= 2


async def test_realtime_playback_follows_the_clock(video: Path) -> None:
    clock = ManualClock()
    driver = UVCDriver(config(video, realtime=True), clock)
    await driver.start()
    frames: list[Frame] = []
    try:
        stream = driver.frames()
        first = await asyncio.wait_for(anext(stream), 5)  # due at t0: no wait
        assert first.t == 0.0
        pending = asyncio.ensure_future(anext(stream))
        await asyncio.sleep(0.1)
        assert not pending.done()  # the next frame is due at 0.05 s on the clock, which has not moved
        for _ in range(10):
            clock.advance(1 / FPS)
            frames.append(await asyncio.wait_for(pending, 5))
            assert frames[-1].t <= clock.now() + 1e-9
            pending = asyncio.ensure_future(anext(stream))
        pending.cancel()
        await stream.aclose()
    finally:
        await driver.stop()
    assert [round(f.t, 6) for f in frames] == [round(i / FPS, 6) for i in range(1, 11)]


async def test_disabled_sensor_emits_nothing(video: Path) -> None:
    driver = UVCDriver(config(video, enabled=False), MonotonicClock())
    assert await collect(driver) == []


async def test_missing_file_and_device_are_unavailable(tmp_path: Path) -> None:
    for device in (str(tmp_path / "nope.mp4"), "/dev/video99"):
        driver = UVCDriver(UVCConfig(name="rgb", device=device), MonotonicClock())
        with pytest.raises(DriverUnavailableError, match="nope.mp4|/dev/video99"):
            await driver.start()
        await driver.stop()
        await driver.stop()
    assert worker_threads() == []


def test_config_validation() -> None:
    with pytest.raises(pydantic.ValidationError, match="rgb frames only"):
        UVCConfig(name="x", modality="thermal")
    with pytest.raises(pydantic.ValidationError):
        UVCConfig(name="x", fourcc="MJPEG")
    with pytest.raises(pydantic.ValidationError):
        UVCConfig(name="x", resolutions=[])
    assert UVCConfig(name="x", device="/dev/respecd-rgb").is_file is False
    assert UVCConfig(name="x", device="clip.mp4").is_file is True


def test_camera_entries_in_a_profile(tmp_path: Path) -> None:
    """The three camera drivers as a profile's sensors, and a typo reported with its line."""
    from respecd.config import load_profile
    from respecd.errors import ConfigError

    text = """name: cameras
sensors:
  - {name: rgb, driver: uvc, device: /dev/respecd-rgb, fourcc: MJPG, resolution: [1280, 720]}
  - {name: thermal, driver: flirone, rate_hz: 9, resolution: [160, 120]}
  - {name: depth, driver: realsense, stream: depth, product: D435I, rate_hz: 15}
  - {name: imu, driver: realsense, modality: imu, stream: imu, product: T265}
"""
    path = tmp_path / "cams.yaml"
    path.write_text(text)
    profile = load_profile(path)
    assert [s.driver for s in profile.sensors] == ["uvc", "flirone", "realsense", "realsense"]
    path.write_text(text.replace("fourcc: MJPG", "fourc: MJPG"))
    with pytest.raises(ConfigError) as err:
        load_profile(path)
    assert any(p.startswith(f"{path}:3: sensors.0.fourc: unknown key") for p in err.value.problems)


async def test_start_after_the_stream_ended_starts_afresh(video: Path) -> None:
    driver = UVCDriver(config(video), MonotonicClock())
    await driver.start()
    try:
        first = [f async for f in driver.frames()]  # ends with the file
        await driver.start()  # no stop in between: the ended worker is replaced
        frame = await asyncio.wait_for(anext(driver.frames()), 5)
    finally:
        await driver.stop()
    assert len(first) == FRAMES and frame.meta["file_frame"] == 0 and frame.seq == FRAMES


async def test_live_source_keeps_only_confirmed_sizes_and_fails_when_it_stops(video: Path) -> None:
    """The file opened as a live source: it ignores size and rate requests like a fixed camera,
    and its end looks like an unplugged camera."""
    cfg = config(video, source="camera", resolution=(160, 120))
    driver = UVCDriver(cfg, MonotonicClock())
    await driver.start()
    got: list[Frame] = []
    try:
        assert driver.capabilities.resolutions == (SIZE,)  # 640x480 and 160x120 were not confirmed
        assert driver.applied.resolution == SIZE
        assert "resolution 160x120 unsupported, using 320x240" in driver.applied.notes
        with pytest.raises(DriverUnavailableError, match="stopped delivering frames"):
            async with asyncio.timeout(10):
                async for frame in driver.frames():
                    got.append(frame)
    finally:
        await driver.stop()
    assert got and got[0].meta == {"source": "camera"} and got[0].data.shape == (240, 320, 3)


def test_camera_that_refuses_a_size_is_reopened_and_reported(video: Path) -> None:
    """Worker-side: a size the capture will not take triggers one reopen, then an honest note."""
    from respecd.drivers.uvc_capture import UVCSource

    cfg = config(video, source="camera")
    source = UVCSource(cfg, MonotonicClock(), SensorConfig("rgb", rate_hz=10.0), threading.Event())
    source.open()
    try:
        first = source.cap
        applied = source.reconfigure(SensorConfig("rgb", rate_hz=10.0, resolution=(160, 120)))
        assert source.cap is not first  # reopened to set the size before streaming
        assert applied.resolution == SIZE
        assert "camera delivers 320x240, not 160x120" in applied.notes
    finally:
        source.close()


class ModedCamera:
    """cv2.VideoCapture as a UVC camera answers it through V4L2: a mode table per pixel format
    (the fastest rate per size), MJPG only if ``mjpg`` (many USB 2 webcams: YUYV 720p at 10 fps)."""

    MODES = {"MJPG": {(1280, 720): 30, (640, 360): 30}, "YUYV": {(1280, 720): 10, (640, 360): 30}}

    def __init__(self, device, api, mjpg: bool = True) -> None:
        self.fourcc, self.size, self.fps, self.mjpg = "YUYV", (640, 360), 30.0, mjpg

    def isOpened(self) -> bool:
        return True

    def release(self) -> None:
        pass

    def set(self, prop: int, value: float) -> bool:
        if prop == cv2.CAP_PROP_FOURCC:
            wanted = "".join(chr((int(value) >> 8 * i) & 0xFF) for i in range(4))
            self.fourcc = wanted if wanted == "YUYV" or self.mjpg else self.fourcc
        elif prop == cv2.CAP_PROP_FRAME_WIDTH:
            self.width = int(value)  # OpenCV sets the format once both are known
        elif prop == cv2.CAP_PROP_FRAME_HEIGHT:
            wanted = (getattr(self, "width", self.size[0]), int(value))
            self.size = wanted if wanted in self.MODES[self.fourcc] else (640, 360)
        elif prop == cv2.CAP_PROP_FPS:
            self.fps = min(float(value), self.MODES[self.fourcc][self.size])
        else:
            return False
        self.fps = min(self.fps, self.MODES[self.fourcc][self.size])  # a size change may lower the rate
        return True

    def get(self, prop: int) -> float:
        values = {cv2.CAP_PROP_FRAME_WIDTH: self.size[0], cv2.CAP_PROP_FRAME_HEIGHT: self.size[1],
                  cv2.CAP_PROP_FPS: self.fps, cv2.CAP_PROP_FOURCC: cv2.VideoWriter.fourcc(*self.fourcc)}
        return float(values.get(prop, 0.0))


def _moded_source(monkeypatch: pytest.MonkeyPatch, mjpg: bool, **cfg):
    from respecd.drivers import uvc_capture

    monkeypatch.setattr(uvc_capture.cv2, "VideoCapture", lambda device, api: ModedCamera(device, api, mjpg))
    config = UVCConfig(name="rgb", device="/dev/video7", resolutions=[(1280, 720), (640, 360)], **cfg)
    source = uvc_capture.UVCSource(config, MonotonicClock(), SensorConfig("rgb", rate_hz=30.0, resolution=(640, 360)),
                                   threading.Event())
    source.open()
    return source


def test_rate_is_read_back_after_a_size_change(monkeypatch: pytest.MonkeyPatch) -> None:
    source = _moded_source(monkeypatch, mjpg=False)
    assert source.applied.rate_hz == 30 and source.device_fps == 30
    applied = source.reconfigure(SensorConfig("rgb", rate_hz=30.0, resolution=(1280, 720)))
    assert applied.resolution == (1280, 720) and source.device_fps == 10  # YUYV 720p: 10 fps
    assert applied.rate_hz == 10 and "camera delivers 10 fps at 1280x720" in applied.notes
    back = source.reconfigure(SensorConfig("rgb", rate_hz=30.0, resolution=(640, 360)))
    assert back.rate_hz == 30 and source.device_fps == 30


def test_the_pixel_format_is_read_back(monkeypatch: pytest.MonkeyPatch) -> None:
    from structlog.testing import capture_logs

    with capture_logs() as logs:
        refused = _moded_source(monkeypatch, mjpg=False, fourcc="MJPG")
    assert refused.fourcc == "YUYV" and "camera streams YUYV, not MJPG" in refused.applied.notes
    assert [e["got"] for e in logs if e["event"] == "uvc_fourcc_refused"] == ["YUYV"]
    taken = _moded_source(monkeypatch, mjpg=True, fourcc="MJPG")
    assert taken.fourcc == "MJPG" and not any("streams" in note for note in taken.applied.notes)
    assert taken.reconfigure(SensorConfig("rgb", rate_hz=30.0, resolution=(1280, 720))).rate_hz == 30


def test_v4l2_reads_give_up_after_a_second(monkeypatch: pytest.MonkeyPatch) -> None:
    """CAP_PROP_READ_TIMEOUT_MSEC does nothing on V4L2; cap_v4l.cpp reads this variable instead."""
    monkeypatch.delenv("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", raising=False)
    source = _moded_source(monkeypatch, mjpg=True)
    import os

    assert os.environ["OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT"] == "1" and source.select_timeout_s == 1
    monkeypatch.setenv("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", "4")  # the operator's own choice wins
    assert _moded_source(monkeypatch, mjpg=True).select_timeout_s == 4


@pytest.fixture(scope="module")
def cut_video(video: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The clip cut at 60% of its bytes (a copy interrupted): the header still declares 30 frames."""
    path = tmp_path_factory.mktemp("uvc-cut") / "cut.avi"
    data = video.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.6)])
    return path


async def test_truncated_file_is_warned_once_and_counted_each_time(cut_video: Path) -> None:
    from structlog.testing import capture_logs

    driver = UVCDriver(config(cut_video), MonotonicClock())
    with capture_logs() as logs:
        first = await collect(driver)
        second = await collect(driver)  # played again (a restart): counted again, not warned again
    assert 0 < len(first) == len(second) < FRAMES
    warned = [e for e in logs if e["event"] == "uvc_file_truncated"]
    assert len(warned) == 1 and warned[0]["log_level"] == "warning"
    assert (warned[0]["frames_read"], warned[0]["frames_declared"], warned[0]["file"]) == (len(first), FRAMES,
                                                                                           str(cut_video))
    assert driver.health.errors == 2
    assert driver.health.last_error == f"video file {cut_video} ended after {len(first)} of the {FRAMES} frames it " \
        "declares (truncated?)"


async def test_truncated_looping_file_is_counted_per_pass(cut_video: Path) -> None:
    driver = UVCDriver(config(cut_video, loop=True), MonotonicClock())
    frames = await collect(driver, limit=40)
    passes = max(f.meta["loop"] for f in frames)
    assert passes >= 1 and driver.health.errors == passes


async def test_complete_file_ends_normally(video: Path) -> None:
    from structlog.testing import capture_logs

    driver = UVCDriver(config(video), MonotonicClock())
    with capture_logs() as logs:
        frames = await collect(driver)
    assert len(frames) == FRAMES and driver.finished
    assert (driver.health.errors, driver.health.last_error) == (0, None)
    ended = [e for e in logs if e["event"] == "uvc_file_ended"]
    assert len(ended) == 1 and ended[0]["log_level"] == "info" and ended[0]["frames"] == FRAMES
    assert not [e for e in logs if e["log_level"] in ("warning", "error")]


async def test_a_stopped_driver_has_not_finished(video: Path) -> None:
    driver = UVCDriver(config(video), MonotonicClock())
    await collect(driver, limit=3)
    assert not driver.finished


async def test_under_the_daemon_a_file_that_ended_stays_ended(video: Path) -> None:
    """The session's runner: one pass, one info line; no stage_returned warning and no replay per backoff."""
    from structlog.testing import capture_logs

    from respecd.supervisor import Backoff, driver_runner, supervise

    driver = UVCDriver(config(video), MonotonicClock())
    frames: list[Frame] = []
    with capture_logs() as logs:
        task = asyncio.create_task(
            supervise("driver:rgb", driver_runner(driver, frames.append),
                      backoff=Backoff(initial_s=0.05, max_s=0.05))
        )
        await asyncio.sleep(1.5)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert len(frames) == FRAMES  # before: played again after every backoff
    assert [e["event"] for e in logs if e["log_level"] in ("warning", "error")] == []
    assert [e["event"] for e in logs if e["event"] == "uvc_file_ended"] == ["uvc_file_ended"]
    assert worker_threads() == []
