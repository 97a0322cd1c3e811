"""From percepts to an ``Observation``: per-percept scene features and the sliding window.

Features are cheap on purpose (they run on the event loop for every percept): images are
read as fixed block grids (``imagestats``), so the cost does not depend on the resolution
the controller chose.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from respecd.control.imagestats import BlockSampler, MotionMeter, spread
from respecd.control.state import Observation
from respecd.errors import UndecodableImageError
from respecd.messages import Frame, Health, Modality, Percept

REFERENCE_FPS = 30.0  # illumination is normalised to a 1/30 s exposure at gain 1
IMAGE_FEATURE_MODALITIES = frozenset({"rgb", "thermal"})  # the imagers whose pixels ``_images`` reads
_HEALTH_LEVEL = {Health.GOOD: 0, Health.FAIR: 1, Health.POOR: 2}


@dataclass(frozen=True, slots=True)
class Sample:
    """What one percept contributes to the window."""

    t: float
    conf_agg: float
    latency_s: float
    luminance: float | None = None
    motion_image: float | None = None
    gyro: float | None = None
    radar_points: float | None = None
    sync_level: int | None = None
    contributions: dict[str, float] | None = None
    truth_quality: float | None = None  # training only: F1 of the boxes against the simulator's ground truth


class FeatureExtractor:
    """Turns percepts into samples; keeps the last block grid per imager for motion."""

    def __init__(self) -> None:
        self._sampler = BlockSampler()
        self._motion = {"rgb": MotionMeter(), "thermal": MotionMeter()}
        self._last_blocks: dict[str, tuple[tuple[int, tuple[int, ...]], np.ndarray]] = {}

    def sample(self, percept: Percept, received_t: float | None = None) -> Sample:
        """Features of one percept, stamped ``received_t`` (when the controller got it; the
        window is "percepts received in the last window_s", so a slow detector's old
        percepts still count) or the percept's own time."""
        luminance = motion = gyro = points = level = None
        bundle = percept.bundle
        if bundle is not None:
            level = _HEALTH_LEVEL.get(bundle.sync.health, 2)
            luminance, motion = self._images(bundle.frames)
            imu = bundle.frames.get("imu")
            if imu is not None and imu.data.size >= 6:
                gyro = float(np.linalg.norm(imu.data[3:6]))
            radar = bundle.frames.get("radar")
            if radar is not None:
                points = float(radar.data.shape[0])
        contributions = dict(percept.contributions) if percept.contributions else None
        t = percept.t if received_t is None else received_t
        return Sample(t, percept.conf_agg, percept.latency, luminance, motion, gyro, points, level, contributions)

    def _images(self, frames: Mapping[Modality, Frame]) -> tuple[float | None, float | None]:
        """Illumination from RGB; motion as the larger score of RGB and thermal (in the dark
        the RGB noise hides a walking person that the thermal camera still sees)."""
        luminance, scores = None, []
        rgb = frames.get("rgb")
        blocks = self._blocks(rgb)
        if rgb is not None and blocks is not None:
            luminance = scene_light(float(blocks.mean()), rgb.meta)
            scores.append(self._motion["rgb"].update(rgb.seq, rgb.shape, blocks))
        thermal = frames.get("thermal")
        blocks = self._blocks(thermal)
        if thermal is not None and blocks is not None:
            motion = self._motion["thermal"]
            if not motion.seen(thermal.seq, thermal.shape):
                scores.append(motion.update(thermal.seq, thermal.shape, blocks, spread(blocks)))
        known = [s for s in scores if s is not None]
        return luminance, (max(known) if known else None)

    def _blocks(self, frame: Frame | None) -> np.ndarray | None:
        """Block means of the frame; a frame already sampled (a slow camera sits in several
        bundles) is not read again. None without a frame, or for a logged image whose bytes do
        not decode (as if it never came: the perception stage says so)."""
        if frame is None:
            return None
        key = (frame.seq, frame.shape)
        last = self._last_blocks.get(frame.modality)
        if last is not None and last[0] == key:
            return last[1]
        try:
            pixels = frame.data
        except UndecodableImageError:
            return None
        blocks = self._sampler.blocks(pixels)
        self._last_blocks[frame.modality] = (key, blocks)
        return blocks


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
        self, now: float, cpu: float | None = None, gpu: float | None = None, power_w: float | None = None,
        busy: float | None = None,
    ) -> Observation:
        """Average the window ending at ``now``; ``cpu``/``gpu`` are shares 0..1; ``busy``
        replaces the detector busy share the samples add up to (a trainer that scores a few
        instants per window knows the share of every inference the window really held)."""
        while self._samples and self._samples[0].t <= now - self.window_s:
            self._samples.popleft()
        s = list(self._samples)
        latency = _mean([x.latency_s for x in s]) or 0.0
        if busy is None:
            busy = sum(x.latency_s for x in s) / self.window_s
        load = max(cpu or 0.0, gpu or 0.0, min(latency / self.latency_budget_s, 1.0))
        levels = [x.sync_level for x in s if x.sync_level is not None]
        return Observation(
            t=now,
            n_percepts=len(s),
            illumination=self._scene("luminance", [x.luminance for x in s if x.luminance is not None]),
            motion_image=self._scene("motion_image", [x.motion_image for x in s if x.motion_image is not None]),
            motion_imu=self._scene("gyro", [x.gyro for x in s if x.gyro is not None]),
            radar_points=self._scene("radar_points", [x.radar_points for x in s if x.radar_points is not None]),
            load=load,
            latency_s=latency,
            busy=busy,
            sync=_mean(levels) if levels else 0.0,  # type: ignore[arg-type]
            conf_agg=_mean([x.conf_agg for x in s]) or 0.0,
            truth_quality=_mean([x.truth_quality for x in s if x.truth_quality is not None]),
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
