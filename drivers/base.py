"""The driver contract every sensor family implements, plus the pieces they share.

A driver owns one sensor stream of one modality. The constructor does no I/O; ``start`` and
``stop`` do, and ``stop`` is idempotent. ``frames()`` yields ``Frame``s until stopped.
``apply`` takes what the controller asks for and returns what was really applied: a request
outside the capabilities is clamped and the clamp is reported in ``SensorConfig.notes``.
Blocking device calls run in worker threads (``asyncio.to_thread``), never on the loop.
"""

from __future__ import annotations

import abc
import math
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field

from respecd.clock import Clock
from respecd.messages import Frame, Modality, RadarMode, Resolution, SensorConfig

MIN_RATE_HZ = 1.0  # never zero: a sensor must be able to prove useful again (PAPER.md)
MAX_RATE_HZ = 30.0


class StrictModel(BaseModel):
    """Base of every profile model: unknown keys are errors, typos never pass silently."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Intrinsics(StrictModel):
    fx: float = Field(description="Focal length x (pixels).", gt=0)
    fy: float = Field(description="Focal length y (pixels).", gt=0)
    cx: float = Field(description="Principal point x (pixels).")
    cy: float = Field(description="Principal point y (pixels).")
    width: int = Field(description="Image width the intrinsics were calibrated at.", gt=0)
    height: int = Field(description="Image height the intrinsics were calibrated at.", gt=0)


class Extrinsics(StrictModel):
    rotation_rpy_deg: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="Roll, pitch, yaw (degrees) from this sensor to the RGB camera frame."
    )
    translation_m: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="Position of this sensor in the RGB camera frame (metres, x right, y down, z forward).",
    )


class Calibration(StrictModel):
    intrinsics: Intrinsics | None = Field(None, description="Pinhole intrinsics; absent for radar.")
    extrinsics: Extrinsics = Field(Extrinsics(), description="Pose relative to the RGB camera.")


class SensorPower(StrictModel):
    """Per-sensor power model used when the board has no power rails to read."""

    static_w: float = Field(0.0, ge=0, description="Watts drawn while enabled, at any rate.")
    per_hz_w: dict[str, float] = Field(
        default_factory=dict,
        description="Watts per Hz of sampling, keyed by resolution 'WxH' or radar mode; key 'default' otherwise.",
    )

    def watts(self, config: SensorConfig) -> float:
        if not config.enabled:
            return 0.0
        key = "default"
        if config.resolution is not None:
            key = f"{config.resolution[0]}x{config.resolution[1]}"
        elif config.mode is not None:
            key = config.mode
        per_hz = self.per_hz_w.get(key, self.per_hz_w.get("default", 0.0))
        return self.static_w + per_hz * config.rate_hz


class DriverConfigBase(StrictModel):
    """Settings every sensor entry in a profile has; each driver adds its own."""

    driver: str
    name: str = Field(description="Unique sensor name, used in logs and the status line.")
    modality: Modality = Field(description="What this sensor's frames are.")
    enabled: bool = Field(True, description="Start with the sensor on.")
    rate_hz: float = Field(30.0, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, description="Initial sampling rate (Hz).")
    resolution: Resolution | None = Field(None, description="Initial resolution [width, height] for imaging sensors.")
    mode: RadarMode | None = Field(None, description="Initial radar preference: range or velocity.")
    tolerance_ms: float = Field(
        150.0, gt=0, le=2000, description="Oldest frame age (ms) the synchronizer still pairs with a tick."
    )
    calibration: Calibration | None = Field(None, description="Intrinsics/extrinsics relative to the RGB camera.")
    power: SensorPower = Field(SensorPower(), description="Power model used when no power rails are readable.")

    def initial_request(self) -> SensorConfig:
        return SensorConfig(
            modality=self.modality,
            enabled=self.enabled,
            rate_hz=self.rate_hz,
            resolution=tuple(self.resolution) if self.resolution else None,  # type: ignore[arg-type]
            mode=self.mode,
        )


@dataclass(frozen=True, slots=True)
class Capabilities:
    """What the device really supports. Resolutions and rates are listed best first."""

    modality: Modality
    resolutions: tuple[Resolution, ...] = ()
    modes: tuple[RadarMode, ...] = ()
    min_rate_hz: float = MIN_RATE_HZ
    max_rate_hz: float = MAX_RATE_HZ
    upscaled: tuple[Resolution, ...] = ()  # offered resolutions produced by interpolation


def clamp_request(caps: Capabilities, request: SensorConfig) -> SensorConfig:
    """Fit a request into the capabilities, saying in ``notes`` what had to change."""
    notes: list[str] = []
    rate = request.rate_hz
    if not math.isfinite(rate) or rate < caps.min_rate_hz:
        notes.append(f"rate {rate:g} Hz raised to {caps.min_rate_hz:g} Hz")
        rate = caps.min_rate_hz
    elif rate > caps.max_rate_hz:
        notes.append(f"rate {rate:g} Hz capped at {caps.max_rate_hz:g} Hz")
        rate = caps.max_rate_hz
    resolution = request.resolution
    if caps.resolutions:
        if resolution is None or tuple(resolution) not in caps.resolutions:
            nearest = _nearest_resolution(caps.resolutions, resolution)
            if resolution is not None:
                notes.append(f"resolution {resolution[0]}x{resolution[1]} unsupported, using {nearest[0]}x{nearest[1]}")
            resolution = nearest
        if resolution in caps.upscaled:
            notes.append(f"{resolution[0]}x{resolution[1]} is upscaled from the native resolution")
    else:
        resolution = None
    mode = request.mode
    if caps.modes:
        if mode not in caps.modes:
            if mode is not None:
                notes.append(f"mode {mode} unsupported, using {caps.modes[0]}")
            mode = caps.modes[0]
    else:
        mode = None
    return replace(request, rate_hz=rate, resolution=resolution, mode=mode, notes=tuple(notes))


def _nearest_resolution(options: tuple[Resolution, ...], wanted: Resolution | None) -> Resolution:
    if wanted is None:
        return options[0]
    area = wanted[0] * wanted[1]
    return min(options, key=lambda r: abs(r[0] * r[1] - area))


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
    shared, seeded world from it); ``replay`` is an opened session log for replay drivers.
    """

    seed: int = 0
    simulation: Any = None
    replay: Any = None


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

    def frame(self, t: float, image: Any = None) -> None:
        """Count a frame at ``t``; ``image`` (H, W[, C]) also records the delivered size."""
        self.frames += 1
        self.meter.tick(t)
        if image is not None and image.ndim >= 2:
            self.resolution = (int(image.shape[1]), int(image.shape[0]))

    def error(self, err: BaseException | str) -> None:
        self.errors += 1
        self.last_error = str(err)


class Driver(abc.ABC):
    """One sensor stream. Subclasses set ``key`` (the YAML ``driver:`` value)."""

    key: ClassVar[str]

    def __init__(self, config: DriverConfigBase, clock: Clock, context: DriverContext | None = None) -> None:
        self.config = config
        self.clock = clock
        self.context = context or DriverContext()
        self.name = config.name
        self.modality: Modality = config.modality
        self.health = DriverHealth()
        self.applied: SensorConfig = config.initial_request()

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
