"""The synchronizer: one tick at f_sync, the newest in-tolerance frame per modality.

f_sync follows the fastest enabled sensor, capped by ``sync.max_rate_hz`` (30 Hz; the
paper's Jetson saturated at 27) and floored at ``sync.min_rate_hz`` (1 Hz). Each tick also
measures how well the pipeline keeps time: tick jitter (actual minus scheduled tick time)
and the stale-frame ratio (expected modalities missing or too old), binned into
good / fair / poor for the controller state.
"""

from __future__ import annotations

import asyncio
import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import structlog

from respecd.clock import Clock
from respecd.drivers.base import Driver
from respecd.messages import Bundle, Frame, Health, Modality, SensorConfig, SyncStats
from respecd.queues import DropOldestQueue
from respecd.ticktimer import TickTimer

log = structlog.get_logger(__name__)

STALE_PERIODS = 1.5  # a frame stays fresh for at least 1.5 of its own sensor's periods


@dataclass(frozen=True, slots=True)
class HealthThresholds:
    jitter_ms_fair: float = 2.0
    jitter_ms_poor: float = 10.0
    stale_fair: float = 0.1
    stale_poor: float = 0.3

    def bin(self, jitter_ms: float, stale_ratio: float) -> Health:
        if jitter_ms > self.jitter_ms_poor or stale_ratio > self.stale_poor:
            return Health.POOR
        if jitter_ms > self.jitter_ms_fair or stale_ratio > self.stale_fair:
            return Health.FAIR
        return Health.GOOD


def tick_rate(rates: list[float], min_hz: float, max_hz: float) -> float:
    """The tick rate for these enabled sensor rates: the fastest, clamped to [min_hz, max_hz]."""
    fastest = max(rates, default=min_hz)
    return min(max(fastest, min_hz), max_hz)


def grid_time(after: float, rate_hz: float, phase: float) -> float:
    """The first tick time later than ``after`` on the grid ``(k + phase) / rate_hz``.

    Ticks sit on a fixed grid of the clock rather than wherever the last tick landed, so
    they never drift; ``phase`` places them between the instants at which sensors sharing
    the clock's grid deliver (the simulator emits at ``k / rate``), when the loop is idle and
    the newest frames have just arrived.
    """
    k = math.floor(after * rate_hz - phase) + 1
    return (k + phase) / rate_hz


def freshness_limit(tolerance_s: float, rate_hz: float) -> float:
    """Oldest age (s) at which a frame of a sensor running at ``rate_hz`` still counts."""
    return max(tolerance_s, STALE_PERIODS / max(rate_hz, 1e-6))


class SyncWindow:
    """Rolling statistics over the last ``window_s`` seconds of ticks."""

    def __init__(self, window_s: float, thresholds: HealthThresholds) -> None:
        self.window_s = window_s
        self.thresholds = thresholds
        self._ticks: deque[tuple[float, float, int, int]] = deque()  # t, lateness s, expected, stale

    def add(self, t: float, lateness_s: float, expected: int, stale: int) -> None:
        self._ticks.append((t, lateness_s, expected, stale))
        while self._ticks and self._ticks[0][0] < t - self.window_s:
            self._ticks.popleft()

    def stats(self, rate_hz: float) -> SyncStats:
        if not self._ticks:
            return SyncStats(rate_hz, 0.0, 0.0, Health.GOOD)
        lateness = [abs(x[1]) for x in self._ticks]
        jitter_ms = 1000.0 * sum(lateness) / len(lateness)
        expected = sum(x[2] for x in self._ticks)
        stale_ratio = sum(x[3] for x in self._ticks) / expected if expected else 0.0
        return SyncStats(rate_hz, jitter_ms, stale_ratio, self.thresholds.bin(jitter_ms, stale_ratio))


class Synchronizer:
    """Ticks on the injected clock and emits one ``Bundle`` per tick.

    ``inputs`` maps sensor name to that sensor's frame queue; the synchronizer drains each
    queue at every tick and keeps only the newest frame (older ones are superseded, not
    dropped: they were never wanted at this rate). What each sensor runs arrives as
    messages (``on_config``, subscribed to the session's ``AppliedConfigs``); ``drivers``
    gives only each sensor's profile entry (its pairing tolerance).
    """

    def __init__(
        self,
        drivers: Mapping[str, Driver],
        inputs: Mapping[str, DropOldestQueue[Frame]],
        output: DropOldestQueue[Bundle],
        clock: Clock,
        *,
        min_rate_hz: float = 1.0,
        max_rate_hz: float = 30.0,
        window_s: float = 1.0,
        thresholds: HealthThresholds | None = None,
        phase: float = 0.5,
        on_tick: Callable[[float, float], None] | None = None,
        applied: Mapping[str, SensorConfig] | None = None,
    ) -> None:
        self.drivers = drivers
        # the start configuration; then only what on_config delivers
        self.applied: dict[str, SensorConfig] = dict(applied or {n: d.applied for n, d in drivers.items()})
        self.inputs = inputs
        self.output = output
        self.clock = clock
        self.min_rate_hz = min_rate_hz
        self.max_rate_hz = max_rate_hz
        self.window = SyncWindow(window_s, thresholds or HealthThresholds())
        self.phase = phase
        self.on_tick = on_tick  # (scheduled, actual): the session's tick hook
        self.latest: dict[str, Frame] = {}
        self.last_stats = SyncStats(0.0, 0.0, 0.0, Health.GOOD)
        self.bundles = 0

    def on_config(self, name: str, applied: SensorConfig) -> None:
        """A sensor's new configuration (rate, enabled): the next tick follows it."""
        if name in self.drivers:
            self.applied[name] = applied

    def current_rate(self) -> float:
        rates = [c.rate_hz for c in self.applied.values() if c.enabled]
        return tick_rate(rates, self.min_rate_hz, self.max_rate_hz)

    async def run(self) -> None:
        timer = TickTimer(self.clock)  # the tick to the microsecond, not the loop's millisecond
        try:
            await self._tick_forever(timer)
        finally:
            timer.close()

    async def _tick_forever(self, timer: TickTimer) -> None:
        rate = self.current_rate()
        scheduled = grid_time(self.clock.now(), rate, self.phase)
        while True:
            await timer.sleep_until(scheduled)
            actual = self.clock.now()
            if self.on_tick is not None:
                self.on_tick(scheduled, actual)
            self.tick(scheduled, actual, rate)
            new_rate = self.current_rate()
            if new_rate != rate or actual - scheduled > 1.0 / rate:
                # a new rate, or behind by a whole period: re-anchor on the grid, don't burst
                rate = new_rate
                scheduled = grid_time(actual, rate, self.phase)
            else:
                scheduled += 1.0 / rate

    def tick(self, scheduled: float, actual: float, rate: float) -> Bundle:
        """Assemble and emit the bundle for one tick (public so tests can drive it directly)."""
        self._drain()
        frames: dict[Modality, Frame] = {}
        expected = stale = 0
        for name, driver in self.drivers.items():
            applied = self.applied[name]
            if not applied.enabled:
                continue
            expected += 1
            frame = self.latest.get(name)
            limit = freshness_limit(driver.config.tolerance_ms / 1000.0, applied.rate_hz)
            if frame is None or actual - frame.t > limit or frame.t > actual + 1e-9:
                stale += 1
                continue
            frames.setdefault(frame.modality, frame)
        self.window.add(actual, actual - scheduled, expected, stale)
        self.last_stats = self.window.stats(rate)
        bundle = Bundle(t=actual, frames=frames, sync=self.last_stats, seq=self.bundles)
        self.bundles += 1
        self.output.put(bundle)
        return bundle

    def _drain(self) -> None:
        for name, queue in self.inputs.items():
            while True:
                try:
                    self.latest[name] = queue.get_nowait()
                except asyncio.QueueEmpty:
                    break
