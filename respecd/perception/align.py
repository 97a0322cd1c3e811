"""Cross-modal alignment: every modality resampled into the RGB camera's pixel grid.

* thermal: a 2D image, re-projected with the plane-induced homography
  ``H = K_rgb (R + t n^T / d) K_thermal^-1`` for a fronto-parallel plane at ``plane_depth_m``
  (exact for a pure rotation, and for targets near that depth when the baseline is small);
* radar: 3D points projected with the extrinsics and the RGB intrinsics, splatted as discs
  whose radius shrinks with range, nearest point drawn last (depth-aware);
* depth: back-projected to 3D with its own intrinsics, moved into the RGB frame and
  re-projected with a z-buffer.

A sensor with no calibration is taken to share the RGB view (the simulator's case, and
LLVIP's pixel-aligned pairs) and is just resized. A missing modality becomes a zero plane
and a 0 presence flag. The result is padded bottom/right to a multiple of 32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from respecd.messages import Frame
from respecd.perception.boxes import pad_to_stride
from respecd.perception.config import PerceptionConfig
from respecd.sensors import Calibration, Intrinsics, rotation_rpy  # noqa: F401 - rotation_rpy re-exported

DEFAULT_RGB_HFOV_DEG = 70.0  # used only when the RGB camera has no calibrated intrinsics
DEFAULT_RGB_SIZE = (640, 360)  # the canvas before any RGB frame, when the RGB camera has no calibrated intrinsics
RADAR_SNR_FULL_DB = 30.0  # SNR mapped to full splat intensity


@dataclass(frozen=True)
class AlignedInput:
    """The detector's input for one bundle."""

    tensor: np.ndarray  # float32 (C, Hp, Wp) in 0..1, C = 3 + aux, padded to multiples of 32
    presence: np.ndarray  # float32 (aux,) 1 = the modality delivered a frame
    size: tuple[int, int]  # RGB (width, height) before padding: detections live in this frame


def camera_matrix(intr: Intrinsics, width: int, height: int) -> np.ndarray:
    """K scaled from the calibrated image size to the frame size actually delivered."""
    sx, sy = width / intr.width, height / intr.height
    return np.array([[intr.fx * sx, 0, intr.cx * sx], [0, intr.fy * sy, intr.cy * sy], [0, 0, 1]], dtype=np.float64)


def default_rgb_matrix(width: int, height: int) -> np.ndarray:
    f = (width / 2) / math.tan(math.radians(DEFAULT_RGB_HFOV_DEG / 2))
    return np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)


class Aligner:
    """Builds the C-channel input from a bundle's frames, using the profile's calibration."""

    def __init__(self, config: PerceptionConfig, calibration: dict[str, Calibration | None] | None = None) -> None:
        self.config = config
        self.aux = config.model.aux_modalities
        self.calibration = calibration or {}
        self.plane_depth_m = config.plane_depth_m
        self.rgb_size = self.first_rgb_size()

    def first_rgb_size(self) -> tuple[int, int]:
        """The canvas before any RGB frame: the calibrated RGB size, else ``DEFAULT_RGB_SIZE``."""
        cal = self.calibration.get("rgb")
        return (cal.intrinsics.width, cal.intrinsics.height) if cal and cal.intrinsics else DEFAULT_RGB_SIZE

    def forget_rgb_size(self) -> None:
        """Back to the canvas before any RGB frame (a new session on a shared detector)."""
        self.rgb_size = self.first_rgb_size()

    def align(self, frames: dict[str, Frame], rgb_size: tuple[int, int] | None = None) -> AlignedInput:
        """The input for ``frames``, on the RGB frame's pixel grid: detections come out in the RGB camera's
        pixels, where the daemon draws and publishes them. Without an RGB frame (the camera stalled or
        failed) the grid is ``rgb_size``, else the last RGB frame's size (at first the calibrated one)."""
        rgb = frames.get("rgb")
        if rgb is not None:
            w, h = self.rgb_size = (rgb.data.shape[1], rgb.data.shape[0])
        else:
            w, h = rgb_size or self.rgb_size
        hp, wp = pad_to_stride(h, w)
        out = np.zeros((3 + len(self.aux), hp, wp), dtype=np.float32)
        if rgb is not None:
            # BGR -> R, G, B planes: cv2.split gives contiguous planes, 4x faster than a strided transpose
            for plane, channel in zip(cv2.split(rgb.data), (2, 1, 0), strict=True):
                np.divide(plane, np.float32(255), out=out[channel, :h, :w], dtype=np.float32)
        k_rgb = self._rgb_matrix(w, h)
        presence = np.zeros(len(self.aux), dtype=np.float32)
        for i, name in enumerate(self.aux):
            frame = pixel_source(frames.get(name))
            if frame is None or frame.data.size == 0 and name != "radar":
                continue
            plane = self._plane(name, frame, k_rgb, w, h)
            out[3 + i, :h, :w] = plane
            presence[i] = 1.0
        return AlignedInput(out, presence, (w, h))

    def _rgb_matrix(self, w: int, h: int) -> np.ndarray:
        cal = self.calibration.get("rgb")
        if cal is not None and cal.intrinsics is not None:
            return camera_matrix(cal.intrinsics, w, h)
        return default_rgb_matrix(w, h)

    def _plane(self, name: str, frame: Frame, k_rgb: np.ndarray, w: int, h: int) -> np.ndarray:
        cal = self.calibration.get(name)
        if name == "thermal":
            return self._thermal(normalize_thermal(frame, self.config), cal, k_rgb, w, h)
        if name == "radar":
            return splat_radar(frame.data, cal, k_rgb, w, h, self.config.radar_max_range_m)
        return self._depth(frame.data, cal, k_rgb, w, h)

    def _thermal(self, img: np.ndarray, cal: Calibration | None, k_rgb: np.ndarray, w: int, h: int) -> np.ndarray:
        if cal is None or cal.intrinsics is None:
            return cv2.resize(img, (w, h), interpolation=cv2.INTER_LINEAR)
        k_t = camera_matrix(cal.intrinsics, img.shape[1], img.shape[0])
        homography = plane_homography(k_t, k_rgb, cal, self.plane_depth_m)
        return cv2.warpPerspective(img, homography, (w, h), flags=cv2.INTER_LINEAR, borderValue=0.0)

    def _depth(self, depth_mm: np.ndarray, cal: Calibration | None, k_rgb: np.ndarray, w: int, h: int) -> np.ndarray:
        z: np.ndarray = depth_mm.astype(np.float32) / 1000.0
        if cal is None or cal.intrinsics is None:
            z = cv2.resize(z, (w, h), interpolation=cv2.INTER_NEAREST)
        else:
            z = reproject_depth(z, camera_matrix(cal.intrinsics, z.shape[1], z.shape[0]), cal, k_rgb, w, h)
        return np.where(z > 0, 1.0 - np.clip(z / self.config.depth_max_m, 0, 1), 0.0).astype(np.float32)


def pixel_source(frame: Frame | None) -> Frame | None:
    """The frame whose pixels an aux modality's plane is made from. An upscaled replay frame
    (record.lazy) holds no more than its source, and it is resampled into the RGB view anyway:
    the source, resampled once."""
    return getattr(frame, "upscale_of", None) or frame


def normalize_thermal(frame: Frame, config: PerceptionConfig) -> np.ndarray:
    """Thermal frame -> float32 0..1: kelvin over ``thermal_range_k``; 8-bit images (LLVIP) / 255."""
    data = frame.data
    if data.ndim == 3:  # 3-channel greyscale export (LLVIP ships IR as such)
        data = data[:, :, 0]
    if data.dtype == np.uint8:
        return data.astype(np.float32) / 255.0
    kelvin = data.astype(np.float32)
    if frame.meta.get("units") != "K":
        kelvin = kelvin / config.thermal_counts_per_k
    low, high = config.thermal_range_k
    return np.clip((kelvin - low) / (high - low), 0.0, 1.0)


def plane_homography(k_src: np.ndarray, k_rgb: np.ndarray, cal: Calibration, depth_m: float) -> np.ndarray:
    """Maps source pixels to RGB pixels for points on the plane z_src = depth_m."""
    rot = rotation_rpy(*cal.extrinsics.rotation_rpy_deg)
    t = np.asarray(cal.extrinsics.translation_m, dtype=np.float64).reshape(3, 1)
    n = np.array([[0.0, 0.0, 1.0]])
    return k_rgb @ (rot + t @ n / depth_m) @ np.linalg.inv(k_src)


def _to_rgb_frame(points: np.ndarray, cal: Calibration | None) -> np.ndarray:
    """(N, 3) sensor-frame points -> RGB camera frame with the extrinsics (identity if absent)."""
    if cal is None:
        return points
    rot = rotation_rpy(*cal.extrinsics.rotation_rpy_deg)
    return points @ rot.T + np.asarray(cal.extrinsics.translation_m)


def splat_radar(
    points: np.ndarray, cal: Calibration | None, k_rgb: np.ndarray, w: int, h: int, max_range_m: float
) -> np.ndarray:
    """Radar (N, 5) x, y (boresight), z (up), v, snr -> one plane of SNR-weighted discs."""
    plane = np.zeros((h, w), dtype=np.float32)
    if points.size == 0:
        return plane
    pts = points.reshape(-1, 5).astype(np.float64)
    cam = np.stack([pts[:, 0], -pts[:, 2], pts[:, 1]], 1)  # TI frame -> camera axes (x right, y down, z forward)
    cam = _to_rgb_frame(cam, cal)
    keep = (cam[:, 2] > 0.2) & (np.linalg.norm(cam, axis=1) < max_range_m)
    cam, snr = cam[keep], pts[keep, 4]
    if len(cam) == 0:
        return plane
    uv = (cam @ k_rgb.T)[:, :2] / cam[:, 2:3]
    # a return stands for ~0.1 m of surface: nearer points make bigger discs
    radius = np.clip(k_rgb[0, 0] * 0.1 / cam[:, 2], 1.5, 0.04 * w)
    value = 0.25 + 0.75 * np.clip(snr / RADAR_SNR_FULL_DB, 0.0, 1.0)
    for i in np.argsort(-cam[:, 2]):  # far first, so the nearest return wins where discs overlap
        u, v = uv[i]
        if -radius[i] <= u < w + radius[i] and -radius[i] <= v < h + radius[i]:
            cv2.circle(plane, (int(round(u)), int(round(v))), int(round(radius[i])), float(value[i]), -1)
    return plane


def reproject_depth(
    z: np.ndarray, k_depth: np.ndarray, cal: Calibration, k_rgb: np.ndarray, w: int, h: int
) -> np.ndarray:
    """Depth (H, W) metres in the depth camera -> (h, w) metres in the RGB view, nearest surface kept."""
    step = max(1, int(round(z.shape[1] / w)))  # no need for more samples than RGB pixels
    zs = z[::step, ::step]
    vs, us = np.nonzero(zs > 0)
    d = zs[vs, us].astype(np.float64)
    pix = np.stack([us * step, vs * step, np.ones_like(d)], 1)
    cam = (pix @ np.linalg.inv(k_depth).T) * d[:, None]  # (N, 3) in the depth camera
    cam = _to_rgb_frame(cam, cal)
    front = cam[:, 2] > 0.05
    cam = cam[front]
    uv = np.round((cam @ k_rgb.T)[:, :2] / cam[:, 2:3]).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    uv, depth = uv[inside], cam[inside, 2]
    out = np.full((h, w), np.inf, dtype=np.float32)
    np.minimum.at(out, (uv[:, 1], uv[:, 0]), depth.astype(np.float32))  # z-buffer
    out[np.isinf(out)] = 0.0
    if step > 1 or k_rgb[0, 0] > k_depth[0, 0]:  # close the holes left by sparser depth samples
        filled = cv2.dilate(out, np.ones((3, 3), np.uint8))
        out = np.where(out > 0, out, filled)
    return out
