"""What a sensor is, whichever driver runs it: the profile entry every sensor has, its
calibration and power model, its capabilities and how a request is fitted into them.

These types are shared by drivers, the controller, perception and the config; drivers
re-export them from ``respecd.drivers.base`` for driver authors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from respecd.messages import Modality, RadarMode, Resolution, SensorConfig

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


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation matrix from roll (about z, the optical axis), pitch (x) and yaw (y), degrees.

    Camera convention x right, y down, z forward: yaw turns left/right, pitch up/down. It
    maps a sensor's points into the RGB camera frame: ``p_rgb = R p_sensor + t``.
    """
    r, p, y = (math.radians(a) for a in (roll, pitch, yaw))
    rz = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    ry = np.array([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    return ry @ rx @ rz


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
