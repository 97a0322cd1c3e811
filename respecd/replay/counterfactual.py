"""What a sensor would have delivered under a configuration, made from what it logged.

The one counterfactual evaluator: ``respecd --replay`` (the ``ReplayDriver``, streaming) and
``bench scenarios --log`` (random access at scored instants) both call these, so a replayed
policy and a benchmarked one see the same frames.

* rate: a sensor at ``r`` Hz delivers the first logged frame of each period ``[k/r, (k+1)/r)``
  of the log's clock (the simulated sensors capture on that grid); a rate above the logged
  one cannot invent frames and delivers every logged frame;
* resolution: images are resized (area averaging down, bilinear up; depth by nearest
  neighbour both ways, so no depth between a foreground and a background is made up) and
  ground-truth boxes follow; above the logged resolution it is an upscale;
* radar mode: points beyond the maximum range of the radar driver's chirp table row for
  (mode, rate) are removed and radial velocities alias into its +-v_max (FMCW folding): the
  table the real radar, the simulator and this share (``respecd.radar.chirp``);
* disabled: nothing.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from respecd.messages import Frame, RadarMode, Resolution, SensorConfig
from respecd.record.lazy import derive

GRID_EPS = 1e-9  # logged times on the grid itself (k / r) count as its first frame
IMAGES = ("rgb", "thermal", "depth")


def period_of(t: float, rate_hz: float) -> int:
    return math.floor(t * rate_hz + GRID_EPS)


def delivers(previous_t: float | None, t: float, rate_hz: float) -> bool:
    """Streaming: does the logged frame at ``t`` (the one before it at ``previous_t``) go out?"""
    return previous_t is None or period_of(t, rate_hz) > period_of(previous_t, rate_hz)


def delivered_index(times: Sequence[float], rate_hz: float, t: float) -> int | None:
    """Random access: the index of the newest frame the sensor has delivered by ``t``."""
    newest = bisect.bisect_right(times, t + GRID_EPS) - 1  # the newest logged frame by t
    if newest < 0:
        return None
    start = period_of(times[newest], rate_hz) / rate_hz  # its period's first logged frame went out
    return bisect.bisect_left(times, start - GRID_EPS)


def resize(frame: Frame, resolution: Resolution) -> Frame:
    """The image at ``resolution``; ground truth in ``meta["gt"]`` is scaled with it. The
    pixels are resized when first read (``LazyFrame``): a frame nobody looks at costs nothing."""
    import cv2

    shape = frame.shape
    height, width = shape[:2]
    if (width, height) == tuple(resolution):
        return frame
    shrink = resolution[0] * resolution[1] < width * height
    if frame.modality == "depth":
        interpolation = cv2.INTER_NEAREST
    else:
        interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    meta = dict(frame.meta)
    if meta.get("gt") is not None:
        meta["gt"] = scale_boxes(meta["gt"], resolution[0] / width, resolution[1] / height)
    size = (int(resolution[0]), int(resolution[1]))
    return derive(frame, lambda data: cv2.resize(data, size, interpolation=interpolation),
                  (size[1], size[0], *shape[2:]), meta, upscale=not shrink)


def scale_boxes(gt: Any, sx: float, sy: float) -> Any:
    """Ground-truth boxes follow the image when it is resized: [x1, y1, x2, y2] in pixels,
    bare or as the ``box`` of a dict (the simulator's form, other keys kept)."""
    if not isinstance(gt, (list, tuple)):
        return gt
    scaled: list[Any] = []
    for item in gt:
        if isinstance(item, dict) and "box" in item:
            x1, y1, x2, y2 = item["box"]
            scaled.append({**item, "box": [x1 * sx, y1 * sy, x2 * sx, y2 * sy]})
        elif isinstance(item, (list, tuple)) and len(item) == 4:
            x1, y1, x2, y2 = item
            scaled.append([x1 * sx, y1 * sy, x2 * sx, y2 * sy])
        else:
            return gt  # an unknown shape: leave it alone rather than guess
    return scaled


def radar_limits(mode: RadarMode, rate_hz: float, max_range_m: Mapping[str, float] | None = None,
                 max_velocity_m_s: Mapping[str, float] | None = None) -> tuple[float, float]:
    """(max range m, max radial velocity m/s) of the chirp table row, unless overridden per mode."""
    from respecd.radar.chirp import lookup

    row = lookup(mode, rate_hz)
    return (max_range_m or {}).get(mode, row.max_range_m), (max_velocity_m_s or {}).get(mode, row.max_velocity_mps)


def radar_points(points: np.ndarray, mode: RadarMode | None, rate_hz: float,
                 max_range_m: Mapping[str, float] | None = None,
                 max_velocity_m_s: Mapping[str, float] | None = None) -> np.ndarray:
    """The point cloud (N, 5: x, y, z, v, snr) as the radar in ``mode`` at ``rate_hz`` would have seen it."""
    if mode is None or not points.size:
        return points
    max_range, vmax = radar_limits(mode, rate_hz, max_range_m, max_velocity_m_s)
    distance = np.linalg.norm(points[:, :3], axis=1)
    points = points[distance <= max_range].copy()
    points[:, 3] = (points[:, 3] + vmax) % (2 * vmax) - vmax  # FMCW Doppler folds into [-vmax, vmax)
    return points.astype(np.float32, copy=False)


def transform(frame: Frame, applied: SensorConfig, max_range_m: Mapping[str, float] | None = None,
              max_velocity_m_s: Mapping[str, float] | None = None) -> Frame | None:
    """A delivered logged frame as the sensor would have sent it under ``applied``; None when off."""
    if not applied.enabled:
        return None
    if frame.modality == "radar":
        data = radar_points(frame.data, applied.mode, applied.rate_hz, max_range_m, max_velocity_m_s)
        return replace(frame, data=data)
    if frame.modality in IMAGES and applied.resolution is not None and len(frame.shape) >= 2:
        return resize(frame, applied.resolution)
    return frame
