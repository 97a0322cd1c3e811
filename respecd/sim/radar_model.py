"""Simulated IWR6843 point cloud: what the out-of-box demo would report for the scene.

The two chirp presets are the real xWR68xx SDK 3.6 visualizer configurations
(``Demo_Visualizer_Best_Range.cfg`` and ``..._Best_Velocity_Res.cfg``, see SENSORS.md 2.4);
the four figures follow from the standard FMCW relations. The frame rate couples them: the
active frame time (loops x TX x chirp time) must fit in the frame period, so at high rates
the velocity preset halves its loops and loses velocity resolution.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from respecd.sim.camera import blocked_mask
from respecd.sim.state import SceneState

C = 3e8
F0_HZ = 60e9
CFAR_FOV_SHARE = 0.89  # the demo cfgs' cfarFov sits at 89 % of the unambiguous range
AZIMUTH_FOV_DEG, ELEVATION_FOV_DEG = 60.0, 20.0  # IWR6843ISK antenna field of view (half angles)
UART_BYTES_PER_S = 92160 * 0.8  # 921600 baud, 10 bits per byte, 80 % usable
POINT_BYTES, FRAME_OVERHEAD_BYTES = 20, 100  # float32 x,y,z,v + int16 snr,noise; header and TLV headers
CFAR_THRESHOLD_DB = 12.0
SNR_AT_3M_DB = {"range": 36.0, "velocity": 39.0}  # velocity preset integrates 2x more samples per frame


@dataclass(frozen=True, slots=True)
class Chirp:
    idle_us: float
    ramp_us: float
    slope_mhz_us: float
    adc_samples: int
    sample_rate_ksps: float
    tx: int
    loops: int


CHIRPS: dict[str, Chirp] = {
    "range": Chirp(388.0, 28.49, 30.0, 256, 12499.0, 3, 16),
    "velocity": Chirp(115.0, 15.0, 100.0, 64, 9142.0, 3, 128),
}


@dataclass(frozen=True, slots=True)
class RadarFigures:
    range_res_m: float
    max_range_m: float
    max_velocity_mps: float
    velocity_res_mps: float
    loops: int
    max_points: int  # what the UART can carry per frame at this rate

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@functools.lru_cache(maxsize=256)
def radar_figures(mode: str, rate_hz: float) -> RadarFigures:
    """The four FMCW figures of ``mode`` at ``rate_hz`` (SENSORS.md 2.4 formulas)."""
    c = CHIRPS[mode]
    chirp_s = (c.idle_us + c.ramp_us) * 1e-6
    loops = c.loops
    while loops > 1 and loops * c.tx * chirp_s >= 1.0 / rate_hz:  # active frame time must fit the period
        loops //= 2
    range_res = C * c.sample_rate_ksps * 1e3 / (2 * c.slope_mhz_us * 1e12 * c.adc_samples)
    max_range = 300 * 0.9 * c.sample_rate_ksps / (2 * c.slope_mhz_us * 1e3)
    v_max = C / (4 * F0_HZ * chirp_s * c.tx)
    v_res = C / (2 * F0_HZ * chirp_s * loops * c.tx)
    points = int((UART_BYTES_PER_S / rate_hz - FRAME_OVERHEAD_BYTES) // POINT_BYTES)
    return RadarFigures(range_res, max_range, v_max, v_res, loops, max(points, 1))


def _wrap(v: np.ndarray, v_max: float) -> np.ndarray:
    """Doppler aliasing: radial speeds beyond +-v_max fold back into the interval."""
    return (v + v_max) % (2 * v_max) - v_max


def _person_scatterers(state: SceneState, mode: str, fig: RadarFigures, rng: np.random.Generator) -> list[np.ndarray]:
    """Rows (x, y, z, v, snr) in the camera frame for body scatterers, before visibility tests."""
    rows = []
    for tg in state.targets:
        r = max(tg.distance_m, 0.3)
        moving = tg.speed_mps > 0.2
        lam = 14.0 * (3.0 / r) * (1.5 if moving and mode == "velocity" else 1.0) * (0.244 / fig.range_res_m) ** 0.5
        n = int(rng.poisson(max(lam, 1.0)))
        if n == 0:
            continue
        (x, y, z), (w, h) = tg.position, tg.size
        xs = x + rng.uniform(-0.5, 0.5, n) * w
        ys = y + rng.uniform(-0.5, 0.5, n) * h
        zs = z + rng.uniform(-0.15, 0.15, n)
        ranges = np.sqrt(xs**2 + ys**2 + zs**2)
        radial = (xs * tg.velocity[0] + ys * tg.velocity[1] + zs * tg.velocity[2]) / ranges
        radial = radial + rng.normal(0.0, 0.3 * tg.speed_mps + 0.02, n)  # limbs swing: micro-Doppler
        snr = SNR_AT_3M_DB[mode] - 40 * np.log10(ranges / 3.0) + rng.normal(0.0, 3.0, n)
        rows.append(np.stack([xs, ys, zs, radial, snr], axis=1))
    return rows


def _static_scatterers(state: SceneState, mode: str, rng: np.random.Generator) -> list[np.ndarray]:
    """Room reflectors and solid occluder faces; they move only by the rover's own motion."""
    pts = [np.asarray(state.room.reflectors, dtype=np.float64).reshape(-1, 3)]
    for occ in state.occluders:
        if occ.kind == "solid":  # a crate or wall edge is a strong reflector
            x1, y1, x2, y2 = occ.bounds()
            n = int(rng.integers(4, 11))
            pts.append(np.stack([rng.uniform(x1, x2, n), rng.uniform(y1, y2, n), np.full(n, occ.center[2])], axis=1))
    xyz = np.concatenate(pts)
    xyz = xyz[rng.random(len(xyz)) < 0.8]  # CFAR flicker: not every reflector fires every frame
    ranges = np.linalg.norm(xyz, axis=1)
    # the rover drives along z at ego speed: static points approach at -v cos(angle)
    radial = -state.ego_speed * xyz[:, 2] / np.maximum(ranges, 1e-6)
    snr = SNR_AT_3M_DB[mode] + 6.0 - 40 * np.log10(np.maximum(ranges, 0.3) / 3.0) + rng.normal(0, 3.0, len(xyz))
    return [np.column_stack([xyz, radial, snr])]


def _measure(cloud: np.ndarray, fig: RadarFigures, rng: np.random.Generator) -> np.ndarray:
    """Apply range/angle/Doppler quantization and noise, field of view and CFAR."""
    x, y, z, v, snr = cloud.T
    rng_m = np.sqrt(x**2 + y**2 + z**2)
    az = np.arctan2(x, z) + np.radians(rng.normal(0, 3.0, len(x)))
    el = np.arcsin(np.clip(-y / np.maximum(rng_m, 1e-6), -1, 1)) + np.radians(rng.normal(0, 6.0, len(x)))
    rng_m = (np.round(rng_m / fig.range_res_m) + rng.normal(0, 0.3, len(x))) * fig.range_res_m
    keep = (snr > CFAR_THRESHOLD_DB) & (rng_m > 0.2) & (rng_m < CFAR_FOV_SHARE * fig.max_range_m)
    keep &= (np.abs(az) < math.radians(AZIMUTH_FOV_DEG)) & (np.abs(el) < math.radians(ELEVATION_FOV_DEG))
    v = _wrap(np.round(v / fig.velocity_res_mps) * fig.velocity_res_mps, fig.max_velocity_mps)
    # TI frame: x right, y boresight, z up
    out = np.stack([rng_m * np.cos(el) * np.sin(az), rng_m * np.cos(el) * np.cos(az), rng_m * np.sin(el), v, snr], 1)
    return out[keep]


def _false_alarms(fig: RadarFigures, rng: np.random.Generator) -> np.ndarray:
    n = int(rng.poisson(1.5))
    rng_m = rng.uniform(0.5, CFAR_FOV_SHARE * fig.max_range_m, n)
    az = np.radians(rng.uniform(-AZIMUTH_FOV_DEG, AZIMUTH_FOV_DEG, n))
    v = rng.uniform(-fig.max_velocity_mps, fig.max_velocity_mps, n)
    snr = rng.uniform(CFAR_THRESHOLD_DB, CFAR_THRESHOLD_DB + 3, n)
    return np.stack([rng_m * np.sin(az), rng_m * np.cos(az), rng.normal(0, 0.3, n), v, snr], 1)


def render_radar(state: SceneState, mode: str, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """float32 (N, 5): x, y (boresight), z (up) in metres, radial v (m/s), snr (dB)."""
    fig = radar_figures(mode, rate_hz)
    people = _person_scatterers(state, mode, fig, rng)
    static = _static_scatterers(state, mode, rng)
    cloud = np.concatenate(people + static) if people or static else np.zeros((0, 5))
    blocked = blocked_mask(cloud[:, 0], cloud[:, 1], cloud[:, 2] - 1e-3, state.occluders, "solid")
    cloud = cloud[~blocked]  # the solid occluder's own face stays (nudged 1 mm nearer above)
    for occ in state.occluders:
        if occ.kind == "smoke":  # smoke costs a few dB, nothing more, at 60 GHz
            behind = blocked_mask(cloud[:, 0], cloud[:, 1], cloud[:, 2], (occ,), "smoke")
            cloud[behind, 4] -= occ.radar_loss_db
    points = np.concatenate([_measure(cloud, fig, rng), _false_alarms(fig, rng)])
    if len(points) > fig.max_points:  # the UART carries only so much per frame: strongest first
        points = points[np.argsort(-points[:, 4])[: fig.max_points]]
    return points.astype(np.float32)
