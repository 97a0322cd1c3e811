"""From percepts to an ``Observation``: per-percept scene features and the sliding window.

Features are cheap on purpose (they run on the event loop for every percept): images are
read on a fixed 18×32 grid of sample points, so the cost does not depend on the resolution
the controller chose, and two frames of different resolutions still compare point by
point for the frame difference.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from respecd.control.state import Observation
from respecd.messages import Frame, Health, Percept

GRID = (18, 32)  # sample points (rows, cols) per image
REFERENCE_FPS = 30.0  # illumination is normalised to a 1/30 s exposure at gain 1
_HEALTH_LEVEL = {Health.GOOD: 0, Health.FAIR: 1, Health.POOR: 2}
_BGR_LUMA = np.array([0.114, 0.587, 0.299], dtype=np.float32) / 255.0  # Rec. 601, BGR order


@dataclass(frozen=True, slots=True)
class Sample:
    """What one percept contributes to the window."""

    t: float
    conf_agg: float
    latency_s: float
    luminance: float | None = None
    frame_diff: float | None = None
    gyro: float | None = None
    radar_points: float | None = None
    sync_level: int | None = None
    contributions: dict[str, float] | None = None


class FeatureExtractor:
    """Turns percepts into samples; remembers the last luminance grid for differencing."""

    def __init__(self) -> None:
        self._grids: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._last_luma: np.ndarray | None = None
        self._last_seq: int | None = None

    def sample(self, percept: Percept) -> Sample:
        luminance = frame_diff = gyro = points = level = None
        bundle = percept.bundle
        if bundle is not None:
            level = _HEALTH_LEVEL.get(bundle.sync.health, 2)
            rgb = bundle.frames.get("rgb")
            if rgb is not None:
                luminance, frame_diff = self._luma(rgb)
                luminance = scene_light(luminance, rgb.meta)
            imu = bundle.frames.get("imu")
            if imu is not None and imu.data.size >= 6:
                gyro = float(np.linalg.norm(imu.data[3:6]))
            radar = bundle.frames.get("radar")
            if radar is not None:
                points = float(radar.data.shape[0])
        contributions = dict(percept.contributions) if percept.contributions else None
        return Sample(
            percept.t, percept.conf_agg, percept.latency, luminance, frame_diff, gyro, points, level, contributions
        )

    def _luma(self, frame: Frame) -> tuple[float, float | None]:
        image = frame.data
        rows, cols = self._grid(image.shape[0], image.shape[1])
        points = image[rows, cols]  # (18, 32, 3) uint8 BGR, or (18, 32) for grey
        luma = points @ _BGR_LUMA if points.ndim == 3 else points.astype(np.float32) / 255.0
        diff = None
        # the same frame can sit in several bundles (slow camera): differencing it would read "still"
        if self._last_luma is not None and frame.seq != self._last_seq:
            diff = float(np.abs(luma - self._last_luma).mean())
        if frame.seq != self._last_seq:
            self._last_luma, self._last_seq = luma, frame.seq
        return float(luma.mean()), diff

    def _grid(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        key = (height, width)
        if key not in self._grids:
            rows = np.linspace(0, height - 1, GRID[0]).round().astype(np.intp)
            cols = np.linspace(0, width - 1, GRID[1]).round().astype(np.intp)
            self._grids[key] = (rows[:, None], cols[None, :])
        return self._grids[key]


def scene_light(luminance: float, meta: dict) -> float:
    """Mean luminance as it would be at a 1/30 s exposure and unity gain, 0..1.

    Auto-exposure hides the dark: a camera at 5 Hz exposes up to 200 ms and returns a frame
    as bright as in daylight. When the frame says how it was exposed (``exposure_s``,
    ``gain`` in its meta, as the simulator and UVC drivers report), undo that.
    """
    exposure, gain = meta.get("exposure_s"), meta.get("gain")
    if not exposure or not gain:
        return luminance
    return min(luminance / (float(exposure) * REFERENCE_FPS * float(gain)), 1.0)


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


class Window:
    """Samples of the last ``window_s`` seconds; scene signals missing from the window keep
    their last known value (a 1 Hz camera must not flip the state to 'unknown')."""

    def __init__(self, window_s: float, latency_budget_s: float) -> None:
        self.window_s = window_s
        self.latency_budget_s = latency_budget_s
        self._samples: deque[Sample] = deque()
        self._last_scene: dict[str, float | None] = {}
        self._last_contributions: dict[str, float] | None = None

    def add(self, sample: Sample) -> None:
        self._samples.append(sample)

    def __len__(self) -> int:
        return len(self._samples)

    def observe(
        self, now: float, cpu: float | None = None, gpu: float | None = None, power_w: float | None = None
    ) -> Observation:
        """Average the window ending at ``now``; ``cpu``/``gpu`` are shares 0..1."""
        while self._samples and self._samples[0].t <= now - self.window_s:
            self._samples.popleft()
        s = list(self._samples)
        latency = _mean([x.latency_s for x in s]) or 0.0
        load = max(cpu or 0.0, gpu or 0.0, min(latency / self.latency_budget_s, 1.0))
        levels = [x.sync_level for x in s if x.sync_level is not None]
        return Observation(
            t=now,
            n_percepts=len(s),
            illumination=self._scene("luminance", [x.luminance for x in s if x.luminance is not None]),
            motion_image=self._scene("frame_diff", [x.frame_diff for x in s if x.frame_diff is not None]),
            motion_imu=self._scene("gyro", [x.gyro for x in s if x.gyro is not None]),
            radar_points=self._scene("radar_points", [x.radar_points for x in s if x.radar_points is not None]),
            load=load,
            latency_s=latency,
            sync=_mean(levels) if levels else 0.0,  # type: ignore[arg-type]
            conf_agg=_mean([x.conf_agg for x in s]) or 0.0,
            contributions=self._contributions(s),
            power_w=power_w,
        )

    def _scene(self, key: str, values: list[float]) -> float | None:
        if values:
            self._last_scene[key] = sum(values) / len(values)
        return self._last_scene.get(key)

    def _contributions(self, samples: list[Sample]) -> dict[str, float] | None:
        # attribution runs about once per window, so a window may hold none: keep the last
        scored = [x.contributions for x in samples if x.contributions]
        if scored:
            keys = {k for c in scored for k in c}
            self._last_contributions = {k: sum(c.get(k, 0.0) for c in scored) / len(scored) for k in keys}
        return self._last_contributions
