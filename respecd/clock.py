"""Injected clocks: live runs use the monotonic clock, replay runs use the log's time.

Every stage asks the clock for ``now()`` and sleeps through ``sleep_until()`` so that a
replay at ``--speed max`` can run in lockstep on logged timestamps and stay deterministic.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Seconds on this clock."""
        ...

    async def sleep_until(self, t: float) -> None:
        """Return once ``now() >= t``."""
        ...


class MonotonicClock:
    """Wall time for live runs: ``time.monotonic`` relative to construction."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    async def sleep_until(self, t: float) -> None:
        delay = t - self.now()
        if delay > 0:
            await asyncio.sleep(delay)

    def monotonic_at(self, t: float) -> float:
        """The ``time.monotonic()`` reading at which this clock reads ``t`` (respecd.ticktimer)."""
        return self._t0 + t


class ScaledClock(MonotonicClock):
    """Replay at a multiple of real time (``--speed 2`` runs twice as fast)."""

    def __init__(self, speed: float, start: float = 0.0) -> None:
        super().__init__()
        self._speed = speed
        self._start = start

    def now(self) -> float:
        return self._start + super().now() * self._speed

    def restart(self) -> None:
        """Back to ``start`` now: a replay's log time begins when its pipeline is up, so no
        logged second is spent loading the detector."""
        self._t0 = time.monotonic()

    async def sleep_until(self, t: float) -> None:
        delay = (t - self.now()) / self._speed
        if delay > 0:
            await asyncio.sleep(delay)

    def monotonic_at(self, t: float) -> float:
        return self._t0 + (t - self._start) / self._speed


class ManualClock:
    """A clock that only moves when told: lockstep replay and tests.

    ``sleep_until`` waits until someone calls ``advance``/``set`` past the target, so the
    order of events depends on logged time alone, not on scheduling.
    """

    def __init__(self, start: float = 0.0) -> None:
        self._now = start
        self._changed = asyncio.Event()

    def now(self) -> float:
        return self._now

    def set(self, t: float) -> None:
        if t > self._now:
            self._now = t
            self._changed.set()
            self._changed = asyncio.Event()

    def advance(self, dt: float) -> None:
        self.set(self._now + dt)

    async def sleep_until(self, t: float) -> None:
        while self._now < t:
            await self._changed.wait()
