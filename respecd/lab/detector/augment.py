"""Training augmentation: scale + crop, mosaic, flip, RGB gain, modality dropout; and batching.

Crops keep objects at the pixel sizes the detector meets at 640x360 .. 1280x720 (scale
0.6-2.0 of a 640x360 render) while the network trains on small 256x160 windows, which
is what makes a from-scratch CPU training fit in minutes. Modality dropout zeroes a
channel and its presence flag, as a switched-off sensor does at run time.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from respecd.lab.detector.data import Sample


@dataclass(frozen=True)
class AugmentConfig:
    size: tuple[int, int] = (256, 160)  # crop width, height (multiples of 32)
    scale: tuple[float, float] = (0.6, 2.0)  # log-uniform zoom of the source sample
    mosaic: float = 0.5  # probability of a 4-sample mosaic
    flip: float = 0.5
    rgb_gain: tuple[float, float] = (0.6, 1.4)
    drop_aux_each: float = 0.15  # per non-RGB modality
    drop_aux_all: float = 0.15  # RGB only: "still detects by day with every non-RGB channel zeroed"
    drop_rgb: float = 0.1  # non-RGB only: thermal must carry the night alone
    target_bias: float = 0.7  # probability that a crop is centred near a person
    pseudo_rgb: float = 0.0  # thermal-only samples: probability that RGB shows the thermal image (see pseudo_rgb)


def scale_crop(s: Sample, w: int, h: int, rng: np.random.Generator, cfg: AugmentConfig) -> Sample:
    """A w x h window of the sample zoomed by a random factor, boxes moved with it."""
    lo, hi = np.log(cfg.scale[0]), np.log(cfg.scale[1])
    z = float(np.exp(rng.uniform(lo, hi)))
    src_h, src_w = s.planes.shape[1:]
    usable = np.where(~s.ignore)[0]
    if len(usable) and rng.random() < cfg.target_bias:
        b = s.boxes[rng.choice(usable)]
        cx = (b[0] + b[2]) / 2 * z + rng.uniform(-0.35, 0.35) * w
        cy = (b[1] + b[3]) / 2 * z + rng.uniform(-0.35, 0.35) * h
    else:
        cx, cy = rng.uniform(0, src_w * z), rng.uniform(0, src_h * z)
    ox, oy = cx - w / 2, cy - h / 2  # window origin in zoomed pixels
    m = np.array([[z, 0, -ox], [0, z, -oy]], dtype=np.float64)  # source -> window
    planes = np.stack([cv2.warpAffine(p, m, (w, h), flags=cv2.INTER_LINEAR, borderValue=0) for p in s.planes])
    boxes, ignore, keep = _move_boxes(s.boxes * z - [ox, oy, ox, oy], s.ignore, w, h)
    return Sample(planes, s.presence.copy(), boxes, ignore, s.labels[keep], meta=s.meta)


def _move_boxes(boxes: np.ndarray, ignore: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip to the window; drop what is mostly outside, mark the half-cut as ignore."""
    clipped = np.clip(boxes, 0, [w, h, w, h]).astype(np.float32)
    area = lambda b: np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)  # noqa: E731
    kept = area(clipped) / np.maximum(area(boxes), 1e-6)
    big = ((clipped[:, 2:] - clipped[:, :2]) >= 2).all(1)
    keep = (kept >= 0.15) & big
    return clipped[keep], (ignore | (kept < 0.45))[keep], keep


def mosaic(samples: list[Sample], w: int, h: int, rng: np.random.Generator, cfg: AugmentConfig) -> Sample:
    """Four samples tiled around a random centre (YOLO mosaic), each scale-cropped to its tile."""
    cx, cy = int(rng.uniform(0.3, 0.7) * w), int(rng.uniform(0.3, 0.7) * h)
    tiles = ((0, 0, cx, cy), (cx, 0, w, cy), (0, cy, cx, h), (cx, cy, w, h))
    planes = np.zeros((samples[0].planes.shape[0], h, w), dtype=np.uint8)
    presence = np.ones_like(samples[0].presence)
    boxes, ignore, labels = [], [], []
    for s, (x1, y1, x2, y2) in zip(samples, tiles, strict=True):
        part = scale_crop(s, x2 - x1, y2 - y1, rng, cfg)
        planes[:, y1:y2, x1:x2] = part.planes
        presence = np.minimum(presence, part.presence)  # a modality missing anywhere counts as missing
        boxes.append(part.boxes + [x1, y1, x1, y1])
        ignore.append(part.ignore)
        labels.append(part.labels)
    has_rgb = all(s.meta.get("rgb", True) for s in samples)
    return Sample(planes, presence, np.concatenate(boxes), np.concatenate(ignore), np.concatenate(labels),
                  meta={"rgb": has_rgb})


def augment(pool, rng: np.random.Generator, cfg: AugmentConfig) -> Sample:
    """One training sample drawn from ``pool`` (anything indexable of Samples)."""
    w, h = cfg.size
    if rng.random() < cfg.mosaic:
        s = mosaic([pool[int(i)] for i in rng.integers(len(pool), size=4)], w, h, rng, cfg)
    else:
        s = scale_crop(pool[int(rng.integers(len(pool)))], w, h, rng, cfg)
    if rng.random() < cfg.flip:
        s.planes = np.ascontiguousarray(s.planes[:, :, ::-1])
        s.boxes = np.stack([w - s.boxes[:, 2], s.boxes[:, 1], w - s.boxes[:, 0], s.boxes[:, 3]], 1).reshape(-1, 4)
    if not s.meta.get("rgb", True) and len(s.presence) and rng.random() < cfg.pseudo_rgb:
        pseudo_rgb(s, rng)
    if rng.random() < 0.5:
        gain = rng.uniform(*cfg.rgb_gain)
        s.planes[:3] = np.clip(s.planes[:3].astype(np.float32) * gain, 0, 255).astype(np.uint8)
    drop_modalities(s, rng, cfg)
    return s


def pseudo_rgb(s: Sample, rng: np.random.Generator) -> None:
    """A thermal-only sample gets a grey 'visible' view of the same scene (random gamma, sometimes
    inverted, per-channel tint), so fusion meets two cameras that both see the people."""
    t = s.planes[3].astype(np.float32) / 255
    if rng.random() < 0.3:
        t = 1 - t
    t = t ** rng.uniform(0.5, 2.0)
    tint = rng.uniform(0.7, 1.0, size=3).astype(np.float32)
    s.planes[:3] = np.clip(t[None] * tint[:, None, None] * 255, 0, 255).astype(np.uint8)
    s.meta = {**s.meta, "rgb": True}


def drop_modalities(s: Sample, rng: np.random.Generator, cfg: AugmentConfig) -> None:
    """Sensor-off augmentation; a sample without RGB keeps its only modalities."""
    if not s.meta.get("rgb", True):
        return
    n_aux = len(s.presence)
    r = rng.random()
    if r < cfg.drop_aux_all:
        drop = np.ones(n_aux, dtype=bool)
    else:
        drop = rng.random(n_aux) < cfg.drop_aux_each
    for i in np.where(drop)[0]:
        s.planes[3 + i] = 0
        s.presence[i] = 0.0
    if not drop.all() and rng.random() < cfg.drop_rgb:
        s.planes[:3] = 0


def collate(samples: list[Sample]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> x (B, C, H, W) 0..1, presence (B, A), gt boxes (B, M, 4), labels (B, M), mask (B, M).

    Ignore boxes are left out of the targets (the loss neither rewards nor trains them).
    """
    x = torch.from_numpy(np.stack([s.planes for s in samples])).float().div_(255)  # (B, C, H, W)
    presence = torch.from_numpy(np.stack([s.presence for s in samples]))
    kept = [(s.boxes[~s.ignore], s.labels[~s.ignore]) for s in samples]
    m = max(1, max(len(b) for b, _ in kept))
    boxes = torch.zeros(len(samples), m, 4)
    labels = torch.zeros(len(samples), m, dtype=torch.long)
    mask = torch.zeros(len(samples), m, dtype=torch.bool)
    for i, (b, lab) in enumerate(kept):
        boxes[i, : len(b)] = torch.from_numpy(b)
        labels[i, : len(b)] = torch.from_numpy(lab)
        mask[i, : len(b)] = True
    return x, presence, boxes, labels, mask
