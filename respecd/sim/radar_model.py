"""Simulated IWR6843 point cloud: what the out-of-box demo would report for the scene.

The chirp for (mode, rate) comes from the radar driver's own lookup table
(``respecd.radar.chirp``), so the simulated and the real radar trade range resolution
against velocity resolution identically: both modes reach 14.99 m (their cfarFovCfg); the
range mode resolves 7 cm but only ~0.7-1.4 m/s; the velocity mode resolves 0.03 m/s at low
rates (0.6 m/s at 30 fps, where the UART write leaves ~4 ms of chirping) but only 0.29 m.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from respecd.radar.chirp import UART_BYTES_PER_S, lookup
from respecd.sim.camera import blocked_mask
from respecd.sim.state import SceneState

AZIMUTH_FOV_DEG, ELEVATION_FOV_DEG = 60.0, 20.0  # IWR6843ISK antenna field of view (half angles)
POINT_BYTES, FRAME_OVERHEAD_BYTES = 20, 128  # TLV 1 (16 B) + TLV 7 (4 B) per point; header and other TLVs
CFAR_THRESHOLD_DB = 12.0
SNR_AT_3M_DB = {"range": 36.0, "velocity": 39.0}  # velocity preset integrates 2x more samples per frame


@dataclass(frozen=True, slots=True)
class RadarFigures:
    range_res_m: float
    max_range_m: float
    cfar_range_m: float  # detections stop here (cfarFovCfg)
    max_velocity_mps: float
    velocity_res_mps: float
    loops: int
    max_points: int  # what the UART carries per frame at this rate

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@functools.lru_cache(maxsize=256)
def radar_figures(mode: str, rate_hz: float) -> RadarFigures:
    """The figures of the chirp the radar driver would send for ``mode`` at ``rate_hz``."""
    p = lookup(mode, rate_hz)  # type: ignore[arg-type]
    points = int((0.8 * UART_BYTES_PER_S / rate_hz - FRAME_OVERHEAD_BYTES) // POINT_BYTES)  # 80 % of the link
    return RadarFigures(
        p.range_resolution_m,
        p.max_range_m,
        p.max_range_m,  # the cfg's cfarFovCfg range limit is the max range (TI's 0.8 Fs convention)
        p.max_velocity_mps,
        p.velocity_resolution_mps,
        p.loops,
        max(points, 1),
    )


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
    keep = (snr > CFAR_THRESHOLD_DB) & (rng_m > 0.2) & (rng_m < fig.cfar_range_m)
    keep &= (np.abs(az) < math.radians(AZIMUTH_FOV_DEG)) & (np.abs(el) < math.radians(ELEVATION_FOV_DEG))
    v = _wrap(np.round(v / fig.velocity_res_mps) * fig.velocity_res_mps, fig.max_velocity_mps)
    # TI frame: x right, y boresight, z up
    out = np.stack([rng_m * np.cos(el) * np.sin(az), rng_m * np.cos(el) * np.cos(az), rng_m * np.sin(el), v, snr], 1)
    return out[keep]


def _false_alarms(fig: RadarFigures, rng: np.random.Generator) -> np.ndarray:
    n = int(rng.poisson(1.5))
    rng_m = rng.uniform(0.5, fig.cfar_range_m, n)
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
        if occ.kind != "solid":  # smoke, fog and thin fabric cost a few dB, nothing more, at 60 GHz
            behind = blocked_mask(cloud[:, 0], cloud[:, 1], cloud[:, 2], (occ,), occ.kind)
            cloud[behind, 4] -= occ.radar_loss_db
    points = np.concatenate([_measure(cloud, fig, rng), _false_alarms(fig, rng)])
    if len(points) > fig.max_points:  # the UART carries only so much per frame: strongest first
        points = points[np.argsort(-points[:, 4])[: fig.max_points]]
    return points.astype(np.float32)
