"""Immutable messages that flow between pipeline stages.

Stages share nothing but bounded queues carrying these frozen dataclasses, so a message
can be handed to a worker thread or a recorder without copying or locking.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Literal

import numpy as np

Modality = Literal["rgb", "thermal", "radar", "depth", "imu"]
MODALITIES: tuple[Modality, ...] = ("rgb", "thermal", "radar", "depth", "imu")

Resolution = tuple[int, int]  # (width, height) in pixels
RadarMode = Literal["range", "velocity"]


class Health(str, Enum):
    """Three ordinal bins used for synchronizer health (and reused by the controller state)."""

    GOOD = "good"
    FAIR = "fair"
    POOR = "poor"


@dataclass(frozen=True, slots=True)
class Frame:
    """One sample from one sensor.

    ``data`` layouts by modality:
      rgb      uint8  (H, W, 3) BGR (OpenCV order)
      thermal  uint16 (H, W) raw counts, or float32 (H, W) kelvin when ``meta["units"] == "K"``
      depth    uint16 (H, W) millimetres
      radar    float32 (N, 5) columns x, y, z (m, y = boresight), v (m/s), snr (dB)
      imu      float32 (6,) ax, ay, az (m/s^2), gx, gy, gz (rad/s)
    ``t`` is seconds on the injected clock; ``seq`` counts frames per driver from 0.
    ``meta`` carries driver facts (``"gt"`` ground truth boxes in the simulator, ``"ffc"`` for
    FLIR flat-field frames, ``"raw"`` radar UART bytes, ...).
    """

    modality: Modality
    t: float
    seq: int
    data: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, ...]:
        """The shape of ``data`` (a replay's ``LazyFrame`` knows it before decoding its pixels)."""
        return tuple(self.data.shape)


@dataclass(frozen=True, slots=True)
class SyncStats:
    """How well the modalities in one bundle line up in time."""

    rate_hz: float  # the synchronizer's current tick rate
    jitter_ms: float  # std-dev of tick-to-tick interval error over the recent window
    stale_ratio: float  # share of expected modalities missing or too old over the window
    health: Health


@dataclass(frozen=True, slots=True)
class Bundle:
    """The newest in-tolerance frame per active modality at one synchronizer tick."""

    t: float
    frames: dict[Modality, Frame]
    sync: SyncStats
    seq: int = 0


@dataclass(frozen=True, slots=True)
class Detection:
    """One detected object in the RGB camera's pixels (its last frame's size when a bundle has none)."""

    box: tuple[float, float, float, float]  # x1, y1, x2, y2
    confidence: float
    label: str = "person"
    contributions: dict[str, float] | None = None  # per modality (rgb, thermal, ...), sums to 1


def conf_agg(confidences: Sequence[float]) -> float:
    """ConfAgg: mean of the top min(3, N) confidences, 0 when nothing is detected (PAPER.md)."""
    top = sorted(confidences, reverse=True)[:3]
    return float(sum(top) / len(top)) if top else 0.0


@dataclass(frozen=True, slots=True)
class Percept:
    """What perception made of one bundle."""

    t: float
    detections: tuple[Detection, ...]
    conf_agg: float  # mean of the top min(3, N) confidences, 0 when N == 0
    contributions: dict[str, float] | None  # scene score per modality; None when not computed
    latency: float  # seconds spent on inference (+ attribution when computed)
    bundle: Bundle | None = None  # the input, for scene statistics downstream
    # Beside the contributions, per modality, from the same attribution (None when not computed or no detection):
    dependence: dict[str, float] | None = None  # share of the detections' confidence lost with it off
    sufficiency: dict[str, float] | None = None  # share of it kept with only that modality on


@dataclass(frozen=True, slots=True)
class SensorConfig:
    """What the controller asks of a driver, and what the driver answers it applied.

    ``resolution`` applies to imaging sensors, ``mode`` to the radar. A driver that cannot
    honour a request clamps it and lists the reason in ``notes`` (never silently).
    """

    modality: Modality
    enabled: bool = True
    rate_hz: float = 30.0
    resolution: Resolution | None = None
    mode: RadarMode | None = None
    notes: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Decision:
    """One controller step, as logged and recorded."""

    t: float
    state: tuple[int, ...]  # bin index per state factor
    action: int
    reward: float
    epsilon: float
    q_values: tuple[float, ...]
    configs: tuple[SensorConfig, ...] = ()  # what the drivers really applied
    terms: dict[str, float] = field(default_factory=dict)  # reward terms, for logs
