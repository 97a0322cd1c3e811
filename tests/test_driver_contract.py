"""The driver contract, run over every key in ``DRIVERS`` (python-can's Back2Back pattern).

Each registered driver has a rig here: a way to build it on its fake device (the seams its
own tests use: a video file, recorded USB reads, an SDK software device, pseudo-terminals, a
recorded log, the simulator) and on no device at all. One test class runs the same contract
over all of them, and a test fails when a registered driver has no rig.
"""

from __future__ import annotations

import asyncio
import os
import threading
import typing
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from respecd.clock import ManualClock, MonotonicClock
from respecd.drivers import DRIVERS
from respecd.drivers.base import Driver, DriverContext
from respecd.errors import DriverUnavailableError
from respecd.messages import Frame, SensorConfig
from respecd.sensors import clamp_request
from respecd.supervisor import Backoff, driver_runner, supervise

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
QUIET_S = 0.6  # how long a disabled sensor is watched for frames


@dataclass
class Rig:
    """How to build one driver: ``make(enabled)`` on its fake device, ``unplugged()`` on none."""

    make: Callable[[bool], Driver]
    unplugged: Callable[[], Driver] | None  # None: the driver has no device to lose (the simulator)
    request: SensorConfig  # a valid change from the start configuration
    out_of_range: SensorConfig  # a request it must clamp and say so
    feed: Callable[[Driver], None] = lambda driver: None  # start the fake device's stream, if it needs it
    device: Callable[[], None] = lambda: None  # plug the fake device in (before ``make``; once)


def _sim(tmp_path: Path) -> Iterator[Rig]:
    from respecd.drivers.sim import SimConfig, SimDriver
    from respecd.sim.config import SimulationConfig

    context = DriverContext(seed=3, simulation=SimulationConfig(scenario_duration_s=5))

    def make(enabled: bool) -> Driver:
        config = SimConfig(driver="sim", name="rgb", modality="rgb", rate_hz=10, resolution=(640, 360), enabled=enabled)
        return SimDriver(config, MonotonicClock(), context)

    yield Rig(make, None, SensorConfig("rgb", rate_hz=5.0, resolution=(960, 540)),
              SensorConfig("rgb", rate_hz=45.0, resolution=(1000, 560)))


def _uvc(tmp_path: Path) -> Iterator[Rig]:
    import cv2

    from respecd.drivers.uvc import UVCConfig, UVCDriver

    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 20, (320, 240))
    for i in range(40):
        writer.write(np.full((240, 320, 3), 5 * i, np.uint8))
    writer.release()

    def make(enabled: bool) -> Driver:
        return UVCDriver(UVCConfig(name="rgb", device=str(video), loop=True, enabled=enabled,
                                   resolutions=[(320, 240), (160, 120)]), MonotonicClock())

    yield Rig(make, lambda: UVCDriver(UVCConfig(name="rgb", device=str(tmp_path / "no-such.avi")), MonotonicClock()),
              SensorConfig("rgb", rate_hz=10.0, resolution=(160, 120)),
              SensorConfig("rgb", rate_hz=90.0, resolution=(1280, 720)))


def _flirone(tmp_path: Path) -> Iterator[Rig]:
    from respecd.drivers.flirone import FlirOneConfig, FlirOneDriver
    from respecd.drivers.flirone_usb import RecordedTransport

    capture = SHARED / "flirone_pro_gen3_usb_moezemara" / "test_chunks_hex"
    if not capture.exists():
        pytest.skip(f"shared capture {capture} absent")
    chunks = RecordedTransport.from_path(capture).chunks

    def make(enabled: bool) -> Driver:
        config = FlirOneConfig(name="thermal", realtime=False, enabled=enabled)
        return FlirOneDriver(config, MonotonicClock(), transport=RecordedTransport(chunks, loop=True))

    yield Rig(make, lambda: FlirOneDriver(FlirOneConfig(name="thermal"), MonotonicClock()),
              SensorConfig("thermal", rate_hz=4.0, resolution=(80, 60)),
              SensorConfig("thermal", rate_hz=30.0, resolution=(1280, 720)))


def _realsense(tmp_path: Path) -> Iterator[Rig]:
    from respecd.drivers.realsense import RealSenseConfig, RealSenseDriver

    unplugged = lambda: RealSenseDriver(RealSenseConfig(name="depth", serial="000000000099"), MonotonicClock())  # noqa: E731
    try:
        import pyrealsense2  # noqa: F401
    except ImportError:  # the SDK is an optional extra: then only the no-device half of the contract runs
        yield Rig(_needs_sdk, unplugged, SensorConfig("depth"), SensorConfig("depth"))
        return
    from test_realsense_sdk import SoftwareD435

    devices: list[Any] = []

    def device() -> None:
        if not devices:
            devices.append(SoftwareD435())

    def make(enabled: bool) -> Driver:
        device()
        config = RealSenseConfig(name="depth", resolution=(640, 480), rate_hz=10.0, enabled=enabled)
        return RealSenseDriver(config, MonotonicClock(), device=devices[-1].device)

    def feed(driver: Driver) -> None:
        devices[-1].feed(driver, "depth")

    yield Rig(make, unplugged, SensorConfig("depth", rate_hz=5.0, resolution=(640, 360)),
              SensorConfig("depth", rate_hz=90.0, resolution=(1280, 720)), feed, device)
    for device in devices:
        device.close()


def _needs_sdk(enabled: bool) -> Driver:
    pytest.skip("pyrealsense2 (optional extra 'realsense') is not installed")


def _iwr6843(tmp_path: Path) -> Iterator[Rig]:
    from fake_radar import FakeRadar, capture_frames, radar_config

    from respecd.drivers.iwr6843 import IWR6843Config, IWR6843Driver

    fakes: list[FakeRadar] = []  # made only when a test wants the device (its pseudo-terminal threads)

    def device() -> None:
        if not fakes:
            fakes.append(FakeRadar(tmp_path, capture_frames()))

    def make(enabled: bool) -> Driver:
        device()
        fake = fakes[-1]
        config = radar_config(fake, cli_timeout_s=0.5, reconnect_initial_s=0.05, reconnect_max_s=0.2, enabled=enabled)
        return IWR6843Driver(config, MonotonicClock())

    def unplugged() -> Driver:
        config = IWR6843Config(name="radar", cli_port=str(tmp_path / "no-cli"), data_port=str(tmp_path / "no-data"))
        return IWR6843Driver(config, MonotonicClock())

    yield Rig(make, unplugged, SensorConfig("radar", rate_hz=20.0, mode="velocity"),
              SensorConfig("radar", rate_hz=45.0, mode="range"), device=device)
    for fake in fakes:
        fake.unplug()


def _replay(tmp_path: Path) -> Iterator[Rig]:
    from respecd.drivers.replay import ReplayConfig, ReplayDriver
    from respecd.record.config import RecordingConfig
    from respecd.record.reader import open_log
    from respecd.record.recorder import Recorder

    async def record() -> Path:
        clock = ManualClock()
        recorder = Recorder(RecordingConfig(path=str(tmp_path / "log.mcap")), {"name": "rig", "sensors": []}, clock)
        recorder.start()
        for i in range(30):
            clock.set(i / 30)
            recorder.on_frame("cam", Frame("rgb", i / 30, i, np.full((360, 640, 3), 8 * i, np.uint8)))
        await recorder.close()
        return recorder.paths[0]

    log = open_log(asyncio.run(record()))

    def make(enabled: bool) -> Driver:
        config = ReplayConfig(name="cam", modality="rgb", native_resolution=(640, 360), enabled=enabled)
        return ReplayDriver(config, MonotonicClock(), DriverContext(replay=log))

    yield Rig(make, lambda: ReplayDriver(ReplayConfig(name="cam", modality="rgb"), MonotonicClock()),
              SensorConfig("rgb", rate_hz=10.0, resolution=(960, 540)),
              SensorConfig("rgb", rate_hz=0.2, resolution=(1000, 560)))


RIGS: dict[str, Callable[[Path], Iterator[Rig]]] = {
    "sim": _sim, "uvc": _uvc, "flirone": _flirone, "realsense": _realsense, "iwr6843": _iwr6843, "replay": _replay,
}


def test_every_registered_driver_is_in_the_contract_suite() -> None:
    assert set(RIGS) == set(DRIVERS), f"no contract rig for: {sorted(set(DRIVERS) - set(RIGS))}"


@pytest.fixture(params=sorted(DRIVERS))
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Rig]:
    if request.param not in RIGS:
        pytest.fail(f"driver {request.param!r} has no contract rig")
    yield from RIGS[request.param](tmp_path)


def _open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


async def _frames_within(driver: Driver, seconds: float, limit: int = 3) -> list[Frame]:
    frames: list[Frame] = []
    stream = driver.frames()
    try:
        async with asyncio.timeout(seconds):
            async for frame in stream:
                frames.append(frame)
                if len(frames) >= limit:
                    break
    except TimeoutError:
        pass
    finally:
        await stream.aclose()
    return frames


class TestDriverContract:
    async def test_the_constructor_does_no_io(self, rig: Rig) -> None:
        rig.device()
        threads, fds = set(threading.enumerate()), _open_fds()
        drivers = [rig.make(True), *([rig.unplugged()] if rig.unplugged else [])]
        assert set(threading.enumerate()) == threads, "a constructor started a thread"
        assert _open_fds() == fds, "a constructor opened a file or device"
        for driver in drivers:
            assert driver.applied.modality == driver.modality  # the start configuration is known without I/O

    async def test_stop_before_start_and_twice(self, rig: Rig) -> None:
        driver = rig.unplugged() if rig.unplugged else rig.make(True)
        await driver.stop()
        await driver.stop()

    async def test_start_and_stop_twice(self, rig: Rig) -> None:
        driver = rig.make(True)
        for _ in range(2):
            await driver.start()
            rig.feed(driver)
            assert await _frames_within(driver, 5.0, limit=1), "no frame after start"
            await driver.stop()
            await driver.stop()

    async def test_a_disabled_sensor_emits_nothing(self, rig: Rig) -> None:
        driver = rig.make(False)
        await driver.start()
        rig.feed(driver)
        try:
            assert await _frames_within(driver, QUIET_S) == []
        finally:
            await driver.stop()

    async def test_apply_returns_what_was_applied(self, rig: Rig) -> None:
        driver = rig.make(True)
        await driver.start()
        rig.feed(driver)
        try:
            await _frames_within(driver, 5.0, limit=1)  # the device has said what it is (FLIR One: its layout)
            applied = await driver.apply(rig.request)
            assert applied == driver.applied
            fitted = clamp_request(driver.capabilities, applied)  # within what it says it supports:
            assert replace(fitted, notes=()) == replace(applied, notes=())  # clamping changes nothing
            clamped = await driver.apply(rig.out_of_range)
            assert clamped == driver.applied and clamped.notes, "an out-of-range request was not reported"
            assert (clamped.rate_hz, clamped.resolution) != (rig.out_of_range.rate_hz, rig.out_of_range.resolution)
        finally:
            await driver.stop()

    async def test_an_unplugged_device_is_unavailable_and_retried(self, rig: Rig) -> None:
        if rig.unplugged is None:
            pytest.skip("the simulator has no device to lose")
        driver = rig.unplugged()
        with pytest.raises(DriverUnavailableError):
            await driver.start()
        await driver.stop()
        fast = Backoff(initial_s=0.01, max_s=0.02)
        task = asyncio.create_task(supervise("contract", driver_runner(driver, lambda frame: None), backoff=fast))
        for _ in range(100):  # up to 2 s: a failed start through a worker thread takes a moment
            await asyncio.sleep(0.02)
            if driver.health.restarts >= 2:
                break
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        assert driver.health.restarts >= 2 and driver.health.errors >= 2  # retried, not given up on


@pytest.mark.parametrize("key", sorted(DRIVERS))
def test_a_driver_key_is_one_name(key: str) -> None:
    """Module name = registry key = the class's ``key`` = the YAML ``driver:`` value."""
    from respecd.drivers import config_classes, driver_class

    module, _, _ = DRIVERS[key]
    assert module == key
    assert driver_class(key).key == key
    spelled = {value for c in config_classes() for value in typing.get_args(c.model_fields["driver"].annotation)}
    assert key in spelled
