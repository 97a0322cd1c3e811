"""Training augmentation: strips and crops, mosaic, flip, RGB gain, modality dropout; and batching.

* ``strip`` (the simulator): a full-height window of a frame rendered at one of the RGB
  resolutions the controller can choose, zoomed 0.8-1.25x. Every person the camera shows
  fits in it whole (at 1280x720 people stand between rows 0 and ~570), so the network learns
  boxes from a few pixels up to the full frame height at their real pixel sizes, and the
  large ones land on the P4 and P5 heads.
* ``scale_crop`` / ``mosaic`` (decoded photo datasets): a zoomed window of a fixed size.

A box the window cuts (it keeps less than ``keep_cut`` of its area) becomes "ignore": a
half person is neither a positive (the net would learn to stop boxes at a crop edge) nor a
negative. A box already cut by the frame itself stays a positive, as at run time.

Modality dropout zeroes a channel and its presence flag, as a switched-off sensor does at
run time; every sensor is sometimes the only one on (``AugmentConfig.keep``). Labels follow
the evidence: a person whom no remaining sensor can see (behind a curtain with the radar
dropped) is removed from the targets, and one only a dark RGB frame hints at (the camera's
signal below ``rgb_min_signal``) is ignored. So the net is never taught to find people
without evidence, nor to do without the one sensor that sees them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from respecd.lab.detector.data import Sample


@dataclass(frozen=True)
class AugmentConfig:
    size: tuple[int, int] = (256, 160)  # crop width, height for scale_crop / mosaic (multiples of 32)
    scale: tuple[float, float] = (0.6, 2.0)  # log-uniform zoom of the source sample (crops)
    zoom: tuple[float, float] = (0.8, 1.25)  # log-uniform zoom of a strip
    # per RGB size (w, h): its own strip zoom range, replacing ``zoom`` there (a fine-tune can zoom
    # 640x360 frames near their own scale and still show 1280x720 people up to twice their size)
    zoom_at: tuple[tuple[tuple[int, int], tuple[float, float]], ...] = ()
    mosaic: float = 0.5  # probability of a 4-sample mosaic (crops)
    flip: float = 0.5
    rgb_gain: tuple[float, float] = (0.6, 1.4)
    # which sensors stay on, with what probability (a sensor the sample lacks is off anyway)
    keep: tuple[tuple[tuple[str, ...], float], ...] = (
        (("rgb", "thermal", "radar"), 0.40),
        (("rgb",), 0.15),
        (("rgb", "thermal"), 0.08),
        (("rgb", "radar"), 0.08),
        (("thermal", "radar"), 0.10),
        (("thermal",), 0.07),
        (("radar",), 0.12),
    )
    rgb_min_signal: float = 0.04  # RGB level per unit reflectance below which the camera sees only a hint
    pseudo_rgb: float = 0.0  # thermal-only samples: probability that RGB shows the thermal image (see pseudo_rgb)
    target_bias: float = 0.8  # probability that a window is centred near a person
    keep_cut: float = 0.9  # a box the window cuts to less than this share of its area is ignored
    min_seen: float = 0.05  # a camera sees a person if at least this share of its light gets through

    def zoom_for(self, size: tuple[int, int]) -> tuple[float, float]:
        """The strip zoom range of frames rendered at RGB ``size``."""
        return dict(self.zoom_at).get((size[0], size[1]), self.zoom)


def _window(s: Sample, z: float, ox: float, oy: float, w: int, h: int, cfg: AugmentConfig) -> Sample:
    """The w x h window at (ox, oy) of the sample zoomed by z, boxes moved and cut with it."""
    m = np.array([[z, 0, -ox], [0, z, -oy]], dtype=np.float64)  # source -> window
    planes = np.stack([cv2.warpAffine(p, m, (w, h), flags=cv2.INTER_LINEAR, borderValue=0) for p in s.planes])
    boxes = s.boxes * z - np.array([ox, oy, ox, oy], np.float32)
    clipped = np.clip(boxes, 0, [w, h, w, h]).astype(np.float32)
    area = lambda b: np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)  # noqa: E731
    kept = area(clipped) / np.maximum(area(boxes), 1e-6)
    keep = (kept >= 0.05) & ((clipped[:, 2:] - clipped[:, :2]) >= 2).all(1)
    ignore = (s.ignore | (kept < cfg.keep_cut))[keep]
    return Sample(planes, s.presence.copy(), clipped[keep], ignore, s.labels[keep], s.meta, s.seen[keep])


def _centre(s: Sample, z: float, w: int, h: int, rng: np.random.Generator, cfg: AugmentConfig) -> tuple[float, float]:
    """A window centre in zoomed pixels: near a random person (target_bias) or anywhere."""
    usable = np.where(~s.ignore)[0]
    if len(usable) and rng.random() < cfg.target_bias:
        b = s.boxes[rng.choice(usable)]
        return ((b[0] + b[2]) / 2 * z + rng.uniform(-0.35, 0.35) * w,
                (b[1] + b[3]) / 2 * z + rng.uniform(-0.35, 0.35) * h)
    src_h, src_w = s.planes.shape[1:]
    return rng.uniform(0, src_w * z), rng.uniform(0, src_h * z)


def strip(s: Sample, w: int, h: int, rng: np.random.Generator, cfg: AugmentConfig,
          zoom: tuple[float, float] | None = None) -> Sample:
    """A w x h window of the frame zoomed by a random factor in ``zoom`` (default ``cfg.zoom``);
    h is the padded frame height.

    Zoomed out, the frame sits at the top with a black band below (like the stride padding
    at run time); zoomed in, the window takes a random band of rows.
    """
    z = float(np.exp(rng.uniform(*np.log(zoom or cfg.zoom))))
    cx, _ = _centre(s, z, w, h, rng, cfg)
    excess = s.planes.shape[1] * z - h
    oy = rng.uniform(0, excess) if excess > 0 else 0.0
    return _window(s, z, cx - w / 2, oy, w, h, cfg)


def scale_crop(s: Sample, w: int, h: int, rng: np.random.Generator, cfg: AugmentConfig) -> Sample:
    """A w x h window of the sample zoomed by a random factor, boxes moved with it."""
    z = float(np.exp(rng.uniform(*np.log(cfg.scale))))
    cx, cy = _centre(s, z, w, h, rng, cfg)
    return _window(s, z, cx - w / 2, cy - h / 2, w, h, cfg)


def mosaic(samples: list[Sample], w: int, h: int, rng: np.random.Generator, cfg: AugmentConfig) -> Sample:
    """Four samples tiled around a random centre (YOLO mosaic), each scale-cropped to its tile."""
    cx, cy = int(rng.uniform(0.3, 0.7) * w), int(rng.uniform(0.3, 0.7) * h)
    tiles = ((0, 0, cx, cy), (cx, 0, w, cy), (0, cy, cx, h), (cx, cy, w, h))
    planes = np.zeros((samples[0].planes.shape[0], h, w), dtype=samples[0].planes.dtype)
    presence = np.ones_like(samples[0].presence)
    boxes, ignore, labels, seen = [], [], [], []
    for s, (x1, y1, x2, y2) in zip(samples, tiles, strict=True):
        part = scale_crop(s, x2 - x1, y2 - y1, rng, cfg)
        planes[:, y1:y2, x1:x2] = part.planes
        presence = np.minimum(presence, part.presence)  # a modality missing anywhere counts as missing
        boxes.append(part.boxes + [x1, y1, x1, y1])
        ignore.append(part.ignore)
        labels.append(part.labels)
        seen.append(part.seen)
    has_rgb = all(s.meta.get("rgb", True) for s in samples)
    return Sample(planes, presence, np.concatenate(boxes), np.concatenate(ignore), np.concatenate(labels),
                  meta={"rgb": has_rgb}, seen=np.concatenate(seen))


AUX = ("thermal", "radar")


def augment(pool, rng: np.random.Generator, cfg: AugmentConfig, aux: tuple[str, ...] = AUX) -> Sample:
    """One training crop drawn from ``pool`` (anything indexable of Samples)."""
    w, h = cfg.size
    if rng.random() < cfg.mosaic:
        s = mosaic([pool[int(i)] for i in rng.integers(len(pool), size=4)], w, h, rng, cfg)
    else:
        s = scale_crop(pool[int(rng.integers(len(pool)))], w, h, rng, cfg)
    return photometric(s, rng, cfg, aux)


def photometric(s: Sample, rng: np.random.Generator, cfg: AugmentConfig, aux: tuple[str, ...] = AUX) -> Sample:
    """Horizontal flip, pseudo-RGB for thermal-only data, RGB gain and modality dropout, in place."""
    w = s.planes.shape[2]
    if rng.random() < cfg.flip:
        s.planes = np.ascontiguousarray(s.planes[:, :, ::-1])
        s.boxes = np.stack([w - s.boxes[:, 2], s.boxes[:, 1], w - s.boxes[:, 0], s.boxes[:, 3]], 1).reshape(-1, 4)
    if not s.meta.get("rgb", True) and len(s.presence) and rng.random() < cfg.pseudo_rgb:
        pseudo_rgb(s, rng)
    if rng.random() < 0.5:
        top = 255 if s.planes.dtype == np.uint8 else 1.0
        gained = s.planes[:3].astype(np.float32) * rng.uniform(*cfg.rgb_gain)
        s.planes[:3] = np.clip(gained, 0, top).astype(s.planes.dtype)
    drop_modalities(s, rng, cfg, aux)
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


def drop_modalities(s: Sample, rng: np.random.Generator, cfg: AugmentConfig, aux: tuple[str, ...] = AUX) -> None:
    """Switch sensors off at random (``cfg.keep``); labels then follow what is left to see.

    Every sensor is sometimes the only one on, so the net must detect from each alone. A
    sample without RGB (a thermal-only dataset) keeps its only modalities.
    """
    if not s.meta.get("rgb", True):
        return
    names = ("rgb", *aux)
    present = {"rgb", *(name for i, name in enumerate(aux) if s.presence[i] > 0)}
    subsets, weights = zip(*cfg.keep, strict=True)
    chosen = set(subsets[int(rng.choice(len(subsets), p=np.asarray(weights) / sum(weights)))])
    keep = (chosen & present) or present
    for m, name in enumerate(names):
        if name in keep or name not in present:
            continue
        if m == 0:
            s.planes[:3] = 0
        else:
            s.planes[2 + m] = 0
            s.presence[m - 1] = 0.0
    _follow_evidence(s, keep, cfg)


def _follow_evidence(s: Sample, on: set[str], cfg: AugmentConfig) -> None:
    """People whom no sensor left on can see are no longer targets; those only a dark RGB frame
    hints at are ignored (neither taught nor punished). The radar sees through obscurants."""
    if len(s.boxes) == 0:
        return
    rgb = ("rgb" in on) & (s.seen[:, 0] >= cfg.min_seen)
    bright = s.meta.get("rgb_signal", 1.0) >= cfg.rgb_min_signal
    strong = (rgb & bright) | (("thermal" in on) & (s.seen[:, 1] >= cfg.min_seen))
    strong |= ("radar" in on) or ("depth" in on)
    keep = strong | rgb | s.ignore
    s.ignore = (s.ignore | ~strong)[keep]
    s.boxes, s.labels, s.seen = s.boxes[keep], s.labels[keep], s.seen[keep]


def collate(samples: list[Sample]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> x (B, C, H, W) 0..1, presence (B, A), gt boxes (B, M, 4), labels (B, M), mask (B, M).

    Ignore boxes are left out of the targets (the loss neither rewards nor trains them).
    """
    stacked = np.stack([s.planes for s in samples])
    x = torch.from_numpy(stacked).float()  # (B, C, H, W)
    if stacked.dtype == np.uint8:
        x = x.div_(255)
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
