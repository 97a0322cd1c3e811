"""Perception latency for lockstep replay, modelled from the log instead of measured.

The controller's load factor and its latency penalty read perception latency. Measured on
the replaying machine, it would make two replays of one log decide differently; modelled,
it is a function of the log and the counterfactual alone. The model is seconds per RGB
pixel (the detector is fully convolutional, so its cost follows the RGB resolution),
fitted as the median over the log's recorded percepts, separately for percepts with
attribution (a backward pass costs a few forward passes) and without.
"""

from __future__ import annotations

import dataclasses
import statistics
from collections.abc import Iterable
from typing import Any

from respecd.messages import Bundle, Percept

# Used only when the log recorded no percepts: the fusion detector's forward + NMS at 640x360
# took 94 ms of CPU time (one torch thread) on the 2-core x86-64 development machine,
# 0.094 s / 0.2304 Mpx = 0.41 s per megapixel (docs/PERFORMANCE.md, "record and replay").
DEFAULT_S_PER_MPIX = 0.41
ATTRIBUTION_FACTOR = 3.0  # DESIGN.md: a backward pass costs about 2-3 forward passes on a CPU


@dataclasses.dataclass
class LatencyModel:
    s_per_pixel: float = DEFAULT_S_PER_MPIX / 1e6
    s_per_pixel_attributed: float = ATTRIBUTION_FACTOR * DEFAULT_S_PER_MPIX / 1e6
    source: str = "default"
    last_pixels: int = 0  # a bundle without RGB still runs the network at the last RGB size

    @classmethod
    def from_log(cls, session: Any) -> LatencyModel:
        return cls.from_percepts(session.json_messages("/respecd/percept"))

    @classmethod
    def from_percepts(cls, percepts: Iterable[dict[str, Any]]) -> LatencyModel:
        """Fit from recorded ``respecd.Percept`` messages (default model when there are none)."""
        plain: list[float] = []
        attributed: list[float] = []
        for msg in percepts:
            pixels = int(msg.get("pixels") or 0)
            if pixels > 0 and float(msg.get("latency_s") or 0.0) > 0.0:  # 0: no detector ran (passthrough)
                (attributed if msg.get("contributions") else plain).append(float(msg["latency_s"]) / pixels)
        if not plain and not attributed:
            return cls()
        base = statistics.median(plain) if plain else statistics.median(attributed) / ATTRIBUTION_FACTOR
        heavy = statistics.median(attributed) if attributed else base * ATTRIBUTION_FACTOR
        return cls(base, heavy, "log")

    def predict(self, bundle: Bundle | None, attributed: bool) -> float:
        """The modelled latency of running the detector on ``bundle`` (known before it runs)."""
        rgb = bundle.frames.get("rgb") if bundle is not None else None
        if rgb is not None and len(rgb.shape) >= 2:
            self.last_pixels = int(rgb.shape[0] * rgb.shape[1])
        return self.last_pixels * (self.s_per_pixel_attributed if attributed else self.s_per_pixel)

    def latency(self, percept: Percept) -> float:
        return self.predict(percept.bundle, percept.contributions is not None)

    def apply(self, percept: Percept) -> Percept:
        return dataclasses.replace(percept, latency=self.latency(percept))
