"""ReplayDriver on a real recorded log: rate drops frames, resolution resizes (ground truth
follows), disabled sends nothing, radar modes cut range and fold velocity, clamps are reported."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from respecd.clock import ManualClock
from respecd.drivers import DRIVERS, driver_class
from respecd.drivers.base import DriverContext
from respecd.drivers.replay import ReplayConfig, ReplayDriver
from respecd.errors import DriverUnavailableError
from respecd.messages import Frame, SensorConfig
from respecd.radar.chirp import lookup
from respecd.record.config import RecordingConfig
from respecd.record.reader import SessionLog, open_log
from respecd.record.recorder import Recorder

RADAR_POINTS = np.array(
    [  # x, y (boresight), z, v, snr
        [0.0, 3.0, 0.0, 0.5, 20.0],
        [1.0, 11.0, 0.0, -2.5, 15.0],  # inside 14.99 m; -2.5 m/s folds in velocity mode at 10 Hz (+-2.26)
        [0.0, 30.0, 0.0, 0.2, 9.0],  # beyond both modes' 14.99 m
    ],
    dtype=np.float32,
)


@pytest.fixture
async def session(tmp_path: Path) -> SessionLog:
    clock = ManualClock()
    recorder = Recorder(RecordingConfig(path=str(tmp_path / "d.mcap")), {"name": "rig", "sensors": []}, clock)
    recorder.start()
    for i in range(30):  # 1 s at 30 Hz
        t = i / 30
        clock.set(t)
        image = np.full((360, 640, 3), 8 * (i % 30), np.uint8)
        recorder.on_frame("cam", Frame("rgb", t, i, image, {"gt": [{"box": [64.0, 36.0, 320.0, 180.0], "id": 1}]}))
        if i % 3 == 0:
            recorder.on_frame("radar", Frame("radar", t, i // 3, RADAR_POINTS))
    await recorder.close()
    return open_log(recorder.paths[0])


def _driver(session: SessionLog, name: str, modality: str, **extra: object) -> ReplayDriver:
    config = ReplayConfig(name=name, modality=modality, **extra)  # type: ignore[arg-type]
    return ReplayDriver(config, ManualClock(), DriverContext(replay=session))


def test_registered_under_replay_key() -> None:
    assert DRIVERS["replay"] == ("replay", "ReplayDriver", "ReplayConfig")
    assert driver_class("replay") is ReplayDriver


async def test_lower_rate_drops_frames_on_the_grid(session: SessionLog) -> None:
    driver = _driver(session, "cam", "rgb", native_resolution=(640, 360))
    applied = await driver.apply(SensorConfig("rgb", True, 10.0, (640, 360)))
    assert applied.rate_hz == 10.0 and applied.notes == ()
    served = [f for f in map(driver.counterfactual, session.frames("cam")) if f is not None]
    assert [f.seq for f in served] == list(range(0, 30, 3))
    assert driver.dropped_by_rate == 20


async def test_lower_resolution_resizes_and_ground_truth_follows(session: SessionLog) -> None:
    driver = _driver(session, "cam", "rgb", native_resolution=(640, 360))
    await driver.apply(SensorConfig("rgb", True, 30.0, (1280, 720)))
    assert any("upscaled" in n for n in driver.applied.notes)  # above the log's resolution: said so
    await driver.apply(SensorConfig("rgb", True, 30.0, (640, 360)))
    first, second = list(session.frames("cam"))[:2]
    assert driver.counterfactual(first).data.shape == (360, 640, 3)
    await driver.apply(SensorConfig("rgb", True, 30.0, (960, 540)))
    up = driver.counterfactual(second)
    assert up.data.shape == (540, 960, 3) and up.meta["gt"] == [{"box": [96.0, 54.0, 480.0, 270.0], "id": 1}]
    small = _driver(session, "cam", "rgb", native_resolution=(1280, 720))
    await small.apply(SensorConfig("rgb", True, 30.0, (640, 360)))
    big = Frame("rgb", 0.0, 0, np.zeros((720, 1280, 3), np.uint8), {"gt": [[128.0, 72.0, 640.0, 360.0]]})
    out = small.counterfactual(big)
    assert out.data.shape == (360, 640, 3)
    assert out.meta["gt"] == [[64.0, 36.0, 320.0, 180.0]]


async def test_disabled_sends_nothing(session: SessionLog) -> None:
    driver = _driver(session, "cam", "rgb", native_resolution=(640, 360))
    await driver.apply(SensorConfig("rgb", False, 30.0, (640, 360)))
    assert all(driver.counterfactual(f) is None for f in session.frames("cam"))


async def test_radar_modes_cut_range_and_fold_velocity(session: SessionLog) -> None:
    driver = _driver(session, "radar", "radar", mode="range")
    frame = next(iter(session.frames("radar")))
    ranged = driver.counterfactual(frame).data
    np.testing.assert_array_equal(ranged[:, :3], RADAR_POINTS[:2, :3])  # the 30 m point is out of range
    np.testing.assert_allclose(ranged[:, 3], [0.5, -2.5], atol=1e-6)  # within the range row's +-10.8 m/s
    driver = _driver(session, "radar", "radar", mode="range")  # the same logged frame, delivered afresh
    await driver.apply(SensorConfig("radar", True, 10.0, mode="velocity"))
    fast = driver.counterfactual(frame).data
    vmax = lookup("velocity", 10).max_velocity_mps  # 2.26 m/s: the row the real radar would run
    np.testing.assert_allclose(fast[:, 3], [0.5, -2.5 + 2 * vmax], atol=1e-5)


async def test_frames_follow_the_clock_and_stop_cleanly(session: SessionLog) -> None:
    driver = _driver(session, "radar", "radar", mode="range")
    await driver.start()
    got: list[Frame] = []

    async def consume() -> None:
        async for frame in driver.frames():
            got.append(frame)

    task = asyncio.create_task(consume())
    await asyncio.sleep(0.05)
    assert len(got) == 1  # t=0 only: the clock has not moved
    driver.clock.set(1.0)  # type: ignore[attr-defined]
    for _ in range(100):
        if len(got) == 10:
            break
        await asyncio.sleep(0.01)
    assert [f.seq for f in got] == list(range(10))
    await driver.stop()
    await asyncio.wait_for(task, timeout=2.0)


async def test_missing_sensor_or_log_is_unavailable(session: SessionLog) -> None:
    with pytest.raises(DriverUnavailableError, match="no sensor 'front'"):
        await _driver(session, "front", "rgb").start()
    orphan = ReplayDriver(ReplayConfig(name="cam", modality="rgb"), ManualClock())
    with pytest.raises(DriverUnavailableError, match="needs an opened log"):
        await orphan.start()


def test_streaming_and_random_access_deliver_the_same_frames() -> None:
    """The replay driver (streaming) and `bench scenarios --log` (random access) share one rule."""
    from respecd.replay import counterfactual

    times = [i / 30 for i in range(90)] + [3.0 + i / 7 for i in range(20)]  # 30 Hz, then a slow stretch
    for rate in (1.0, 5.0, 9.0, 10.0, 30.0):
        streamed, previous = [], None
        for i, t in enumerate(times):
            if counterfactual.delivers(previous, t, rate):
                streamed.append(i)
            previous = t
        for t in np.linspace(0.0, times[-1], 400):
            newest = max((i for i in streamed if times[i] <= t + 1e-9), default=None)
            assert counterfactual.delivered_index(times, rate, float(t)) == newest, (rate, t)


def test_depth_is_resized_by_nearest_neighbour_only() -> None:
    from respecd.replay import counterfactual

    depth = np.array([[1000, 1000, 4000, 4000]] * 2, np.uint16)  # a foreground edge against a wall
    for size in ((2, 1), (8, 4)):
        out = counterfactual.resize(Frame("depth", 0.0, 0, depth), size).data
        assert set(np.unique(out)) <= {1000, 4000}  # no depth in between was made up


async def test_read_ahead_decodes_only_the_modalities_named(tmp_path: Path) -> None:
    """Without a detector the features read RGB and thermal pixels, never depth's: the read-ahead
    threads decode the RGB JPEGs and leave the depth PNGs encoded."""
    from respecd.control.features import IMAGE_FEATURE_MODALITIES

    clock = ManualClock()
    recorder = Recorder(RecordingConfig(path=str(tmp_path / "rd.mcap")), {"name": "rig", "sensors": []}, clock)
    recorder.start()
    for i in range(5):
        clock.set(i / 10)
        recorder.on_frame("cam", Frame("rgb", i / 10, i, np.full((36, 64, 3), 40 * i, np.uint8)))
        recorder.on_frame("tof", Frame("depth", i / 10, i, np.full((48, 64), 1000 + i, np.uint16)))
    await recorder.close()
    log_ = open_log(recorder.paths[0])
    context = DriverContext(replay=log_, decode_ahead=IMAGE_FEATURE_MODALITIES)
    drivers = {m: ReplayDriver(ReplayConfig(name=n, modality=m), ManualClock(), context)  # type: ignore[arg-type]
               for n, m in (("cam", "rgb"), ("tof", "depth"))}
    for driver in drivers.values():
        await driver.start()
    try:
        read = {m: [d._prefetch.get() for _ in range(5)] for m, d in drivers.items()}  # type: ignore[union-attr]
    finally:
        for driver in drivers.values():
            await driver.stop()
    assert all(getattr(f, "decoded", True) for f in read["rgb"])
    assert not any(getattr(f, "decoded", True) for f in read["depth"])
    assert read["depth"][4].data[0, 0] == 1004  # still decodes when something reads it
