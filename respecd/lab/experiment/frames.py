"""What the simulated sensors deliver at one scene instant under one configuration.

A sensor running at ``r`` Hz delivers frames on the grid k / r of world time (as
``drivers/sim.py`` does), so at instant ``t`` the newest frame of that sensor is from
``floor(t * r) / r``: a slow sensor hands the detector a stale view of a moving scene, and
that staleness is part of what a low rate costs. The RGB exposure is capped at one frame
period (as the simulated driver does), so a slow RGB camera blurs more in the dark.

A frame is identified by (modality, setting, frame time); its noise comes from a generator
seeded with (world seed, modality, frame time in microseconds), so the same frame is the
same array wherever and whenever it is rendered — the property the outcome cache relies on.

In a static scenario (nobody walks, the rover stands) the scene is the same at every
instant and frames differ only in sensor noise. There a frame is identified by a *noise
slot* instead of its time: instant ``k`` of the run uses slot ``k mod NOISE_SLOTS``, so the
detector sees ``NOISE_SLOTS`` noise realizations per setting, each reused across the run
(a static scene's outcome does not depend on when it is looked at, only on the noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from respecd.messages import MODALITIES, Frame, SensorConfig
from respecd.sim.render import (
    ground_truth,
    render_depth,
    render_imu,
    render_lepton,
    render_radar,
    render_rgb,
    rgb_exposure,
)
from respecd.sim.world import World

NOISE_SLOTS = 4


def frame_time(t: float, rate_hz: float) -> float:
    """Time stamp of the newest frame at ``t`` of a sensor on the grid k / rate."""
    return math.floor(t * rate_hz + 1e-9) / rate_hz


def _micros(t: float) -> int:
    return int(round(t * 1e6))


@dataclass(frozen=True, slots=True)
class FrameId:
    """Everything a rendered frame depends on besides the world."""

    modality: str
    t_us: int  # frame time, microseconds of world time
    resolution: tuple[int, int] | None
    mode: str | None
    rate_hz: float  # RGB: sets the exposure cap; radar: sets the chirp loops

    def key(self) -> str:
        setting = f"{self.resolution[0]}x{self.resolution[1]}" if self.resolution else (self.mode or "-")
        return f"{self.modality}:{setting}@{self.rate_hz:g}:{self.t_us}"


def frame_id(config: SensorConfig, t: float, slot: int | None = None) -> FrameId:
    """The frame a sensor in ``config`` delivers as its newest at instant ``t``.

    ``slot``: the noise slot in a static scene (the frame time is then irrelevant).
    """
    t_us = -1 - slot % NOISE_SLOTS if slot is not None else _micros(frame_time(t, config.rate_hz))
    rate = config.rate_hz if config.modality in ("rgb", "radar") else 0.0
    res = tuple(config.resolution) if config.resolution is not None else None
    return FrameId(config.modality, t_us, res, config.mode, rate)  # type: ignore[arg-type]


def previous(fid: FrameId, rate_hz: float) -> FrameId:
    """The frame before ``fid`` on the same sensor (for the image-difference motion cue)."""
    if fid.t_us < 0:  # static scene: the previous frame is another noise realization
        t_prev = -1 - (-fid.t_us) % NOISE_SLOTS
    else:
        t_prev = max(0, fid.t_us - _micros(1.0 / rate_hz))
    return FrameId(fid.modality, t_prev, fid.resolution, fid.mode, fid.rate_hz)


def render(world: World, fid: FrameId) -> Frame:
    """Render one frame exactly as the simulated driver would (same renderers, same metadata)."""
    t = max(0.0, fid.t_us / 1e6)  # a noise slot (negative) renders the static scene at t = 0
    state = world.state_at(t)
    rng = np.random.default_rng([world.seed, MODALITIES.index(fid.modality), abs(fid.t_us), 11 + (fid.t_us < 0)])
    seq = fid.t_us  # unique per frame of this sensor: the feature extractor compares seq
    res = fid.resolution  # None only for radar and IMU
    if fid.modality == "rgb" and res is not None:  # with the exposure metadata the driver adds (illumination undoes it)
        exposure = min(1.0 / fid.rate_hz, world.config.max_exposure_s)
        meta = rgb_exposure(state, res, exposure)
        return Frame("rgb", t, seq, render_rgb(state, res, exposure, rng), meta)
    if fid.modality == "thermal" and res is not None:
        return Frame("thermal", t, seq, render_lepton(state, res, rng), {"units": "cK"})
    if fid.modality == "depth" and res is not None:
        return Frame("depth", t, seq, render_depth(state, res, rng), {"units": "mm"})
    if fid.modality == "radar":
        return Frame("radar", t, seq, render_radar(state, fid.mode or "range", fid.rate_hz, rng))
    raise ValueError(f"no detector input for modality {fid.modality}")


def imu_frame(world: World, t: float) -> Frame:
    """The IMU sample at ``t`` (cheap: rendered fresh each time, never cached)."""
    rng = np.random.default_rng([world.seed, MODALITIES.index("imu"), _micros(t), 11])
    return Frame("imu", t, _micros(t), render_imu(world.state_at(t), rng))


def truth(world: World, t: float, resolution: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth boxes (M, 4) at ``resolution`` and their ignore flags, at instant ``t``."""
    from respecd.lab.detector.data import gt_arrays

    return gt_arrays(ground_truth(world.state_at(t), resolution))
