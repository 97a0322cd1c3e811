"""One accelerator, as in the daemon: the detector as a single server behind a drop-oldest queue.

The daemon's synchronizer emits a bundle at every tick (its rate is the fastest enabled
sensor's, clamped to ``sync``'s range; on the grid ``(k + tick_phase) / rate``), onto a
``DropOldestQueue`` of ``sync.bundle_queue`` bundles; perception takes the oldest, skips it
when none of the detector's inputs brings a frame it has not seen, and otherwise runs the
detector on it — one inference at a time, on one accelerator, for as long as the latency
table says for that bundle's RGB size (plain, or attributed: the first bundle taken after
the controller asks). While it runs, ticks queue up and the oldest are dropped. A percept is
delivered when its inference ends, and it stays the newest result until the next one ends:
what the daemon would hand on at any instant is the last delivered percept, however stale.

``Accelerator`` replays exactly that on the rollout's lockstep clock, arithmetically (no
detector runs here): ``advance(t)`` processes every tick before ``t`` and every completion at
or before it; ``close_window(t)`` gives the busy share of the window ending at ``t`` (at most
1: one accelerator), the bundles dropped and the inferences run in it.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from respecd.lab.experiment.frames import frame_time
from respecd.lab.experiment.latency import Latency
from respecd.messages import SensorConfig
from respecd.sync import grid_time

InputKey = tuple[Any, ...]


@dataclass(frozen=True, slots=True)
class Bundle:
    """What the synchronizer emitted at one tick: the newest frame of every running sensor."""

    t: float  # rollout time of the tick
    source: Any  # whatever the caller needs to render it again (the piece run: world, offset)
    local_t: float  # time inside the piece (the frames' clock)
    configs: Mapping[str, SensorConfig]  # by modality, what ran at the tick
    inputs: InputKey  # identity of the detector inputs' newest frames (the daemon's new-input check)

    @property
    def resolution(self) -> tuple[int, int]:
        res = self.configs["rgb"].resolution
        assert res is not None, "the RGB camera always has a resolution"
        return (int(res[0]), int(res[1]))


@dataclass(frozen=True, slots=True)
class Inference:
    """One detector run: the bundle it took, when it started and ended, whether it attributed."""

    bundle: Bundle
    start: float
    end: float
    attributed: bool

    @property
    def service_s(self) -> float:
        return self.end - self.start


@dataclass(frozen=True, slots=True)
class WindowLoad:
    """The accelerator over one decision window."""

    busy: float  # busy share, 0..1
    dropped: int  # bundles the full queue dropped
    inferences: int  # inferences started


class Accelerator:
    """The detector as one server: ticks in, inferences out, on the caller's clock."""

    def __init__(self, latency: Mapping[tuple[int, int], Latency], inputs: tuple[str, ...], queue_size: int,
                 tick_phase: float = 0.5, min_rate_hz: float = 1.0, max_rate_hz: float = 30.0) -> None:
        self.latency = latency
        self.inputs = inputs
        self.queue: deque[Bundle] = deque()
        self.queue_size = queue_size
        self.phase = tick_phase
        self.min_rate_hz, self.max_rate_hz = min_rate_hz, max_rate_hz
        self.delivered: Inference | None = None  # the newest finished inference
        self.dropped = 0
        self.skipped = 0  # bundles taken without a new detector input
        self.started = 0
        self._running: Inference | None = None
        self._history: deque[Inference] = deque()  # inferences that may overlap the open window
        self._attributed: list[Inference] = []  # finished attributed inferences nobody has read yet
        self._window_services: list[float] = []
        self._attribute_next = True  # perception attributes its first bundle
        self._last_inputs: InputKey | None = None
        self._source: Any = None
        self._offset = 0.0
        self._configs: Mapping[str, SensorConfig] = {}
        self._rate = min_rate_hz
        self._next_tick = math.inf
        self._window_start = 0.0
        self._closed = (0, 0)  # dropped, started at the last window's close

    def configure(self, now: float, source: Any, offset: float, configs: Mapping[str, SensorConfig],
                  rates: list[float]) -> None:
        """From ``now`` on the sensors run ``configs`` (by modality) on piece ``source`` (starting
        at ``offset``); ``rates``: every enabled sensor's rate, which sets the tick rate."""
        self.advance(now)
        self._source, self._offset, self._configs = source, offset, dict(configs)
        self._rate = min(max(max(rates, default=self.min_rate_hz), self.min_rate_hz), self.max_rate_hz)
        self._next_tick = grid_time(now - 1e-9, self._rate, self.phase)

    def request_attribution(self) -> None:
        """The controller closed a window: the next bundle taken is attributed."""
        self._attribute_next = True

    def advance(self, until: float) -> None:
        """Every completion at or before ``until`` and every tick before it, in time order."""
        while True:
            done = self._running.end if self._running is not None else math.inf
            if done <= until and done <= self._next_tick:
                self._finish(done)
            elif self._next_tick < until:
                self._tick(self._next_tick)
                self._next_tick += 1.0 / self._rate
            else:
                return

    def close_window(self, now: float, period: float) -> WindowLoad:
        """The window ``[now - period, now)``: busy share, drops and inferences; opens the next."""
        self.advance(now)
        start = now - period
        running = [self._running] if self._running is not None else []
        busy = sum(max(0.0, min(i.end, now) - max(i.start, start)) for i in (*self._history, *running))
        while self._history and self._history[0].end <= now:
            self._history.popleft()
        dropped, started = self._closed
        self._closed = (self.dropped, self.started)
        self._window_start = now
        self._window_services = []
        return WindowLoad(min(busy / period, 1.0), self.dropped - dropped, self.started - started)

    def take_attributed(self) -> list[Inference]:
        """Attributed inferences finished since the last call (their contributions reach the controller)."""
        out, self._attributed = self._attributed, []
        return out

    def mean_latency_s(self) -> float | None:
        """Mean inference time of the open window so far (what the daemon's window averages)."""
        services = self._window_services or ([self.delivered.service_s] if self.delivered else [])
        return sum(services) / len(services) if services else None

    def _tick(self, t: float) -> None:
        local = t - self._offset
        inputs = tuple((m, c.resolution, c.mode, frame_time(local, c.rate_hz)) for m, c in self._configs.items()
                       if m in self.inputs and c.enabled)
        self.queue.append(Bundle(t, self._source, local, self._configs, (id(self._source), inputs)))
        if len(self.queue) > self.queue_size:
            self.queue.popleft()
            self.dropped += 1
        if self._running is None:
            self._start(t)

    def _start(self, now: float) -> None:
        """Take bundles, oldest first, until one brings a new input; run the detector on it."""
        while self.queue:
            bundle = self.queue.popleft()
            if bundle.inputs == self._last_inputs:
                self.skipped += 1
                continue
            self._last_inputs = bundle.inputs
            attributed, self._attribute_next = self._attribute_next, False
            lat = self.latency[bundle.resolution]
            self._running = Inference(bundle, now, now + (lat.attribution_s if attributed else lat.forward_s),
                                      attributed)
            self._history.append(self._running)
            self.started += 1
            return

    def _finish(self, now: float) -> None:
        done, self._running = self._running, None
        assert done is not None
        self.delivered = done
        self._window_services.append(done.service_s)
        if done.attributed:
            self._attributed.append(done)
        self._start(now)
