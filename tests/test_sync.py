"""The synchronizer: tick rate, nearest-frame choice, staleness, jitter bins."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import replace

import numpy as np
import pytest

from respecd.clock import ManualClock
from respecd.drivers.base import Driver
from respecd.messages import Frame, Health, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.sensors import Capabilities, DriverConfigBase
from respecd.sync import HealthThresholds, Synchronizer, SyncWindow, freshness_limit, tick_rate


class ScriptedDriver(Driver):
    """A driver whose frames the test pushes by hand: only ``applied`` matters to the synchronizer."""

    key = "scripted"

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(modality=self.modality)

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def frames(self) -> AsyncIterator[Frame]:  # pragma: no cover - never iterated here
        if False:
            yield

    async def apply(self, request: SensorConfig) -> SensorConfig:
        self.applied = request
        return request


def make(name: str, modality: str, rate: float, tolerance_ms: float = 50.0) -> ScriptedDriver:
    config = DriverConfigBase(driver="scripted", name=name, modality=modality, rate_hz=rate, tolerance_ms=tolerance_ms)
    return ScriptedDriver(config, ManualClock())


def frame(modality: str, t: float, seq: int = 0) -> Frame:
    return Frame(modality=modality, t=t, seq=seq, data=np.zeros(1))


def rig(*drivers: ScriptedDriver, max_rate: float = 30.0):
    clock = ManualClock()
    by_name = {d.name: d for d in drivers}
    inputs = {d.name: DropOldestQueue[Frame](8) for d in drivers}
    out = DropOldestQueue(4)
    sync = Synchronizer(by_name, inputs, out, clock, max_rate_hz=max_rate, window_s=1.0)
    return sync, inputs, out, clock


@pytest.mark.parametrize(
    ("rates", "expected"),
    [([9.0, 30.0, 10.0], 30.0), ([45.0], 30.0), ([0.2], 1.0), ([], 1.0), ([12.5, 3.0], 12.5)],
)
def test_tick_rate_follows_fastest_sensor_within_caps(rates, expected):
    assert tick_rate(rates, 1.0, 30.0) == expected


def test_tick_rate_ignores_disabled_sensors():
    fast, slow = make("cam", "rgb", 30.0), make("th", "thermal", 9.0)
    sync, *_ = rig(fast, slow, max_rate=27.0)
    assert sync.current_rate() == 27.0  # the paper's Jetson cap
    sync.on_config("cam", replace(fast.applied, enabled=False))  # a config message, not a driver attribute
    assert sync.current_rate() == 9.0


def test_bundle_takes_newest_frame_per_sensor():
    cam, th = make("cam", "rgb", 30.0), make("th", "thermal", 9.0)
    sync, inputs, out, _ = rig(cam, th)
    for i, t in enumerate((0.90, 0.93, 0.96)):
        inputs["cam"].put(frame("rgb", t, i))
    inputs["th"].put(frame("thermal", 0.95))
    bundle = sync.tick(scheduled=1.0, actual=1.0, rate=30.0)
    assert bundle.frames["rgb"].t == 0.96
    assert bundle.frames["thermal"].t == 0.95
    assert out.get_nowait() is bundle


def test_stale_frame_is_left_out_and_counted():
    cam, th = make("cam", "rgb", 30.0, tolerance_ms=50), make("th", "thermal", 30.0, tolerance_ms=50)
    sync, inputs, _, _ = rig(cam, th)
    inputs["cam"].put(frame("rgb", 0.99))
    inputs["th"].put(frame("thermal", 0.80))  # 200 ms old at a 30 Hz sensor: stale
    bundle = sync.tick(1.0, 1.0, 30.0)
    assert set(bundle.frames) == {"rgb"}
    assert bundle.sync.stale_ratio == pytest.approx(0.5)
    assert bundle.sync.health is Health.POOR


def test_slow_sensor_frame_stays_fresh_for_its_own_period():
    # a 2 Hz sensor's frame is 400 ms old between its samples: not stale
    assert freshness_limit(0.05, 2.0) == pytest.approx(0.75)
    slow = make("radar", "radar", 2.0, tolerance_ms=50)
    sync, inputs, _, _ = rig(slow)
    inputs["radar"].put(frame("radar", 0.6))
    assert "radar" in sync.tick(1.0, 1.0, 2.0).frames


def test_future_frame_is_not_used():
    cam = make("cam", "rgb", 30.0)
    sync, inputs, _, _ = rig(cam)
    inputs["cam"].put(frame("rgb", 1.5))
    assert sync.tick(1.0, 1.0, 30.0).frames == {}


@pytest.mark.parametrize(
    ("jitter_ms", "stale", "health"),
    [
        (0.5, 0.0, Health.GOOD),
        (2.0, 0.1, Health.GOOD),
        (2.01, 0.0, Health.FAIR),
        (0.0, 0.11, Health.FAIR),
        (10.01, 0.0, Health.POOR),
        (0.0, 0.31, Health.POOR),
    ],
)
def test_health_bins_edges(jitter_ms, stale, health):
    assert HealthThresholds(2.0, 10.0, 0.1, 0.3).bin(jitter_ms, stale) is health


def test_window_forgets_old_ticks():
    window = SyncWindow(1.0, HealthThresholds())
    window.add(0.0, 0.020, 1, 1)  # one bad tick at t=0
    for i in range(1, 31):
        window.add(1.0 + i / 30, 0.0, 1, 0)
    stats = window.stats(30.0)
    assert stats.jitter_ms == 0.0 and stats.stale_ratio == 0.0 and stats.health is Health.GOOD


async def test_run_ticks_at_sensor_rate_on_the_clock():
    cam = make("cam", "rgb", 10.0)
    sync, _, out, clock = rig(cam)
    task = asyncio.create_task(sync.run())
    for _ in range(100):  # one simulated second in 10 ms steps
        clock.advance(0.01)
        await asyncio.sleep(0)
        await asyncio.sleep(0)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert 9 <= sync.bundles <= 11
    sync.on_config("cam", await cam.apply(replace(cam.applied, rate_hz=25.0)))
    assert sync.current_rate() == 25.0


@pytest.mark.parametrize(
    ("after", "rate", "phase", "expected"),
    [(0.0, 10.0, 0.5, 0.05), (0.05, 10.0, 0.5, 0.15), (0.149, 10.0, 0.5, 0.15), (1.0, 30.0, 0.0, 1.0 + 1 / 30)],
)
def test_ticks_sit_on_a_fixed_phase_grid(after, rate, phase, expected):
    from respecd.sync import grid_time

    assert grid_time(after, rate, phase) == pytest.approx(expected)


async def test_ticks_fall_between_sensor_frames():
    cam = make("cam", "rgb", 10.0)
    sync, _, _, clock = rig(cam)
    ticks: list[float] = []
    sync.on_tick = lambda scheduled, actual: ticks.append(scheduled)
    task = asyncio.create_task(sync.run())
    for _ in range(50):
        clock.advance(0.01)
        await asyncio.sleep(0)
        await asyncio.sleep(0)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert ticks[:3] == pytest.approx([0.05, 0.15, 0.25])  # half a period after the 10 Hz frame instants
