"""Cached, per-scenario images that do not change frame to frame: the room seen by each
imager, a fabric texture, a smoke texture and a bank of sensor noise.

Built once per (room, resolution) with vectorized numpy (tens of milliseconds at 1280x720,
once per 30 s scenario), so a frame costs a copy plus the moving parts.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from respecd.sim.camera import Camera
from respecd.sim.state import Room

NOISE_STD = 32.0  # the noise bank is uint8 with mean 128 and this standard deviation
NOISE_PAD = 64  # frames take the bank at a random offset within this margin
DEPTH_MIN_MM, DEPTH_MAX_MM = 300, 3000  # D435i valid range as the paper uses it


@functools.cache
def noise_bank() -> np.ndarray:
    """uint8 (720 + pad, 1280 + pad, 3) Gaussian noise, fixed seed, generated once and cached."""
    rng = np.random.default_rng(0x5EED)
    bank = rng.normal(128.0, NOISE_STD, size=(720 + NOISE_PAD, 1280 + NOISE_PAD, 3))
    return np.clip(bank, 0, 255).astype(np.uint8)


def noise_slice(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A (height, width, 3) view of the noise bank at a random offset (no copy)."""
    bank = noise_bank()
    oy = int(rng.integers(0, bank.shape[0] - height + 1))
    ox = int(rng.integers(0, bank.shape[1] - width + 1))
    return bank[oy : oy + height, ox : ox + width]


def _low_freq(seed: int, height: int, width: int, cells: int = 12) -> np.ndarray:
    """Smooth float32 noise in [-1, 1]: a tiny random grid scaled up with bicubic interpolation."""
    small = np.random.default_rng(seed).uniform(-1, 1, size=(cells, cells)).astype(np.float32)
    return np.clip(cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC), -1, 1)


def _rays(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Normalized image coordinates x/z (1, W) and y/z (H, 1) of every pixel centre."""
    xn = ((np.arange(cam.width, dtype=np.float32) + 0.5 - cam.cx) / cam.fx)[None, :]
    yn = ((np.arange(cam.height, dtype=np.float32) + 0.5 - cam.cy) / cam.fy)[:, None]
    return xn, yn


def room_depth(room: Room, camera_height: float, cam: Camera) -> np.ndarray:
    """float32 (H, W) z-depth (m) of the floor (y = camera_height) or the back wall."""
    xn, yn = _rays(cam)
    with np.errstate(divide="ignore"):
        floor_z = np.where(yn > 0, camera_height / np.maximum(yn, 1e-9), np.inf)
    z = np.minimum(floor_z, room.wall_z).astype(np.float32)  # (H, 1): a plane's z-depth depends on the row only
    return np.broadcast_to(z, (cam.height, cam.width)).copy()


@functools.lru_cache(maxsize=12)
def rgb_background(room: Room, camera_height: float, cam: Camera) -> tuple[np.ndarray, float]:
    """uint8 BGR reflectance of the room under full light, and its mean level (0..255)."""
    xn, yn = _rays(cam)
    z = room_depth(room, camera_height, cam)[:, :1]  # (H, 1): planes, so depth depends on the row only
    floor_rows = (z[:, 0] < room.wall_z).nonzero()[0]
    panels = np.where((xn * room.wall_z) % 1.2 < 0.03, 0.7, 1.0).astype(np.float32)  # seams every 1.2 m
    skirting = np.where(yn * room.wall_z > camera_height - 0.12, 0.6, 1.0).astype(np.float32)
    shade = panels * skirting  # (H, W) wall
    zf = z[floor_rows]  # floor rows only: 60 cm tiles in world x (= xn * z) and z
    parity = (np.floor(xn * zf * (1 / 0.6)) + np.floor(zf * (1 / 0.6))).astype(np.int32) & 1
    shade[floor_rows] = 0.88 + 0.12 * parity.astype(np.float32)
    shade *= 1.0 + 0.15 * _low_freq(room.texture_seed, cam.height, cam.width)
    image = np.empty((cam.height, cam.width, 3), np.uint8)
    for ch in range(3):
        color = np.full((cam.height, 1), room.wall_color[ch], np.float32)
        color[floor_rows] = room.floor_color[ch]
        image[..., ch] = cv2.convertScaleAbs(shade * color)  # saturating cast to uint8
    _posters(image, room, cam)
    return image, float(image.mean())


def _posters(image: np.ndarray, room: Room, cam: Camera) -> None:
    """A few rectangles on the back wall (doors, posters, shelves): clutter for the detector."""
    rng = np.random.default_rng(room.texture_seed + 1)
    for _ in range(int(rng.integers(2, 6))):
        x1, y1 = rng.uniform(-6, 5), rng.uniform(-2.0, -0.3)
        w, h = rng.uniform(0.4, 1.5), rng.uniform(0.4, 2.0)
        p1 = cam.project(x1, y1, room.wall_z)
        p2 = cam.project(x1 + w, min(y1 + h, 0.4), room.wall_z)
        color = tuple(int(c) for c in rng.integers(20, 240, size=3))
        cv2.rectangle(image, (int(p1[0]), int(p1[1])), (int(p2[0]), int(p2[1])), color, -1)


@functools.lru_cache(maxsize=12)
def thermal_background(room: Room, camera_height: float, cam: Camera) -> np.ndarray:
    """float32 (H, W) kelvin: walls at ambient, floor a little cooler, a few warm spots."""
    z = room_depth(room, camera_height, cam)
    temp = np.where(z < room.wall_z, room.ambient_k - 1.0, room.ambient_k).astype(np.float32)
    temp += 0.4 * _low_freq(room.texture_seed + 2, cam.height, cam.width, cells=6)
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float32)
    for u, v, radius, kelvin in room.warm_spots:  # radiators, lamps, screens
        r2 = ((uu / cam.width - u) ** 2 + (vv / cam.height - v) ** 2) / (radius * radius)
        temp += kelvin * np.exp(-r2).astype(np.float32)
    return temp


@functools.lru_cache(maxsize=12)
def depth_background(room: Room, camera_height: float, cam: Camera) -> np.ndarray:
    """float32 (H, W) z-depth (m) of the room; the renderer blanks what is out of range."""
    return room_depth(room, camera_height, cam)


@functools.lru_cache(maxsize=8)
def fabric(height: int, width: int) -> np.ndarray:
    """uint8 (H, W, 3) multiplicative cloth texture (scale 1/255): weave plus folds."""
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float32)
    weave = 0.92 + 0.08 * np.sign(np.sin(uu * 1.3) * np.sin(vv * 1.3))
    folds = 0.85 + 0.15 * _low_freq(7, height, width, cells=24)
    tex = np.clip(255 * weave * folds, 0, 255).astype(np.uint8)
    return np.repeat(tex[..., None], 3, axis=2)


@functools.lru_cache(maxsize=8)
def smoke_texture(height: int, width: int, color: tuple[int, int, int]) -> np.ndarray:
    """uint8 (H, W, 3) billowing grey for the smoke occluder."""
    billow = 0.85 + 0.15 * _low_freq(11, height, width, cells=16)
    return np.clip(np.array(color, np.float32) * billow[..., None], 0, 255).astype(np.uint8)


@functools.lru_cache(maxsize=8)
def curtain_texture(height: int, width: int, color: tuple[int, int, int]) -> np.ndarray:
    """uint8 (H, W, 3) a hanging cloth: vertical folds (light and shade across the width)."""
    u = np.arange(width, dtype=np.float32)
    folds = 0.8 + 0.2 * np.sin(u * (2 * np.pi / max(8.0, width / 24)))  # about 24 folds across the frame
    shade = folds[None, :] * (0.95 + 0.05 * _low_freq(13, height, width, cells=8))
    return np.clip(np.array(color, np.float32) * shade[..., None], 0, 255).astype(np.uint8)
