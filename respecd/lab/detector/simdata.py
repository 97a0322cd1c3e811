"""Simulated frames for training and evaluation, rendered on demand the way the daemon sees them.

* **Alignment**: the sim-rover profile's calibration, through the same ``Aligner`` the
  perception stage builds (thermal warped by its homography, radar points projected with
  the RGB intrinsics), never a plain resize.
* **Timing**: the synchronizer hands the detector each sensor's newest frame, so the thermal
  frame (the FLIR One stops near 9 Hz) and the radar frame are up to one of their periods
  older than the RGB frame; a walker has moved in between.
* **Settings**: a training frame draws the RGB rate (exposure, motion blur), the thermal size
  (320x240 is the Lepton's 160x120 upscaled) and the radar preset and rate; an evaluation
  frame uses the profile's defaults (RGB 30 Hz, thermal 160x120 at 9 Hz, radar range at 10 Hz).

Rendering is cheap beside a training step, so training and evaluation render what they need
at any RGB resolution instead of holding a pool in memory.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from respecd.lab.detector.augment import AugmentConfig, photometric, strip
from respecd.lab.detector.data import Sample, gt_arrays
from respecd.messages import Frame
from respecd.perception.align import Aligner
from respecd.perception.config import PerceptionConfig

RESOLUTIONS = ((640, 360), (960, 540), (1280, 720))  # what the controller can choose
THERMAL_MAX_HZ, RADAR_HZ = 9.0, 10.0
# evaluation conditions -> the scenarios they pool (motion overlaps good-light and dark)
CONDITIONS: dict[str, tuple[str, ...]] = {
    "good-light": ("good-light-static", "good-light-moving"),
    "dark": ("poor-light-static", "poor-light-moving"),
    "occlusion": ("occlusion-partial",),
    "smoke": ("occlusion-smoke",),
    "radar-only": ("behind-curtain",),
    "motion": ("good-light-moving", "poor-light-moving"),
}


def condition_of(scenario: str) -> list[str]:
    return [c for c, names in CONDITIONS.items() if scenario in names]


@functools.cache
def sim_calibration() -> dict:
    """Per modality, the calibration the daemon's perception stage reads from builtin:sim-rover."""
    from respecd.config import load_profile
    from respecd.perception.stage import calibration_from_profile

    return calibration_from_profile(load_profile("builtin:sim-rover"))


@dataclass(frozen=True)
class Settings:
    """One frame's sensor settings and how stale the slower sensors' frames are."""

    rgb_rate_hz: float = 30.0
    thermal_size: tuple[int, int] = (160, 120)
    radar_mode: str = "range"
    radar_rate_hz: float = RADAR_HZ
    thermal_age_s: float = 0.0
    radar_age_s: float = 0.0

    @classmethod
    def draw(cls, rng: np.random.Generator, randomize: bool) -> Settings:
        """Random ages always (the daemon's sync gives them); random settings for training."""
        if not randomize:
            return cls(thermal_age_s=rng.uniform(0, 1 / THERMAL_MAX_HZ), radar_age_s=rng.uniform(0, 1 / RADAR_HZ))
        radar_rate = float(rng.choice([5.0, 10.0, 20.0, 30.0]))
        thermal_rate = float(rng.choice([5.0, THERMAL_MAX_HZ, THERMAL_MAX_HZ]))  # mostly the static rate
        return cls(float(rng.choice([5.0, 10.0, 15.0, 30.0])), ((160, 120), (320, 240))[int(rng.integers(2))],
                   ("range", "velocity")[int(rng.integers(2))], radar_rate,
                   rng.uniform(0, 1 / thermal_rate), rng.uniform(0, 1 / radar_rate))


class SimFrames:
    """Renders aligned, labelled samples of one seeded world (all scenarios, looping)."""

    def __init__(self, config: PerceptionConfig, seed: int, scenarios: tuple[str, ...] | None = None,
                 calibration: dict | None = None) -> None:
        from respecd.sim.world import SCENARIOS, SimulationConfig, World

        self.sim = SimulationConfig(scenarios=list(scenarios or SCENARIOS), loop=True)
        self.world = World(self.sim, seed)
        self.aligner = Aligner(config, sim_calibration() if calibration is None else calibration)

    def time_in(self, segment: int, fraction: float) -> float:
        """World time ``fraction`` (0..1) into segment ``segment`` (which runs scenario segment mod N)."""
        return (segment + fraction) * self.sim.scenario_duration_s

    def sample(self, t: float, size: tuple[int, int], rng: np.random.Generator, randomize: bool) -> Sample:
        """The detector's input and ground truth at world time ``t``, RGB at ``size``."""
        from respecd.sim.render import ground_truth, render_lepton, render_radar, render_rgb, rgb_exposure

        s = Settings.draw(rng, randomize)
        state = self.world.state_at(t)
        max_exposure = min(1.0 / s.rgb_rate_hz, self.sim.max_exposure_s)
        data = {
            "rgb": render_rgb(state, size, max_exposure, rng),
            "thermal": render_lepton(self.world.state_at(t - s.thermal_age_s), s.thermal_size, rng),
            "radar": render_radar(self.world.state_at(t - s.radar_age_s), s.radar_mode, s.radar_rate_hz, rng),
        }
        if "depth" in self.aligner.aux:
            from respecd.sim.render import render_depth

            data["depth"] = render_depth(state, (640, 480), rng)
        frames = {k: Frame(modality=k, t=t, seq=0, data=v) for k, v in data.items()}  # type: ignore[arg-type]
        aligned = self.aligner.align(frames)
        truth = ground_truth(state, size)
        boxes, ignore = gt_arrays(truth)
        seen = np.array([[g["transmission"]["rgb"], g["transmission"]["thermal"]] for g in truth],
                        np.float32).reshape(-1, 2)
        w, h = aligned.size
        exposure = rgb_exposure(state, size, max_exposure)  # the auto-exposure: how bright the scene comes out
        signal = state.light * exposure["exposure_s"] * 30.0 * exposure["gain"]  # DN out per DN of reflectance
        return Sample(np.ascontiguousarray(aligned.tensor[:, :h, :w]), aligned.presence, boxes, ignore, seen=seen,
                      meta={"scenario": state.scenario, "light": state.light, "t": t, "rgb_signal": signal})


# Training draws the hard scenarios more often than the easy ones: a static scene barely
# changes between instants, while partial occlusion and radar-only localization need examples.
SCENARIO_WEIGHTS = {"good-light-static": 0.75, "poor-light-static": 0.75, "occlusion-partial": 2.0,
                    "behind-curtain": 2.0}


def draw_resolution(rng: np.random.Generator, p: np.ndarray | None = None) -> tuple[int, int]:
    """One of the controller's RGB resolutions: uniform (``p`` None, one ``rng.integers`` draw, as
    every shipped stage drew it) or with probabilities ``p``."""
    if p is None:
        return RESOLUTIONS[int(rng.integers(len(RESOLUTIONS)))]
    return RESOLUTIONS[int(rng.choice(len(RESOLUTIONS), p=p))]


class SimStream:
    """Training batches from fresh frames: one RGB resolution per step, full-height strips.

    Each step draws one of the controller's resolutions and renders ``batch`` frames at 640x360
    (fewer at larger sizes, so a step costs about the same), ``per_segment`` instants from each
    random scenario run (the room's backgrounds are built once per run); scenarios are drawn
    with ``weights`` (default ``SCENARIO_WEIGHTS``; 1 for the others), resolutions with
    ``resolution_weights`` (default 1 each: a fine-tune can favour the size the controller runs most).
    """

    def __init__(self, frames: SimFrames, augment: AugmentConfig, batch: int, aux: tuple[str, ...],
                 strip_width: int = 320, per_segment: int = 2, weights: dict[str, float] | None = None,
                 resolution_weights: dict[tuple[int, int], float] | None = None) -> None:
        self.frames, self.augment, self.batch, self.aux = frames, augment, batch, aux
        self.strip_width, self.per_segment = strip_width, per_segment
        table = SCENARIO_WEIGHTS if weights is None else weights
        self.weights = {name: table.get(name, 1.0) for name in frames.sim.scenarios}
        drawn = np.array(list(self.weights.values()))
        self.scenario_p = drawn / drawn.sum()
        sizes = resolution_weights or {}
        self.resolution_weights = {f"{w}x{h}": sizes.get((w, h), 1.0) for w, h in RESOLUTIONS}
        drawn = np.array(list(self.resolution_weights.values()))
        # None when uniform: the draw stays rng.integers, so the shipped recipe's random stream is unchanged
        self.resolution_p = None if np.all(drawn == drawn[0]) else drawn / drawn.sum()

    def _segment(self, rng: np.random.Generator) -> int:
        """A random run of a scenario drawn by weight (segment i runs scenario i mod N)."""
        n = len(self.scenario_p)
        return int(rng.integers(0, 100_000)) * n + int(rng.choice(n, p=self.scenario_p))

    def draw(self, rng: np.random.Generator) -> tuple[list[Sample], tuple[int, int]]:
        """(samples, (width, height)) of one step."""
        size = draw_resolution(rng, self.resolution_p)
        height = math.ceil(size[1] / 32) * 32
        n = max(2, round(self.batch * 384 / height))
        out: list[Sample] = []
        while len(out) < n:
            segment = self._segment(rng)
            for _ in range(min(self.per_segment, n - len(out))):
                s = self.frames.sample(self.frames.time_in(segment, rng.uniform(0.02, 0.98)), size, rng, True)
                s = strip(s, self.strip_width, height, rng, self.augment, self.augment.zoom_for(size))
                out.append(photometric(s, rng, self.augment, self.aux))
        return out, (self.strip_width, height)
