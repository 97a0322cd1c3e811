"""Typed models of respecd's own JSON channels: one pydantic model per channel schema.

The log's JSON Schemas are generated from these (``respecd.record.schemas``), so a field
added here is described in every new log, and a test checks the encoders in
``respecd.record.events`` / ``codec`` against them. The encoders build plain dicts (the
writer thread's hot path); these models are the contract they are held to. A new channel
is a model here plus its name in ``MODELS``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Time(_Message):
    """Timestamp of the sample."""

    sec: int = Field(ge=0)
    nsec: int = Field(ge=0, le=999_999_999)


class Vector3(_Message):
    x: float
    y: float
    z: float


class Imu(_Message):
    """An IMU sample (accelerometer and gyroscope)."""

    timestamp: Time
    frame_id: str = Field(description="Frame of reference")
    linear_acceleration: Vector3 = Field(description="m/s^2")
    angular_velocity: Vector3 = Field(description="rad/s")


class RawBytes(_Message):
    """Bytes exactly as the device sent them (radar UART data port), for the live parser."""

    timestamp: Time
    frame_id: str = Field(description="Frame of reference")
    data: str = Field(description="base64", json_schema_extra={"contentEncoding": "base64"})
    respecd: dict[str, Any] = Field(description="the frame's session time t and sequence number seq")


class FrameMeta(_Message):
    """What a Foxglove sensor message cannot carry: the frame's exact session time, sequence
    number, modality and the driver's metadata (the simulator's ground truth 'gt'); written
    just before the frame, same log time."""

    t: float = Field(description="session time (s)")
    seq: int
    modality: str
    meta: dict[str, Any]


class _Applied(_Message):
    modality: str
    enabled: bool
    rate_hz: float
    resolution: list[int] | None = Field(description="width, height")
    mode: str | None
    notes: list[str] = Field(description="what the driver changed in the request, and why")


class SensorConfig(_Applied):
    """What a driver really applied."""

    t: float = Field(description="session time (s)")
    sensor: str


class Detection(_Message):
    box: list[float] = Field(description="x1, y1, x2, y2 in RGB pixels")
    confidence: float
    label: str


class Percept(_Message):
    """Detections, ConfAgg and per-modality contribution scores of one bundle."""

    t: float = Field(description="session time (s)")
    conf_agg: float
    latency_s: float
    contributions: dict[str, float] | None = Field(
        description="Per modality, normalized to sum 1: what the controller reads; null when not computed")
    dependence: dict[str, float] | None = Field(
        description="Per modality, 0..1: share of the detections' confidence lost with it off")
    sufficiency: dict[str, float] | None = Field(
        description="Per modality, 0..1: share of the detections' confidence kept with only it on")
    detections: list[Detection]
    pixels: int = Field(description="RGB pixels in the bundle (compute proxy)")


class Decision(_Message):
    """One controller step: state bins, action, reward and its terms, applied configs."""

    t: float = Field(description="session time (s)")
    state: list[int]
    action: int
    reward: float
    epsilon: float
    q_values: list[float]
    terms: dict[str, float]
    configs: list[_Applied]


class Sync(_Message):
    """Synchronizer health at one tick and which frames it paired."""

    t: float = Field(description="session time (s)")
    seq: int
    rate_hz: float
    jitter_ms: float
    stale_ratio: float
    health: Literal["good", "fair", "poor"]
    frames: dict[str, list[float]] = Field(description="modality -> [frame t, frame seq]")


MODELS: dict[str, type[BaseModel]] = {
    "respecd.Imu": Imu,
    "respecd.RawBytes": RawBytes,
    "respecd.FrameMeta": FrameMeta,
    "respecd.SensorConfig": SensorConfig,
    "respecd.Percept": Percept,
    "respecd.Decision": Decision,
    "respecd.Sync": Sync,
}
