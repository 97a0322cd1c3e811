"""Datasets for training and evaluation: the simulated rover and the LLVIP layout.

A ``Sample`` is the detector's aligned input (uint8 planes, to keep thousands in memory)
with its boxes. Simulated samples are rendered once into memory from many segments of a
seeded world (every segment draws its own light, people, distances, speeds and
occluders: that is the domain randomization), with sensor settings drawn per sample too.
LLVIP-layout folders (``visible/``, ``infrared/``, ``Annotations/*.xml``) load lazily.
"""

from __future__ import annotations

import functools
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
CONDITIONS: dict[str, tuple[str, ...]] = {
    "day": ("good-light-static", "good-light-moving"),
    "night": ("poor-light-static", "poor-light-moving"),
    "occlusion": ("occlusion-partial", "occlusion-smoke"),
    "motion": ("good-light-moving", "poor-light-moving"),
}


@dataclass
class Sample:
    planes: np.ndarray  # uint8 (C, H, W): R, G, B, aux... in 0..255 (x/255 = network input)
    presence: np.ndarray  # float32 (A,)
    boxes: np.ndarray  # float32 (M, 4) x1y1x2y2 pixels
    ignore: np.ndarray  # bool (M,)
    labels: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (M,)
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(self.labels) != len(self.boxes):
            self.labels = np.zeros(len(self.boxes), dtype=np.int64)


def to_sample(aligned_tensor: np.ndarray, presence: np.ndarray, size: tuple[int, int], boxes: np.ndarray,
              ignore: np.ndarray, meta: dict) -> Sample:
    w, h = size
    planes = np.round(aligned_tensor[:, :h, :w] * 255).astype(np.uint8)  # drop the stride padding
    return Sample(planes, presence.astype(np.float32), boxes.astype(np.float32).reshape(-1, 4), ignore, meta=meta)


# --- the simulated rover -------------------------------------------------------------------------

def progress(iterable, enabled: bool, **kwargs):
    """tqdm when asked; the bare iterable otherwise (a disabled tqdm still starts its monitor thread)."""
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, leave=False, **kwargs)


def sim_samples(config: PerceptionConfig, seed: int, segments: int, per_segment: int,
                rgb_size: tuple[int, int] = (640, 360), scenarios: tuple[str, ...] | None = None,
                randomize_sensors: bool = True, show_progress: bool = False) -> list[Sample]:
    """Render ``segments x per_segment`` samples from the world of ``seed``.

    Segment ``i`` runs scenario ``i mod 6`` (or of ``scenarios``) with its own random draw;
    times inside it are uniform. With ``randomize_sensors`` the RGB rate (hence exposure
    and blur), thermal resolution and radar mode vary per sample.
    """
    from respecd.sim.world import SCENARIOS, SimulationConfig, World

    names = list(scenarios or SCENARIOS)
    sim = SimulationConfig(scenarios=names, loop=True)
    world = World(sim, seed)
    aligner = Aligner(config)
    rng = np.random.default_rng([seed, 7])
    out: list[Sample] = []
    for i in progress(range(segments * per_segment), show_progress, desc="render", unit="frame"):
        t = (i // per_segment + rng.uniform(0.02, 0.98)) * sim.scenario_duration_s
        out.append(render_sample(world.state_at(t), aligner, rng, rgb_size, randomize_sensors))
    return out


def render_sample(state, aligner: Aligner, rng: np.random.Generator, rgb_size: tuple[int, int],
                  randomize: bool) -> Sample:
    """All modalities of one simulated instant -> aligned Sample with ground truth."""
    from respecd.sim.render import ground_truth, render_depth, render_radar, render_rgb, render_thermal

    rate = float(rng.choice([5.0, 10.0, 15.0, 30.0])) if randomize else 30.0
    t_res = ((160, 120), (320, 240))[int(rng.integers(2))] if randomize else (160, 120)
    mode = ("range", "velocity")[int(rng.integers(2))] if randomize else "range"
    data = {
        "rgb": render_rgb(state, rgb_size, 1.0 / rate, rng),
        "thermal": render_thermal(state, t_res, rng),
        "radar": render_radar(state, mode, 10.0, rng),
    }
    if "depth" in aligner.aux:
        data["depth"] = render_depth(state, (640, 480), rng)
    frames = {k: Frame(modality=k, t=state.t, seq=0, data=v) for k, v in data.items()}  # type: ignore[arg-type]
    aligned = aligner.align(frames)
    boxes, ignore = gt_arrays(ground_truth(state, rgb_size))
    meta = {"scenario": state.scenario, "light": state.light, "t": state.t}
    return to_sample(aligned.tensor, aligned.presence, aligned.size, boxes, ignore, meta)


def gt_arrays(gt: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    boxes = np.array([g["box"] for g in gt], dtype=np.float32).reshape(-1, 4)
    wh = boxes[:, 2:] - boxes[:, :2]
    ignore = np.array([g["visible"] < MIN_VISIBLE for g in gt], dtype=bool).reshape(-1)
    ignore |= (wh < MIN_BOX_PX).any(1)
    return boxes, ignore


def condition_of(scenario: str) -> list[str]:
    return [c for c, names in CONDITIONS.items() if scenario in names]


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
