"""FLIR One driver: recorded EP 0x85 reads through the transport seam, the worker thread,
decimation, the rate cap, upscaling, FFC flags, unplug, and the missing-libusb path."""

from __future__ import annotations

import asyncio
import struct
import threading
from pathlib import Path

import cv2
import numpy as np
import pydantic
import pytest

from respecd.clock import MonotonicClock
from respecd.drivers import DRIVERS, driver_class
from respecd.drivers.flirone import FlirOneConfig, FlirOneDriver
from respecd.drivers.flirone_protocol import build_frame, encode_pro_thermal
from respecd.drivers.flirone_usb import RecordedTransport
from respecd.errors import DriverTimeoutError, DriverUnavailableError
from respecd.messages import Frame, SensorConfig


@pytest.fixture
def chunks(shared_data: Path) -> list[bytes]:
    return RecordedTransport.from_path(shared_data / "flirone_pro_gen3_usb_moezemara" / "test_chunks_hex").chunks


def config(**kw) -> FlirOneConfig:
    kw.setdefault("realtime", False)  # recorded reads timed by the camera's own clock
    return FlirOneConfig(name="thermal", **kw)


async def collect(driver: FlirOneDriver, limit: int = 1000) -> list[Frame]:
    frames: list[Frame] = []
    await driver.start()
    try:
        async with asyncio.timeout(20):
            async for frame in driver.frames():
                frames.append(frame)
                if len(frames) >= limit:
                    break
    finally:
        await driver.stop()
    return frames


def worker_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("respecd-driver-")]


def test_registered() -> None:
    assert DRIVERS["flirone"][0] == "flirone"
    assert driver_class("flirone") is FlirOneDriver


async def test_real_capture_through_the_driver(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(resolution=(80, 60)), MonotonicClock(), transport=RecordedTransport(chunks))
    assert driver.capabilities.resolutions[0] == (160, 120)  # assumed One Pro until a frame says otherwise
    frames = await collect(driver)
    # 20 frames in 1.97 s of camera time; the two resent ones arrive 35-60 ms after their twin,
    # inside the 9 Hz cap, so the decimator lets 18 through
    assert len(frames) == 18
    assert all(f.data.shape == (60, 80) and f.data.dtype == np.uint16 for f in frames)
    assert [f.seq for f in frames] == list(range(18))
    gaps = np.diff([f.t for f in frames])
    assert gaps.min() >= 0.75 / 9.0
    assert driver.capabilities.resolutions == ((80, 60), (160, 120), (320, 240))
    assert driver.capabilities.upscaled == ((160, 120), (320, 240))
    assert driver.applied.resolution == (80, 60)
    assert not any("upscaled" in n for n in driver.applied.notes)
    assert not any(f.meta["ffc"] for f in frames)
    assert frames[0].meta["status"]["ffcState"] == "FFC_VALID_RAD"
    assert worker_threads() == []


async def test_upscale_and_rate_cap_are_reported(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(), MonotonicClock(), transport=RecordedTransport(chunks))
    applied = await driver.apply(SensorConfig("thermal", rate_hz=30.0, resolution=(320, 240)))
    assert applied.rate_hz == 9.0
    assert any("capped at 9 Hz" in n for n in applied.notes)
    assert any("320x240 is upscaled" in n for n in applied.notes)
    frames = await collect(driver, limit=3)
    assert frames[0].data.shape == (240, 320)
    assert frames[0].meta["upscaled_from"] == (80, 60)


async def test_lower_rate_is_decimated(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(rate_hz=2.0), MonotonicClock(), transport=RecordedTransport(chunks))
    frames = await collect(driver)
    assert 3 <= len(frames) <= 5  # 2 Hz over 1.97 s of camera time
    assert np.diff([f.t for f in frames]).min() >= 0.75 / 2.0


async def test_apply_while_running_changes_the_rate(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(), MonotonicClock(), transport=RecordedTransport(chunks, loop=True))
    await driver.start()
    try:
        times: list[float] = []
        async with asyncio.timeout(20):
            async for frame in driver.frames():
                times.append(frame.t)
                if len(times) == 5:
                    await driver.apply(SensorConfig("thermal", rate_hz=1.0, resolution=(80, 60)))
                    mark = len(times)
                if len(times) == 12:
                    break
    finally:
        await driver.stop()
    late = np.diff(times[mark + 3 :])  # up to three were read before the change
    assert late.min() >= 0.75


async def test_visible_stream_decodes_the_jpeg(chunks: list[bytes]) -> None:
    cfg = config(stream="visible", modality="rgb")
    driver = FlirOneDriver(cfg, MonotonicClock(), transport=RecordedTransport(chunks))
    frames = await collect(driver, limit=2)
    assert frames[0].modality == "rgb" and frames[0].data.shape == (1080, 1440, 3)
    assert driver.capabilities.resolutions == ((1440, 1080),)


def ffc_stream() -> list[bytes]:
    y, x = np.mgrid[0:120, 0:160]
    ok, jpeg = cv2.imencode(".jpg", np.zeros((48, 64, 3), np.uint8))
    assert ok
    states = ["ON", "ON", "FFC", "ON", "ON", "ON"]
    out = []
    for i, state in enumerate(states):
        image = (3000 + x + y + 100 * i).astype(np.uint16)
        status = {"shutterState": state, "usbNotifiedTimestamp": 1000.0 + 0.115 * i}
        out.append(build_frame(encode_pro_thermal(image), jpeg.tobytes(), status, repeat_word=i))
    return out


async def test_ffc_frames_are_flagged_then_skipped() -> None:
    driver = FlirOneDriver(config(), MonotonicClock(), transport=RecordedTransport(ffc_stream()))
    frames = await collect(driver)
    assert [f.meta["ffc"] for f in frames] == [False, False, True, True, False, False]
    assert frames[0].data.shape == (120, 160) and frames[0].meta["layout"] == (160, 120)
    skipping = FlirOneDriver(config(skip_ffc=True), MonotonicClock(), transport=RecordedTransport(ffc_stream()))
    kept = await collect(skipping)
    assert [int(f.data[0, 0]) for f in kept] == [3000, 3100, 3400, 3500]


class UnpluggedAfter(RecordedTransport):
    """Recorded reads, then the error pyusb's ENODEV becomes in the real transport."""

    def __init__(self, chunks: list[bytes], reads: int) -> None:
        super().__init__(chunks)
        self.reads_left = reads

    def read(self, size: int, timeout_ms: int) -> bytes:
        self.reads_left -= 1
        if self.reads_left < 0:
            raise DriverUnavailableError("flirone: camera unplugged (USB no device)")
        return super().read(size, timeout_ms)


async def test_unplug_ends_frames_with_unavailable(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(), MonotonicClock(), transport=UnpluggedAfter(chunks, reads=30))
    await driver.start()
    got = 0
    with pytest.raises(DriverUnavailableError, match="unplugged"):
        async with asyncio.timeout(10):
            async for _ in driver.frames():
                got += 1
    await driver.stop()
    assert got >= 3


async def test_recording_from_profile_path(shared_data: Path) -> None:
    path = shared_data / "flirone_pro_gen3_usb_moezemara" / "usb_stream_concat.bin"
    driver = FlirOneDriver(config(recording=str(path), loop=False), MonotonicClock())
    frames = await collect(driver)
    assert len(frames) == 18


async def test_missing_usb_device_or_libusb_is_unavailable() -> None:
    driver = FlirOneDriver(FlirOneConfig(name="thermal"), MonotonicClock())
    await driver.stop()  # before start: a no-op
    with pytest.raises(DriverUnavailableError, match=r"libusb|09cb:1996|pyusb|permission"):
        await driver.start()
    await driver.stop()
    await driver.stop()
    assert worker_threads() == []


def test_config_checks_stream_and_modality() -> None:
    with pytest.raises(pydantic.ValidationError, match="produces rgb frames"):
        FlirOneConfig(name="x", stream="visible")
    with pytest.raises(pydantic.ValidationError):
        FlirOneConfig(name="x", rate_hz=40)
    assert FlirOneConfig(name="x", stream="visible", modality="rgb").modality == "rgb"


class SilentAfter(RecordedTransport):
    """Recorded reads, then a camera that stays attached but sends nothing (bulk timeouts)."""

    def read(self, size: int, timeout_ms: int) -> bytes:
        chunk = super().read(size, timeout_ms)
        if not chunk:
            threading.Event().wait(timeout_ms / 1000)
        return chunk

    @property
    def exhausted(self) -> bool:
        return False


async def test_silent_camera_is_a_stall(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(stall_timeout_s=0.3), MonotonicClock(), transport=SilentAfter(chunks[:20]))
    await driver.start()
    got = 0
    with pytest.raises(DriverTimeoutError, match="no frame for 0.3 s"):
        async with asyncio.timeout(10):
            async for _ in driver.frames():
                got += 1
    await driver.stop()
    assert got >= 1 and worker_threads() == []


class BusyOnStart(RecordedTransport):
    def start(self) -> None:
        raise OSError("Resource busy")  # what a vendor library raises, unwrapped


async def test_vendor_error_on_open_is_unavailable(chunks: list[bytes]) -> None:
    driver = FlirOneDriver(config(), MonotonicClock(), transport=BusyOnStart(chunks))
    with pytest.raises(DriverUnavailableError, match="cannot open: OSError: Resource busy") as err:
        await driver.start()
    assert isinstance(err.value.__cause__, OSError)
    await driver.stop()
    assert worker_threads() == []


@pytest.mark.parametrize("policy", ["drop", "flag"])
async def test_a_frame_with_a_corrupted_line_is_dropped_or_flagged(chunks: list[bytes], policy: str) -> None:
    from structlog.testing import capture_logs

    header = next(i for i, c in enumerate(chunks) if len(c) == 28)
    thermal = bytearray(chunks[header + 1])
    thermal[164 * 30 + 10] ^= 0x80  # one pixel bit of row 30 of the first frame
    damaged = chunks[: header + 1] + [bytes(thermal)] + chunks[header + 2 :]
    driver = FlirOneDriver(config(line_crc=policy), MonotonicClock(), transport=RecordedTransport(damaged))
    with capture_logs() as logs:
        frames = await collect(driver)
    warned = [e for e in logs if e["event"] == "flirone_line_crc_failed"]
    assert len(warned) == 1 and warned[0]["lines"] == 1
    if policy == "drop":
        # frame 0 is gone; its resent twin (frame 1) now takes its slot in the 9 Hz grid
        assert len(frames) == 18 and driver.health.drops >= 1 and all(f.meta["crc_errors"] == 0 for f in frames)
    else:
        assert len(frames) == 18 and frames[0].meta["crc_errors"] == 1


@pytest.mark.parametrize("damage", ["cut", "bad_magic", "bad_length"])
async def test_damaged_frames_are_counted_and_logged_once(chunks: list[bytes], damage: str) -> None:
    from structlog.testing import capture_logs

    starts = [i for i, c in enumerate(chunks) if c.startswith(b"\xef\xbe\x00\x00")]
    damaged = [bytearray(c) for c in chunks]
    for k in (5, 11):
        if damage == "bad_magic":
            damaged[starts[k]][0:4] = b"\xef\xbe\x00\x01"
        elif damage == "bad_length":
            struct.pack_into("<I", damaged[starts[k]], 8, 900_000)
    if damage == "cut":  # each frame's last read lost
        damaged = [c for i, c in enumerate(damaged) if i not in (starts[6] - 1, starts[12] - 1)]
    undecimated = config(rate_hz=30, max_rate_hz=30)  # every frame assembled is delivered
    driver = FlirOneDriver(undecimated, MonotonicClock(), transport=RecordedTransport([bytes(c) for c in damaged]))
    with capture_logs() as logs:
        frames = await collect(driver)
    assert len(frames) == 18
    assert driver.health.drops == 2 and driver.health.errors == 2
    assert driver.health.last_error is not None and "2 damaged frames dropped" in driver.health.last_error
    first = [e for e in logs if e["event"] == "flirone_stream_damaged"]
    summaries = [e for e in logs if e["event"] == "flirone_stream_damage_summary"]
    assert len(first) == 1 and first[0]["log_level"] == "warning"
    # the second damaged frame is not a line of its own: it is in the summary written at stop
    assert len(summaries) == 1 and summaries[0]["damaged_frames"] == 1
    assert summaries[0]["truncated"] + summaries[0]["lost_sync"] == 2


async def test_undamaged_capture_reports_nothing(chunks: list[bytes]) -> None:
    from structlog.testing import capture_logs

    driver = FlirOneDriver(config(), MonotonicClock(), transport=RecordedTransport(chunks))
    with capture_logs() as logs:
        await collect(driver)
    assert (driver.health.drops, driver.health.errors) == (0, 0)
    assert not [e for e in logs if e["event"].startswith("flirone_stream_damage")]
