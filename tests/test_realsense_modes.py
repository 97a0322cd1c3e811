"""RealSense driver without a device: config validation, the missing-SDK message, stream-mode
selection from a D435i-like profile list, and frame conversions."""

from __future__ import annotations

import sys
import types
from types import SimpleNamespace

import numpy as np
import pydantic
import pytest

from respecd.clock import MonotonicClock
from respecd.drivers import DRIVERS, driver_class
from respecd.drivers.realsense import RealSenseConfig, RealSenseDriver
from respecd.drivers.realsense_modes import (
    StreamMode,
    color_to_bgr,
    depth_to_mm,
    imu_vector,
    pose_meta,
    select_motion_modes,
    select_video_mode,
    version_tuple,
    video_capabilities,
    video_modes,
)
from respecd.errors import DriverUnavailableError

# D435i depth and colour modes as its firmware lists them (a subset: sizes x rates)
DEPTH_SIZES = ((1280, 720), (848, 480), (640, 480), (640, 360))
D435I = [
    *(StreamMode("depth", "z16", w, h, f) for w, h in DEPTH_SIZES for f in (6, 15, 30)),
    *(StreamMode("depth", "z16", w, h, f) for w, h in DEPTH_SIZES[1:] for f in (60, 90)),
    *(StreamMode("color", c, w, h, f) for c in ("rgb8", "yuyv") for w, h in DEPTH_SIZES[::2] for f in (15, 30)),
    StreamMode("infrared", "y8", 848, 480, 30),
]


def test_registered() -> None:
    assert DRIVERS["realsense"][0] == "realsense" and driver_class("realsense") is RealSenseDriver


def test_config_validation() -> None:
    assert RealSenseConfig(name="d").modality == "depth"
    assert RealSenseConfig(name="c", stream="color", modality="rgb").stream == "color"
    with pytest.raises(pydantic.ValidationError, match="produces imu frames"):
        RealSenseConfig(name="i", stream="imu")
    with pytest.raises(pydantic.ValidationError):
        RealSenseConfig(name="d", wait_timeout_ms=0)
    with pytest.raises(pydantic.ValidationError):
        RealSenseConfig(name="d", exposure=3)


async def test_missing_sdk_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import pyrealsense2 -> ImportError
    driver = RealSenseDriver(RealSenseConfig(name="depth"), MonotonicClock())
    with pytest.raises(DriverUnavailableError, match=r"pip install 'respecd\[realsense\]'"):
        await driver.start()
    await driver.stop()
    await driver.stop()


@pytest.mark.parametrize("product", ["T265", None])
async def test_a_t265_on_a_new_sdk_gets_the_way_that_works(monkeypatch: pytest.MonkeyPatch, product) -> None:
    """pyrealsense2 >= 2.54 lists no T265: the message says what works instead (issue 21, item 9)."""
    sdk = types.SimpleNamespace(__version__="2.59.1", context=lambda: types.SimpleNamespace(query_devices=list))
    monkeypatch.setitem(sys.modules, "pyrealsense2", sdk)  # an SDK that sees no device at all
    driver = RealSenseDriver(RealSenseConfig(name="imu", modality="imu", stream="imu", product=product),
                             MonotonicClock())
    with pytest.raises(DriverUnavailableError) as err:
        await driver.start()
    await driver.stop()
    assert "librealsense 2.59.1 cannot see a T265" in str(err.value)
    assert "v2.53.1 from source" in str(err.value) and "product: D435I" in str(err.value)


async def test_a_d435i_imu_request_gets_no_t265_advice(monkeypatch: pytest.MonkeyPatch) -> None:
    sdk = types.SimpleNamespace(__version__="2.59.1", context=lambda: types.SimpleNamespace(query_devices=list))
    monkeypatch.setitem(sys.modules, "pyrealsense2", sdk)
    driver = RealSenseDriver(RealSenseConfig(name="imu", modality="imu", stream="imu", product="D435I"),
                             MonotonicClock())
    with pytest.raises(DriverUnavailableError, match="no RealSense found for D435I$"):
        await driver.start()
    await driver.stop()


def test_capabilities_from_the_modes() -> None:
    caps = video_capabilities(video_modes(D435I, "depth"), "depth")
    assert caps.resolutions == ((1280, 720), (848, 480), (640, 480), (640, 360))
    assert caps.max_rate_hz == 30.0  # 90 fps exists, the pipeline's cap is 30
    colour = video_modes(D435I, "color")
    assert {m.fmt for m in colour} == {"rgb8"}  # rgb8 preferred over yuyv; bgr8 is not offered here


def test_exact_mode_is_chosen_with_the_slowest_sufficient_rate() -> None:
    depth = video_modes(D435I, "depth")
    mode, notes = select_video_mode(depth, (848, 480), 10.0)
    assert mode == StreamMode("depth", "z16", 848, 480, 15)
    assert notes == ["device at 15 fps, decimated to 10 Hz"]
    mode, notes = select_video_mode(depth, (640, 360), 30.0)
    assert mode.fps == 30 and notes == []


def test_unoffered_size_and_rate_are_reported() -> None:
    depth = video_modes(D435I, "depth")
    mode, notes = select_video_mode(depth, (960, 540), 5.0)
    assert mode.size == (848, 480) and mode.fps == 6
    assert notes[0] == "960x540 not offered, using 848x480"
    mode, notes = select_video_mode(depth, (1280, 720), 60.0)
    assert mode.fps == 30 and "1280x720 runs at most 30 fps" in notes
    mode, _ = select_video_mode(depth, None, 30.0)
    assert mode.size == (1280, 720)
    with pytest.raises(ValueError):
        select_video_mode([], None, 30.0)


def test_motion_modes_one_per_stream() -> None:
    t265 = [StreamMode("gyro", "motion_xyz32f", 0, 0, 200), StreamMode("accel", "motion_xyz32f", 0, 0, 62),
            StreamMode("pose", "six_dof", 0, 0, 200), StreamMode("accel", "motion_xyz32f", 0, 0, 250)]
    assert [(m.stream, m.fps) for m in select_motion_modes(t265)] == [("accel", 62), ("gyro", 200), ("pose", 200)]


def test_depth_conversion_to_millimetres() -> None:
    raw = np.array([[0, 1000, 65535]], dtype=np.uint16)
    assert depth_to_mm(raw, 0.001).tolist() == [[0, 1000, 65535]]
    assert depth_to_mm(raw, 0.0001).tolist() == [[0, 100, 6554]]  # 100 um units (high-accuracy preset)
    assert depth_to_mm(np.array([[40000]], np.uint16), 0.002).tolist() == [[65535]]  # saturates, never wraps
    assert depth_to_mm(raw, 0.001) is not raw


def test_colour_conversion_to_bgr() -> None:
    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 200  # red
    bgr = color_to_bgr(rgb, "rgb8")
    assert bgr[0, 0].tolist() == [0, 0, 200] and bgr.flags.c_contiguous
    assert color_to_bgr(bgr, "bgr8").tolist() == bgr.tolist()
    yuyv = np.full((2, 4, 2), 128, np.uint8)  # mid grey
    assert color_to_bgr(yuyv, "yuyv").shape == (2, 4, 3)
    with pytest.raises(ValueError):
        color_to_bgr(rgb, "raw16")


def test_imu_and_pose() -> None:
    vector = imu_vector((0.0, -9.81, 0.1), (0.01, 0.02, 0.03))
    assert vector.dtype == np.float32 and vector.shape == (6,)
    xyz = SimpleNamespace(x=1.0, y=2.0, z=3.0)
    pose = SimpleNamespace(translation=xyz, velocity=xyz, rotation=SimpleNamespace(w=1.0, x=0.0, y=0.0, z=0.0),
                           tracker_confidence=3)
    meta = pose_meta(pose)
    assert meta["rotation_wxyz"] == (1.0, 0.0, 0.0, 0.0) and meta["tracker_confidence"] == 3


def test_version_tuple() -> None:
    assert version_tuple("2.53.1.4623") == (2, 53, 1, 4623)
    assert version_tuple("2.59.1") > (2, 53, 1) >= version_tuple("2.53.1")
    assert version_tuple("2.50.0-rc") == (2, 50)
