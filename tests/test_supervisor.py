"""A failing sensor is retried with backoff while the rest keeps running."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import numpy as np
import pytest

from respecd.clock import MonotonicClock
from respecd.drivers.base import Driver
from respecd.errors import DriverIOError, DriverUnavailableError
from respecd.messages import Frame, SensorConfig
from respecd.sensors import Capabilities, DriverConfigBase
from respecd.supervisor import Backoff, driver_runner, supervise


class FlakyDriver(Driver):
    """Unavailable for ``fail_starts`` starts, then streams; optionally dies after ``die_after`` frames."""

    key = "flaky"

    def __init__(self, name: str, fail_starts: int = 0, die_after: int | None = None) -> None:
        super().__init__(DriverConfigBase(driver="flaky", name=name, modality="rgb"), MonotonicClock())
        self.fail_starts = fail_starts
        self.die_after = die_after
        self.starts = self.stops = 0

    @property
    def capabilities(self) -> Capabilities:
        return Capabilities(modality="rgb")

    async def start(self) -> None:
        self.starts += 1
        if self.starts <= self.fail_starts:
            raise DriverUnavailableError("device absent")

    async def stop(self) -> None:
        self.stops += 1

    async def frames(self) -> AsyncIterator[Frame]:
        for seq in range(10**6):
            if self.die_after is not None and seq == self.die_after:
                raise DriverIOError("cable pulled")
            await asyncio.sleep(0.001)
            yield Frame("rgb", self.clock.now(), seq, np.zeros(1))

    async def apply(self, request: SensorConfig) -> SensorConfig:
        return request


FAST = Backoff(initial_s=0.01, max_s=0.04, stable_s=10.0)


async def run_until(done, *drivers: FlakyDriver, limit_s: float = 20.0) -> dict[str, int]:
    """Supervise ``drivers`` until ``done(counts)`` holds (a deadline, not a fixed time: CI may be loaded)."""
    counts = {d.name: 0 for d in drivers}

    def sink_for(name: str):
        def sink(frame: Frame) -> None:
            counts[name] += 1

        return sink

    tasks = [asyncio.create_task(supervise(d.name, driver_runner(d, sink_for(d.name)), backoff=FAST)) for d in drivers]
    loop = asyncio.get_running_loop()
    deadline = loop.time() + limit_s
    while not done(counts) and loop.time() < deadline:
        await asyncio.sleep(0.01)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    return counts


async def test_unavailable_driver_is_retried_while_others_stream():
    absent, healthy = FlakyDriver("absent", fail_starts=3), FlakyDriver("healthy")
    counts = await run_until(lambda c: c["absent"] > 0 and c["healthy"] > 50, absent, healthy)
    assert absent.starts >= 4  # three refusals, then it came up
    assert counts["absent"] > 0 and counts["healthy"] > 0
    assert absent.health.errors == 3 and absent.health.last_error == "device absent"


async def test_driver_that_dies_is_stopped_and_restarted():
    dying = FlakyDriver("dying", die_after=5)
    counts = await run_until(lambda c: c["dying"] >= 10 and dying.starts >= 2, dying)
    assert dying.starts >= 2 and dying.stops >= dying.starts - 1
    assert dying.health.restarts >= 1 and "cable pulled" in dying.health.last_error
    assert counts["dying"] >= 10


@pytest.mark.parametrize(
    ("attempt", "recent", "delay"), [(1, 1, 0.5), (2, 2, 1.0), (5, 5, 8.0), (9, 9, 30.0), (2, 10, 30.0)]
)
def test_backoff_doubles_and_is_rate_limited(attempt, recent, delay):
    assert Backoff().delay(attempt, recent) == delay
