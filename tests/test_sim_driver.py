"""The simulated driver: honours rate, resolution, mode and enable; clamps and says so; stops cleanly."""

from __future__ import annotations

import asyncio

import cv2
import numpy as np
import pytest

from respecd.clock import ManualClock, MonotonicClock
from respecd.config import load_profile
from respecd.drivers import driver_class
from respecd.drivers.base import DriverContext
from respecd.drivers.sim import SimConfig, SimDriver, _thermal_frame
from respecd.messages import Frame, SensorConfig
from respecd.sim.render import render_thermal
from respecd.sim.world import SimulationConfig, World

CONTEXT = DriverContext(seed=11, simulation=SimulationConfig(scenario_duration_s=5))


def _driver(modality: str = "rgb", clock=None, **fields) -> SimDriver:  # type: ignore[no-untyped-def]
    fields.setdefault("render_in_thread", "never")
    config = SimConfig(driver="sim", name=f"sim-{modality}", modality=modality, **fields)
    return SimDriver(config, clock or ManualClock(), CONTEXT)


async def _settle() -> None:
    for _ in range(30):  # let the reader task run through its awaits
        await asyncio.sleep(0)


class Reader:
    """Collects a driver's frames in a task while the test moves a ManualClock."""

    def __init__(self, driver: SimDriver) -> None:
        self.driver = driver
        self.frames: list[Frame] = []
        self.task = asyncio.create_task(self._run(), name="sim-reader")

    async def _run(self) -> None:
        async for frame in self.driver.frames():
            self.frames.append(frame)

    async def run_until(self, clock: ManualClock, t: float, step: float = 0.01) -> None:
        await _settle()
        while clock.now() < t - 1e-9:
            clock.advance(step)
            await _settle()

    async def close(self) -> None:
        await self.driver.stop()
        await asyncio.wait_for(self.task, timeout=5)


async def test_rate_is_exact_on_the_clock_grid() -> None:
    clock = ManualClock()
    driver = _driver("rgb", clock, rate_hz=10, resolution=(640, 360))
    await driver.start()
    reader = Reader(driver)
    await reader.run_until(clock, 1.0)
    await reader.close()
    assert [f.t for f in reader.frames] == pytest.approx([k / 10 for k in range(11)])
    assert [f.seq for f in reader.frames] == list(range(11))
    assert driver.health.drops == 0


async def test_apply_takes_effect_on_the_next_frame() -> None:
    clock = ManualClock()
    driver = _driver("thermal", clock, rate_hz=9, resolution=(160, 120))
    await driver.start()
    reader = Reader(driver)
    await reader.run_until(clock, 0.5)
    applied = await driver.apply(SensorConfig("thermal", rate_hz=2.0, resolution=(320, 240)))
    assert applied.rate_hz == 2.0 and applied.resolution == (320, 240)
    assert applied.notes == ("320x240 is upscaled from the native resolution",)  # as on the FLIR One
    count = len(reader.frames)
    await reader.run_until(clock, 2.55)
    await reader.close()
    before, after = reader.frames[:count], reader.frames[count:]
    assert all(f.data.shape == (120, 160) for f in before)
    assert all(f.data.shape == (240, 320) and f.data.dtype == np.uint16 for f in after)
    assert [f.t for f in before] == pytest.approx([k / 9 for k in range(5)])
    assert [f.t for f in after] == pytest.approx([0.5, 1.0, 1.5, 2.0, 2.5])  # the 2 Hz grid from the next slot
    assert driver.health.drops == 0
    assert after[0].meta["units"] == "cK" and after[0].meta["gt"] is not None
    assert after[0].meta["upscaled_from"] == (160, 120) and "upscaled_from" not in before[0].meta


async def test_thermal_keeps_to_the_flir_one_limits() -> None:
    """The Lepton delivers about 9 frames per second at 160x120; the simulated one does no better."""
    clock = ManualClock()
    driver = _driver("thermal", clock, rate_hz=9, resolution=(160, 120))
    applied = await driver.apply(SensorConfig("thermal", rate_hz=30.0, resolution=(160, 120)))
    assert applied.rate_hz == 9.0 and applied.notes == ("rate 30 Hz capped at 9 Hz",)
    await driver.start()
    reader = Reader(driver)
    await reader.run_until(clock, 2.0)
    await reader.close()
    assert len(reader.frames) == 19  # t = 0, 1/9, ..., 18/9
    native = reader.frames[0].data
    upscaled, _ = _thermal_frame(World(SimulationConfig(), 0).state_at(1.0), (320, 240), np.random.default_rng(0))
    plain = render_thermal(World(SimulationConfig(), 0).state_at(1.0), (160, 120), np.random.default_rng(0))
    assert native.shape == (120, 160)
    assert np.array_equal(upscaled, cv2.resize(plain, (320, 240), interpolation=cv2.INTER_LINEAR))


async def test_raising_the_rate_mid_period_drops_nothing() -> None:
    clock = ManualClock()
    driver = _driver("imu", clock, rate_hz=1)
    await driver.start()
    reader = Reader(driver)
    await reader.run_until(clock, 0.5)
    await driver.apply(SensorConfig("imu", rate_hz=20))
    await reader.run_until(clock, 1.02)
    await reader.close()
    assert [f.t for f in reader.frames] == pytest.approx([0.0] + [k / 20 for k in range(10, 21)])
    assert driver.health.drops == 0


async def test_requests_outside_the_capabilities_are_clamped_and_reported() -> None:
    driver = _driver("rgb")
    applied = await driver.apply(SensorConfig("rgb", rate_hz=45.0, resolution=(1000, 560), mode="velocity"))
    assert applied.rate_hz == 30.0 and applied.resolution == (960, 540) and applied.mode is None
    assert any("capped" in n for n in applied.notes) and any("unsupported" in n for n in applied.notes)
    radar = _driver("radar")
    applied = await radar.apply(SensorConfig("radar", rate_hz=0.2, resolution=(640, 480), mode="velocity"))
    assert applied.rate_hz == 1.0 and applied.mode == "velocity" and applied.resolution is None
    assert driver_class("sim") is SimDriver


async def test_radar_mode_and_every_layout() -> None:
    clock = ManualClock()
    drivers = {m: _driver(m, clock, rate_hz=5) for m in ("rgb", "thermal", "radar", "depth", "imu")}
    await drivers["radar"].apply(SensorConfig("radar", rate_hz=5, mode="velocity"))
    readers = []
    for driver in drivers.values():
        await driver.start()
        readers.append(Reader(driver))
    await readers[0].run_until(clock, 0.2)
    for reader in readers:
        await reader.close()
    first = {r.driver.modality: r.frames[0] for r in readers}
    assert first["rgb"].data.shape == (720, 1280, 3) and first["rgb"].data.dtype == np.uint8
    assert first["depth"].data.shape == (480, 848) and first["depth"].meta["units"] == "mm"
    assert first["radar"].data.shape[1] == 5 and first["radar"].meta["mode"] == "velocity"
    assert first["radar"].meta["figures"]["max_range_m"] < 15
    assert first["imu"].data.shape == (6,)
    for frame in first.values():
        assert frame.meta["scenario"] == "good-light-static" and 0 < frame.meta["light"] <= 1
        assert isinstance(frame.meta["gt"], list) and frame.meta["gt"]


async def test_disabled_sensor_is_silent_until_enabled() -> None:
    clock = ManualClock()
    driver = _driver("imu", clock, rate_hz=10)
    await driver.start()
    await driver.apply(SensorConfig("imu", enabled=False, rate_hz=10))
    reader = Reader(driver)
    await reader.run_until(clock, 1.0)
    assert reader.frames == []
    await driver.apply(SensorConfig("imu", enabled=True, rate_hz=10))
    await reader.run_until(clock, 1.5)
    await reader.close()
    assert 5 <= len(reader.frames) <= 6 and reader.frames[0].t == pytest.approx(1.0)


async def test_stop_ends_the_stream_while_it_waits() -> None:
    clock = ManualClock()
    driver = _driver("rgb", clock, rate_hz=1, resolution=(640, 360))
    await driver.stop()  # before start: harmless
    await driver.start()
    reader = Reader(driver)
    await reader.run_until(clock, 0.5)
    assert len(reader.frames) == 1
    await driver.stop()  # the clock never reaches the next frame: stop alone must end the stream
    await asyncio.wait_for(reader.task, timeout=2)
    await driver.stop()


async def test_same_seed_same_frames() -> None:
    clock = ManualClock(start=3.0)
    a, b = _driver("rgb", clock, resolution=(640, 360)), _driver("rgb", clock, resolution=(640, 360))
    await a.start()
    await b.start()
    assert a.world is b.world
    readers = [Reader(a), Reader(b)]
    await readers[0].run_until(clock, 3.2)
    for reader in readers:
        await reader.close()
    fa, fb = readers[0].frames, readers[1].frames
    assert len(fa) == len(fb) >= 6
    assert all(np.array_equal(x.data, y.data) and x.t == y.t for x, y in zip(fa, fb, strict=True))


async def test_worker_thread_render_on_the_live_clock() -> None:
    driver = _driver("rgb", MonotonicClock(), rate_hz=30, render_in_thread="always")
    frames: list[Frame] = []

    async def read() -> None:
        async for frame in driver.frames():
            frames.append(frame)
            if len(frames) == 6:
                await driver.stop()

    await driver.start()
    await asyncio.wait_for(read(), timeout=10)
    slots = [(f.t - frames[0].t) * 30 for f in frames]  # grid slots; a late consumer skips some
    assert len(frames) == 6 and slots == pytest.approx([round(s) for s in slots], abs=1e-6)
    assert (np.diff(slots) > 0).all()
    assert all(f.data.shape == (720, 1280, 3) for f in frames)


async def test_builtin_profile_builds_five_sim_sensors() -> None:
    profile = load_profile()
    assert profile.name == "sim-rover" and profile.simulation.scenario_duration_s == 30
    clock = ManualClock()
    context = DriverContext(seed=2, simulation=profile.simulation)
    drivers = [driver_class(s.driver)(s, clock, context) for s in profile.sensors]
    rates = {d.modality: d.applied.rate_hz for d in drivers}
    assert rates == {"rgb": 30, "thermal": 9, "radar": 10, "depth": 15, "imu": 30}
    assert {d.applied.resolution for d in drivers} == {(1280, 720), (160, 120), (640, 480), None}
    for d in drivers:
        assert d.config.power.watts(d.applied) > 0


async def test_thread_and_inline_renders_are_identical() -> None:
    clock = ManualClock(start=1.0)
    inline = _driver("depth", clock, rate_hz=10, resolution=(424, 240))
    threaded = _driver("depth", clock, rate_hz=10, resolution=(424, 240), render_in_thread="always")
    readers = []
    for driver in (inline, threaded):
        await driver.start()
        readers.append(Reader(driver))
    for step in range(4):
        for _ in range(500):  # the threaded render finishes in real time, not clock time
            if all(len(r.frames) > step for r in readers):
                break
            await asyncio.sleep(0.002)
        clock.advance(0.1)
    for reader in readers:
        await reader.close()
    a, b = readers[0].frames[:4], readers[1].frames[:4]
    assert len(a) == len(b) == 4
    assert all(
        np.array_equal(x.data, y.data) and x.t == y.t and x.meta["gt"] == y.meta["gt"]
        for x, y in zip(a, b, strict=True)
    )
