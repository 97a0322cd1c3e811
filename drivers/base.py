"""The driver contract every sensor family implements, plus the pieces they share.

A driver owns one sensor stream of one modality. The constructor does no I/O; ``start`` and
``stop`` do, and ``stop`` is idempotent. ``frames()`` yields ``Frame``s until stopped.
``apply`` takes what the controller asks for and returns what was really applied: a request
outside the capabilities is clamped and the clamp is reported in ``SensorConfig.notes``.
Blocking device calls run in worker threads (``asyncio.to_thread``), never on the loop.
"""

from __future__ import annotations

import abc
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from respecd.clock import Clock
from respecd.messages import Frame, Modality, Resolution, SensorConfig
from respecd.sensors import MAX_RATE_HZ, MIN_RATE_HZ, Capabilities, DriverConfigBase, clamp_request

# the sensor types a driver module needs, importable from the driver contract's own module
__all__ = [
    "MAX_RATE_HZ", "MIN_RATE_HZ", "Capabilities", "Decimator", "Driver", "DriverConfigBase", "DriverContext",
    "DriverHealth", "RateMeter", "clamp_request",
]


class RateMeter:
    """Measured frame rate over a sliding window of frame times."""

    def __init__(self, window: int = 30) -> None:
        self._times: deque[float] = deque(maxlen=window)

    def tick(self, t: float) -> None:
        self._times.append(t)

    @property
    def rate_hz(self) -> float:
        if len(self._times) < 2:
            return 0.0
        span = self._times[-1] - self._times[0]
        return (len(self._times) - 1) / span if span > 0 else 0.0


class Decimator:
    """Lets frames through at most at ``rate_hz`` from a faster native stream."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = rate_hz
        self._next_t: float | None = None

    def accept(self, t: float) -> bool:
        period = 1.0 / self.rate_hz
        if self._next_t is None or t >= self._next_t - 0.25 * period:
            # schedule from the ideal grid, not from t, so the average rate is exact
            base = t if self._next_t is None or t - self._next_t > period else self._next_t
            self._next_t = base + period
            return True
        return False


@dataclass(frozen=True)
class DriverContext:
    """What a driver may need beyond its own profile entry.

    ``simulation`` is the profile's ``simulation:`` section (simulated drivers build their
    shared, seeded world from it); ``replay`` is an opened session log for replay drivers,
    and ``decode_ahead`` names the modalities whose every frame's pixels will be read (no
    detector: the controller's features read each RGB and thermal frame), so their read-ahead
    threads decode them too (else a frame is decoded when something first reads its pixels,
    and a depth frame nobody reads is never decoded).
    """

    seed: int = 0
    simulation: Any = None
    replay: Any = None
    decode_ahead: frozenset[str] = frozenset()


@dataclass
class DriverHealth:
    """Counters shown in the status line and logs."""

    frames: int = 0
    drops: int = 0
    errors: int = 0
    restarts: int = 0
    last_error: str | None = None
    paused: bool = False  # e.g. the radar between sensorStop and sensorStart
    meter: RateMeter = field(default_factory=RateMeter)
    resolution: Resolution | None = None  # measured: the last image frame's (width, height)

    def frame(self, t: float, shape: tuple[int, ...] | None = None) -> None:
        """Count a frame at ``t``; an image's ``shape`` (H, W[, C]) also records the delivered size."""
        self.frames += 1
        self.meter.tick(t)
        if shape is not None and len(shape) >= 2:
            self.resolution = (int(shape[1]), int(shape[0]))

    def error(self, err: BaseException | str) -> None:
        self.errors += 1
        self.last_error = str(err)


class Driver(abc.ABC):
    """One sensor stream. Subclasses set ``key`` (the YAML ``driver:`` value)."""

    key: ClassVar[str]
    _announce: Callable[[], None] | None = None  # set by announce_changes
    # frames() returned because the stream ended by itself (a video file or recording played to
    # its end without loop), not through stop() or an error: a normal end, not a failure
    finished: bool = False

    def __init__(self, config: DriverConfigBase, clock: Clock, context: DriverContext | None = None) -> None:
        self.config = config
        self.clock = clock
        self.context = context or DriverContext()
        self.name = config.name
        self.modality: Modality = config.modality
        self.health = DriverHealth()
        self.applied = config.initial_request()

    @property
    def applied(self) -> SensorConfig:
        """What the device runs now: the answer to the last ``apply``, or what the device itself
        turned out to run (a camera that negotiated another mode at start, a FLIR One reporting its
        real frame size, a radar recovering to its last good profile)."""
        return self._applied

    @applied.setter
    def applied(self, value: SensorConfig) -> None:
        changed = value != getattr(self, "_applied", None)
        self._applied = value
        if changed and self._announce is not None:
            self._announce()

    def announce_changes(self, callback: Callable[[], None] | None) -> None:
        """Have ``callback()`` called, from whichever thread set it, each time ``applied`` changes.

        The session publishes the new value to everyone who follows configurations; without
        this, a change the device made on its own would stay inside the driver.
        """
        self._announce = callback

    @property
    @abc.abstractmethod
    def capabilities(self) -> Capabilities:
        """What the device supports (may be refined once ``start`` has talked to it)."""

    @abc.abstractmethod
    async def start(self) -> None:
        """Open the device and begin streaming; raise DriverUnavailableError to be retried."""

    @abc.abstractmethod
    async def stop(self) -> None:
        """Stop streaming and release the device. Safe to call twice or before start."""

    @abc.abstractmethod
    def frames(self) -> AsyncIterator[Frame]:
        """Frames as they arrive, until ``stop``. The supervisor counts them in ``health``."""

    @abc.abstractmethod
    async def apply(self, request: SensorConfig) -> SensorConfig:
        """Reconfigure; return what was really applied (clamped, with notes)."""

    async def __aenter__(self) -> Driver:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()
