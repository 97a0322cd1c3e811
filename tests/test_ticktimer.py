"""The synchronizer's tick timer: a timerfd on the live clocks, the clock's own sleep elsewhere."""

from __future__ import annotations

import asyncio
import os
import sys
import time

import pytest
from test_sync import make

from respecd.clock import ManualClock, MonotonicClock, ScaledClock
from respecd.queues import DropOldestQueue
from respecd.sync import Synchronizer
from respecd.ticktimer import TickTimer

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timerfd is Linux's")


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


@linux_only
@pytest.mark.parametrize("clock", [MonotonicClock(), ScaledClock(4.0, start=100.0)], ids=["monotonic", "scaled"])
async def test_wakes_through_the_timerfd_never_before_the_deadline(clock: MonotonicClock) -> None:
    timer = TickTimer(clock)
    assert timer.precise
    try:
        for step in (0.0003, 0.0017, 0.004, 0.0101):
            deadline = clock.now() + step
            await timer.sleep_until(deadline)
            assert clock.now() >= deadline
        assert asyncio.get_running_loop().remove_reader(timer._fd) is False  # nothing left registered
    finally:
        timer.close()


@linux_only
def test_a_clock_time_maps_onto_the_monotonic_reading() -> None:
    clock = ScaledClock(2.0, start=10.0)
    now_mono, now = time.monotonic(), clock.now()
    assert clock.monotonic_at(now + 1.0) - now_mono == pytest.approx(0.5, abs=0.01)  # 1 log-second at 2x
    plain = MonotonicClock()
    assert plain.monotonic_at(plain.now()) == pytest.approx(time.monotonic(), abs=0.01)


async def test_a_manual_clock_keeps_its_own_sleep() -> None:
    clock = ManualClock(0.0)
    timer = TickTimer(clock)
    assert not timer.precise  # a lockstep replay's time is not the wall clock's
    sleeper = asyncio.create_task(timer.sleep_until(5.0))
    await asyncio.sleep(0.01)
    assert not sleeper.done()
    clock.set(5.0)
    await asyncio.wait_for(sleeper, 1.0)


@linux_only
async def test_a_past_deadline_returns_at_once_and_a_cancelled_sleep_leaves_no_reader() -> None:
    clock = MonotonicClock()
    timer = TickTimer(clock)
    try:
        await asyncio.wait_for(timer.sleep_until(clock.now() - 1.0), 0.5)
        sleeper = asyncio.create_task(timer.sleep_until(clock.now() + 60.0))
        await asyncio.sleep(0.01)
        sleeper.cancel()
        with pytest.raises(asyncio.CancelledError):
            await sleeper
        assert asyncio.get_running_loop().remove_reader(timer._fd) is False
        deadline = clock.now() + 0.002
        await asyncio.wait_for(timer.sleep_until(deadline), 1.0)  # still usable after a cancel
        assert clock.now() >= deadline
    finally:
        timer.close()


@linux_only
async def test_the_synchronizer_ticks_on_the_timer_and_releases_it_when_stopped() -> None:
    before = open_fds()
    drivers = {"cam": make("cam", "rgb", 30.0)}
    ticks: list[tuple[float, float]] = []
    sync = Synchronizer(drivers, {"cam": DropOldestQueue(4)}, DropOldestQueue(64), MonotonicClock(),
                        max_rate_hz=30.0, on_tick=lambda s, a: ticks.append((s, a)))
    task = asyncio.create_task(sync.run())
    await asyncio.sleep(0.25)
    assert open_fds() == before + 1  # the timerfd
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert open_fds() == before
    assert len(ticks) >= 3
    assert all(actual >= scheduled for scheduled, actual in ticks)  # a tick never fires early
