"""Samples (the detector's aligned input with its boxes) and the LLVIP-layout dataset.

Simulated samples are rendered on demand (``simdata.py``); LLVIP-layout folders
(``visible/``, ``infrared/``, ``Annotations/*.xml``) load lazily, as uint8 planes.
"""

from __future__ import annotations

import functools
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from respecd.errors import InputError
from respecd.messages import Frame
from respecd.perception.align import Aligner
from respecd.perception.config import PerceptionConfig

MIN_VISIBLE = 0.3  # a person less visible than this (behind a solid occluder) is "ignore" ground truth
MIN_BOX_PX = 4.0  # ... and so is one smaller than this on either side


@dataclass
class Sample:
    """The detector's input (R, G, B, aux...) with its boxes.

    ``planes`` is uint8 0..255 for decoded photos (x / 255 is the network input) or float32
    0..1 for rendered frames (kept as the daemon feeds them: a 0.05 K thermal step survives).
    ``seen`` holds, per box, the share of its light that reaches the RGB and the thermal
    camera through smoke, fog or a curtain (1 = clear; the radar sees through all three).
    """

    planes: np.ndarray  # (C, H, W) uint8 0..255 or float32 0..1
    presence: np.ndarray  # float32 (A,)
    boxes: np.ndarray  # float32 (M, 4) x1y1x2y2 pixels
    ignore: np.ndarray  # bool (M,)
    labels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (M,)
    meta: dict = field(default_factory=dict)
    seen: np.ndarray = field(default_factory=lambda: np.ones((0, 2), dtype=np.float32))  # (M, 2) rgb, thermal

    def __post_init__(self) -> None:
        if len(self.labels) != len(self.boxes):
            self.labels = np.zeros(len(self.boxes), dtype=np.int64)
        if len(self.seen) != len(self.boxes):
            self.seen = np.ones((len(self.boxes), 2), dtype=np.float32)


def to_sample(aligned_tensor: np.ndarray, presence: np.ndarray, size: tuple[int, int], boxes: np.ndarray,
              ignore: np.ndarray, meta: dict) -> Sample:
    w, h = size
    planes = np.round(aligned_tensor[:, :h, :w] * 255).astype(np.uint8)  # drop the stride padding
    return Sample(planes, presence.astype(np.float32), boxes.astype(np.float32).reshape(-1, 4), ignore, meta=meta)


def progress(iterable, enabled: bool, **kwargs):
    """tqdm when asked and stderr is a terminal (not a pipe, a file or the journal); the bare
    iterable otherwise (a disabled tqdm still starts its monitor thread)."""
    if not enabled or not sys.stderr.isatty():
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, leave=False, **kwargs)


def gt_arrays(gt: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    boxes = np.array([g["box"] for g in gt], dtype=np.float32).reshape(-1, 4)
    wh = boxes[:, 2:] - boxes[:, :2]
    ignore = np.array([g["visible"] < MIN_VISIBLE for g in gt], dtype=bool).reshape(-1)
    ignore |= (wh < MIN_BOX_PX).any(1)
    return boxes, ignore


# --- LLVIP layout ---------------------------------------------------------------------------------

def llvip_ids(root: Path, annotated_only: bool = True) -> list[str]:
    """Pair ids present in ``visible/`` and ``infrared/`` (and ``Annotations/`` if asked)."""
    for sub in ("visible", "infrared"):
        if not (root / sub).is_dir():
            raise InputError(
                f"{root}: not an LLVIP-layout folder (missing {sub}/; expected visible/, infrared/, Annotations/)"
            )
    ids = sorted(p.stem for p in (root / "visible").glob("*.jpg") if (root / "infrared" / p.name).is_file())
    if annotated_only:
        ids = [i for i in ids if (root / "Annotations" / f"{i}.xml").is_file()]
    if not ids:
        raise InputError(f"{root}: no {'annotated ' if annotated_only else ''}visible/infrared .jpg pairs found")
    return ids


def read_voc(path: Path, classes: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (M, 4) and class indices (M,) of a PASCAL-VOC XML file; other classes are skipped."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise InputError(f"{path}: not valid VOC XML ({err})") from err
    boxes, labels = [], []
    for obj in root.iter("object"):
        name = (obj.findtext("name") or "").strip()
        bnd = obj.find("bndbox")
        if name not in classes or bnd is None:
            continue
        try:
            boxes.append([float(bnd.findtext(k) or "nan") for k in ("xmin", "ymin", "xmax", "ymax")])
        except ValueError as err:
            raise InputError(f"{path}: object {name!r} has a non-numeric bndbox") from err
        labels.append(classes.index(name))
    return np.array(boxes, dtype=np.float32).reshape(-1, 4), np.array(labels, dtype=np.int64)


def llvip_frames(root: Path, pair_id: str) -> dict[str, Frame]:
    """The pair as Frames: BGR visible, 8-bit infrared (pixel-aligned, so no calibration)."""
    rgb = cv2.imread(str(root / "visible" / f"{pair_id}.jpg"), cv2.IMREAD_COLOR)
    ir = cv2.imread(str(root / "infrared" / f"{pair_id}.jpg"), cv2.IMREAD_GRAYSCALE)
    if rgb is None or ir is None:
        raise InputError(f"{root}: cannot decode the JPEG pair {pair_id}")
    return {"rgb": Frame("rgb", 0.0, 0, rgb), "thermal": Frame("thermal", 0.0, 0, ir)}


def llvip_sample(root: Path, pair_id: str, config: PerceptionConfig, scale: float = 0.5) -> Sample:
    """One annotated pair at ``scale`` of its 1280x1024 size (boxes scaled with it)."""
    frames = llvip_frames(root, pair_id)
    if scale != 1.0:
        frames = {k: Frame(f.modality, 0.0, 0, cv2.resize(f.data, None, fx=scale, fy=scale,
                                                          interpolation=cv2.INTER_AREA)) for k, f in frames.items()}
    aligned = Aligner(config).align(frames)
    boxes, labels = read_voc(root / "Annotations" / f"{pair_id}.xml", config.model.classes)
    sample = to_sample(aligned.tensor, aligned.presence, aligned.size, boxes * scale,
                       np.zeros(len(boxes), dtype=bool), {"scenario": "llvip", "id": pair_id})
    sample.labels = labels
    return sample


class LlvipSource:
    """Lazily decoded LLVIP pairs, so a full dataset does not have to fit in memory.

    The most recently used ``cache`` samples stay decoded (JPEG decoding of two 1280x1024
    images costs more than a training step's share of the batch).
    """

    def __init__(self, root: Path, config: PerceptionConfig, scale: float = 0.5, cache: int = 256) -> None:
        self.root, self.config, self.scale = root, config, scale
        self.ids = llvip_ids(root)
        self._load = functools.lru_cache(maxsize=cache)(self._decode)

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> Sample:
        s = self._load(i)  # augmentation writes into samples: hand out a copy
        return Sample(s.planes.copy(), s.presence.copy(), s.boxes.copy(), s.ignore.copy(), s.labels.copy(), s.meta)

    def _decode(self, i: int) -> Sample:
        return llvip_sample(self.root, self.ids[i], self.config, self.scale)
