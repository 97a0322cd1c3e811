"""Real image folders in the formats people have: LLVIP/VOC pairs, COCO json, YOLO txt.

``open_folder(root)`` recognises the layout and returns the train and validation items;
``FolderSource`` decodes them lazily into detector ``Sample``s (RGB planes, the aligned aux
planes, presence flags, boxes). A set with one modality (HIT-UAV is thermal only) trains
the branch it has: the other planes are zero and their presence 0, as for a sensor that
is off.

* **LLVIP / VOC**: ``visible/``, ``infrared/`` (either may be missing), ``Annotations/*.xml``.
* **COCO**: ``annotations/*.json`` (or ``*.json`` in the folder) naming images relative to
  the json's split folder; tolerated spellings: ``annotation`` for ``annotations`` and
  ``filename`` for ``file_name`` (HIT-UAV's export); categories matched to the model's
  classes by name, case-insensitively; ``DontCare`` boxes and ``iscrowd`` become ignore boxes.
* **YOLO**: ``images/<split>/*.jpg`` with ``labels/<split>/*.txt`` (``class cx cy w h``,
  normalised), class names from ``data.yaml`` / ``classes.txt`` / ``obj.names`` (else class
  0 is the first model class).

Splits: a ``val`` split (json, folder) is the validation set; without one, a seeded 10 %
of the images is held out. Single-channel images count as thermal, colour ones as RGB,
unless ``modality`` says otherwise.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from respecd.errors import InputError
from respecd.lab.detector.data import Sample, read_voc, to_sample
from respecd.messages import Frame
from respecd.perception.align import Aligner
from respecd.perception.config import PerceptionConfig

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
IGNORE_NAMES = ("dontcare", "ignore", "ignored")
VAL_SHARE = 0.1


@dataclass(frozen=True)
class Item:
    """One annotated image (or pixel-aligned pair); boxes x1y1x2y2 in its own pixels."""

    key: str
    rgb: Path | None
    thermal: Path | None
    boxes: np.ndarray  # (M, 4) float32
    labels: np.ndarray  # (M,) int64
    ignore: np.ndarray  # (M,) bool


@dataclass
class Folder:
    kind: str  # "voc", "coco", "yolo"
    root: Path
    train: list[Item]
    val: list[Item]
    notes: list[str] = field(default_factory=list)

    @property
    def modalities(self) -> set[str]:
        return {m for it in self.train + self.val for m in ("rgb", "thermal") if getattr(it, m) is not None}


def open_folder(root: Path, classes: tuple[str, ...], modality: str = "auto", seed: int = 0,
                hold_out: bool = True) -> Folder:
    """Recognise the layout of ``root`` and read its annotations (not its pixels).

    ``hold_out``: without a val split, hold out a seeded share of the images for validation.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"--data {root}: no such folder")
    if (root / "Annotations").is_dir() and ((root / "visible").is_dir() or (root / "infrared").is_dir()):
        items, kind = _voc_items(root, classes), "voc"
        splits = {"train": items}
    elif _coco_files(root):
        splits, kind = _coco_splits(root, classes, modality), "coco"
    elif (root / "labels").is_dir() or any(root.glob("*.txt")):
        splits, kind = _yolo_splits(root, classes, modality), "yolo"
    else:
        raise InputError(f"--data {root}: not a dataset folder (expected visible/ + infrared/ + Annotations/ "
                         "(LLVIP/VOC), annotations/*.json (COCO) or images/ + labels/ (YOLO))")
    train = [it for name, items in splits.items() if name != "val" for it in items]
    val = splits.get("val", [])
    notes = []
    if not val and len(train) > 1 and hold_out:
        order = np.random.default_rng(seed).permutation(len(train))
        n_val = max(1, int(round(VAL_SHARE * len(train))))
        val = [train[i] for i in sorted(order[:n_val])]
        train = [train[i] for i in sorted(order[n_val:])]
        notes.append(f"no val split: held out a seeded {n_val} of {len(train) + n_val} images")
    if not train and not val:
        raise InputError(f"--data {root}: no annotated images found ({kind} layout)")
    return Folder(kind, root, train, val, notes)


# --- LLVIP / VOC ---------------------------------------------------------------------------------

def _voc_items(root: Path, classes: tuple[str, ...]) -> list[Item]:
    items = []
    for xml in sorted((root / "Annotations").glob("*.xml")):
        rgb, thermal = _find_image(root / "visible", xml.stem), _find_image(root / "infrared", xml.stem)
        if rgb is None and thermal is None:
            continue
        boxes, labels = read_voc(xml, classes)
        items.append(Item(xml.stem, rgb, thermal, boxes, labels, np.zeros(len(boxes), dtype=bool)))
    return items


def _find_image(folder: Path, stem: str) -> Path | None:
    for suffix in IMAGE_SUFFIXES:
        path = folder / f"{stem}{suffix}"
        if path.is_file():
            return path
    return None


# --- COCO ----------------------------------------------------------------------------------------

def _coco_files(root: Path) -> list[Path]:
    found = sorted((root / "annotations").glob("*.json")) if (root / "annotations").is_dir() else []
    return found or sorted(root.glob("*.json"))


def _coco_splits(root: Path, classes: tuple[str, ...], modality: str) -> dict[str, list[Item]]:
    splits: dict[str, list[Item]] = {}
    for path in _coco_files(root):
        split = path.stem.lower().removeprefix("instances_")
        split = "val" if split.startswith("val") else split
        splits.setdefault(split, []).extend(_coco_items(path, root, classes, modality))
    return splits


def _coco_items(path: Path, root: Path, classes: tuple[str, ...], modality: str) -> list[Item]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"{path}: not readable COCO json ({err})") from err
    anns = doc.get("annotations", doc.get("annotation"))
    if not isinstance(doc.get("images"), list) or not isinstance(anns, list):
        raise InputError(f"{path}: COCO json needs lists 'images' and 'annotations' (or 'annotation')")
    wanted = {c.lower(): i for i, c in enumerate(classes)}
    category = {}
    for cat in doc.get("categories", []):
        name = str(cat.get("name", "")).lower()
        category[cat.get("id")] = wanted.get(name, -2 if name in IGNORE_NAMES else -1)
    by_image: dict[object, list[dict]] = {}
    for i, ann in enumerate(anns):
        if not isinstance(ann, dict) or "image_id" not in ann or len(ann.get("bbox", [])) != 4:
            raise InputError(f"{path}: annotation #{i} needs image_id and bbox [x, y, w, h]")
        by_image.setdefault(ann["image_id"], []).append(ann)
    folders = [path.parent.parent / path.stem, root / path.stem, root / "images" / path.stem, root / "images", root]
    items = []
    for image in doc["images"]:
        name = image.get("file_name", image.get("filename"))
        if name is None:
            raise InputError(f"{path}: image id {image.get('id')} has no file_name (or filename)")
        file = next((f / name for f in folders if (f / name).is_file()), None)
        if file is None:
            raise InputError(f"{path}: image {name} not found beside it (looked in {folders[0]}, {folders[2]}, ...)")
        modality = image_modality(file) if modality == "auto" else modality  # one look per json file
        items.append(_coco_item(file, by_image.get(image.get("id"), []), category, modality))
    return items


def _coco_item(file: Path, anns: list[dict], category: dict, modality: str) -> Item:
    boxes, labels, ignore = [], [], []
    for ann in anns:
        label = category.get(ann.get("category_id"), -1)
        if label == -1:
            continue
        x, y, w, h = (float(v) for v in ann["bbox"])
        boxes.append([x, y, x + w, y + h])
        labels.append(max(label, 0))
        ignore.append(label == -2 or bool(ann.get("iscrowd", 0)))
    return _single(file, boxes, labels, ignore, modality)


def _single(file: Path, boxes: list, labels: list, ignore: list, modality: str) -> Item:
    return Item(file.stem, file if modality == "rgb" else None, file if modality == "thermal" else None,
                np.array(boxes, dtype=np.float32).reshape(-1, 4), np.array(labels, dtype=np.int64),
                np.array(ignore, dtype=bool))


def image_modality(file: Path) -> str:
    """'thermal' for single-channel images (and 3-channel ones whose channels are equal), else 'rgb'."""
    img = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{file}: cannot decode the image")
    if img.ndim == 2 or img.shape[2] == 1:
        return "thermal"
    sample = img[::7, ::7, :3].astype(np.int16)
    return "thermal" if np.abs(sample - sample[:, :, :1]).max() <= 2 else "rgb"


# --- YOLO ----------------------------------------------------------------------------------------

def _yolo_splits(root: Path, classes: tuple[str, ...], modality: str) -> dict[str, list[Item]]:
    names = _yolo_names(root)
    mapping = {i: classes.index(n) if n in classes else -1 for i, n in enumerate(names)} if names else {0: 0}
    image_dir = root / "images" if (root / "images").is_dir() else root
    subdirs = [d for d in sorted(image_dir.iterdir()) if d.is_dir()] or [image_dir]
    splits: dict[str, list[Item]] = {}
    for folder in subdirs:
        split = "val" if folder.name.lower().startswith("val") else folder.name
        images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        mod = image_modality(images[0]) if modality == "auto" and images else modality  # one look per folder
        for image in images:
            label_file = _yolo_label_path(root, image)
            if label_file is not None:
                splits.setdefault(split, []).append(_yolo_item(image, label_file, mapping, mod))
    return splits


def _yolo_names(root: Path) -> list[str]:
    for name in ("classes.txt", "obj.names"):
        if (root / name).is_file():
            return [n.strip().lower() for n in (root / name).read_text(encoding="utf-8").splitlines() if n.strip()]
    if (root / "data.yaml").is_file():
        import yaml

        doc = yaml.safe_load((root / "data.yaml").read_text(encoding="utf-8")) or {}
        names = doc.get("names", [])
        if isinstance(names, dict):
            names = [names[k] for k in sorted(names)]
        return [str(n).lower() for n in names]
    return []


def _yolo_label_path(root: Path, image: Path) -> Path | None:
    beside = image.with_suffix(".txt")
    if beside.is_file():
        return beside
    try:
        rel = image.relative_to(root / "images")
    except ValueError:
        return None
    path = (root / "labels" / rel).with_suffix(".txt")
    return path if path.is_file() else None


def _yolo_item(image: Path, labels_path: Path, mapping: dict[int, int], modality: str) -> Item:
    img = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{image}: cannot decode the image")
    h, w = img.shape[:2]
    boxes, labels = [], []
    for number, line in enumerate(labels_path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            fields = line.split()
            c, values = int(fields[0]), [float(v) for v in fields[1:5]]
            if len(values) != 4:
                raise ValueError(line)
        except ValueError as err:
            raise InputError(f"{labels_path}:{number}: expected 'class cx cy w h', found {line.strip()!r}") from err
        if not all(math.isfinite(v) for v in values) or mapping.get(c, -1) < 0:
            continue
        cx, cy, bw, bh = values
        boxes.append([(cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h])
        labels.append(mapping[c])
    return _single(image, boxes, labels, [False] * len(boxes), modality)


# --- decoding ------------------------------------------------------------------------------------

def item_frames(item: Item) -> dict[str, Frame]:
    frames = {}
    if item.rgb is not None:
        rgb = cv2.imread(str(item.rgb), cv2.IMREAD_COLOR)
        if rgb is None:
            raise InputError(f"{item.rgb}: cannot decode the image")
        frames["rgb"] = Frame("rgb", 0.0, 0, rgb)
    if item.thermal is not None:
        ir = cv2.imread(str(item.thermal), cv2.IMREAD_GRAYSCALE)
        if ir is None:
            raise InputError(f"{item.thermal}: cannot decode the image")
        frames["thermal"] = Frame("thermal", 0.0, 0, ir)
    return frames


def item_sample(item: Item, config: PerceptionConfig, scale: float = 1.0, scenario: str = "real") -> Sample:
    """The item at ``scale`` as a detector Sample (pixel-aligned pairs: no calibration needed)."""
    frames = item_frames(item)
    if "rgb" not in frames:  # thermal only: the RGB view is the thermal image's own grid
        ir = frames["thermal"].data
        frames["rgb"] = Frame("rgb", 0.0, 0, np.zeros((*ir.shape[:2], 3), np.uint8))
    if scale != 1.0:
        frames = {k: Frame(f.modality, 0.0, 0, cv2.resize(f.data, None, fx=scale, fy=scale,
                                                          interpolation=cv2.INTER_AREA if scale < 1 else
                                                          cv2.INTER_LINEAR)) for k, f in frames.items()}
    aligned = Aligner(config).align(frames)
    sample = to_sample(aligned.tensor, aligned.presence, aligned.size, item.boxes * scale, item.ignore.copy(),
                       {"scenario": scenario, "id": item.key, "rgb": item.rgb is not None})
    sample.labels = item.labels.copy()
    return sample


class FolderSource:
    """Lazily decoded items (the most recent ``cache`` kept), indexable like a list of Samples."""

    def __init__(self, items: list[Item], config: PerceptionConfig, scale: float = 1.0, cache: int = 256,
                 scenario: str = "real") -> None:
        self.items, self.config, self.scale, self.scenario = items, config, scale, scenario
        self._load = functools.lru_cache(maxsize=cache)(self._decode)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> Sample:
        s = self._load(i)  # augmentation writes into samples: hand out a copy
        return Sample(s.planes.copy(), s.presence.copy(), s.boxes.copy(), s.ignore.copy(), s.labels.copy(),
                      dict(s.meta))

    def _decode(self, i: int) -> Sample:
        return item_sample(self.items[i], self.config, self.scale, self.scenario)
