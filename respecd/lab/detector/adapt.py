"""``respecd adapt``: teach the detector's thermal path from the rover's own recordings, without labels.

In good light the RGB camera finds people well; the thermal path is what fails in the dark when
its training never saw this camera. So the RGB detector (the checkpoint itself, RGB alone, or
``teacher``) labels the recorded RGB frames, and the thermal path learns to find the same people
in the thermal frames recorded beside them:

* **Teacher boxes.** RGB frames of ``every_s`` spacing, bright enough (mean level >= ``min_light``
  of 255: the teacher is trusted in good light only), run through the teacher with every other
  sensor off, exactly as the daemon runs it. Boxes at or above ``confident`` are the labels; a frame
  with a box between ``unsure`` and ``confident`` is left out (its people would be taught as
  background), as is a frame without its thermal partner.
* **The thermal view.** Each frame pair is aligned as the perception stage aligns it, with the
  session's recorded calibration (``perception/align.py``: thermal warped into the RGB view), so
  the RGB boxes are the thermal image's boxes, and what is learned is what the daemon will see.
* **Student.** The checkpoint trains with the shared loop (``train.train``) on crops of these
  pairs, with modality dropout that mostly leaves thermal alone; everything that also serves RGB
  stays frozen (``default_freeze``), so the RGB detector is the one that taught.
* **Held back.** ``val_share`` of the frames, whole ``block_s`` stretches of a session (neighbouring
  frames are near copies), never trained on: they choose the epoch and give the before/after
  scores, mAP@0.5 against the teacher's boxes with thermal only, with every recorded sensor on and
  with RGB only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import structlog
import torch
import torch.nn.functional as F
from torch import nn

from respecd.errors import InputError
from respecd.lab.detector.augment import AugmentConfig
from respecd.lab.detector.data import Sample, progress, to_sample
from respecd.lab.detector.recorded import Recording, open_recording, paired_frames
from respecd.messages import Frame
from respecd.perception import checkpoint
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.model import FusionNet

log = structlog.get_logger(__name__)

ALIGNMENT_KEYS = ("thermal_range_k", "thermal_counts_per_k", "plane_depth_m", "radar_max_range_m", "depth_max_m")
# which sensors stay on in a training crop: mostly thermal alone (what is learned), with RGB so that
# thermal beside a seeing RGB camera is not pushed away, and RGB alone so the sensor-off input stays put
KEEP = ((("thermal",), 0.35), (("thermal", "radar"), 0.2), (("rgb", "thermal"), 0.1),
        (("rgb", "thermal", "radar"), 0.15), (("rgb",), 0.1), (("rgb", "radar"), 0.1))
ANCHOR_WEIGHT = 10.0  # SensorsOff: the squared feature drift counts this much beside the detection loss
VIEWS = ("thermal only", "every sensor", "RGB only")


@dataclass(frozen=True)
class AdaptConfig:
    logs: tuple[Path, ...]
    out: Path
    weights: str  # the checkpoint whose thermal path learns
    teacher: str | None = None  # the RGB detector that labels (default: ``weights``, RGB alone)
    profile: dict[str, Any] | None = None  # replaces every log's recorded profile (its calibration)
    confident: float = 0.5
    unsure: float = 0.2
    min_light: float = 20.0
    every_s: float = 0.5
    max_skew_s: float = 0.1
    width: int = 640  # RGB frames are scaled down to this width (never up)
    val_share: float = 0.2
    block_s: float = 10.0
    epochs: int = 8
    steps: int = 100
    batch: int = 8
    lr: float = 2e-3
    crop: tuple[int, int] = (320, 192)
    freeze: tuple[str, ...] | None = None  # None: default_freeze(the net)
    seed: int = 0
    threads: int = 1
    progress: bool = True


@dataclass
class Frames:
    """The labelled frames of the sessions and what was left out, by reason."""

    samples: list[Sample] = field(default_factory=list)
    keys: list[tuple[int, int]] = field(default_factory=list)  # (log, block) per sample
    seen: int = 0
    dark: int = 0
    unsure: int = 0
    boxes: int = 0


def default_freeze(model: checkpoint.Net) -> tuple[str, ...]:
    """Every part that also serves RGB: the thermal path (backbone 2, and the Darknet net's fusion
    maps from it) is what trains."""
    from respecd.perception.darknet_fusion import DarknetFusionNet

    if isinstance(model, DarknetFusionNet):
        return ("rgb", "head", "fuse.*.rgb")
    return ("rgb", "neck", "head")


def adapt(cfg: AdaptConfig) -> dict[str, Any]:
    """Label, train, score; the checkpoint and its card are written to ``cfg.out``. Returns the summary."""
    from respecd.lab.detector.train import TrainConfig, train

    recordings = [open_recording(p, cfg.profile) for p in cfg.logs]  # every log checked before any work
    spec = checkpoint.spec_of(cfg.weights)
    if "thermal" not in spec.aux_modalities:
        raise InputError(f"{cfg.weights}: the net has no thermal input (aux modalities: "
                         f"{', '.join(spec.aux_modalities) or 'none'}); nothing to adapt")
    for rec in recordings:
        if rec.truncated:
            log.warning("adapt.truncated_log", path=str(rec.path), readable_s=round(rec.session.duration_s, 2))
    frames = label_frames(recordings, spec, cfg)
    train_set, val_set = split_frames(frames, cfg.val_share, cfg.seed)
    if not train_set or not val_set:
        raise InputError(f"{', '.join(map(str, cfg.logs))}: {len(frames.samples)} usable frames (of {frames.seen}: "
                         f"{frames.dark} too dark, {frames.unsure} with unsure teacher boxes); adapt needs frames "
                         "to train on and to hold back: record more good-light time")
    views = {name: [view(s, name, spec.aux_modalities) for s in val_set] for name in VIEWS}
    before = scores(checkpoint.load(cfg.weights)[0], views)
    model = checkpoint.load(cfg.weights)[0]
    freeze = cfg.freeze if cfg.freeze is not None else default_freeze(model)
    augment = AugmentConfig(size=cfg.crop, keep=KEEP, mosaic=0.3)
    tcfg = TrainConfig(data=f"{len(cfg.logs)} recorded sessions", out=cfg.out, epochs=cfg.epochs, batch=cfg.batch,
                       lr=cfg.lr, seed=cfg.seed, steps_per_epoch=cfg.steps, threads=cfg.threads,
                       progress=cfg.progress, augment=augment, init=cfg.weights, freeze=freeze,
                       extra_loss=SensorsOff(model, cfg.crop) if isinstance(model, FusionNet) else None)
    summary = train(tcfg, PerceptionConfig(model=spec), data=(_crops(train_set, tcfg, spec), views["thermal only"]))
    after = scores(checkpoint.load(str(cfg.out))[0], views)
    report = {"logs": [str(p) for p in cfg.logs], "weights": cfg.weights, "teacher": cfg.teacher or cfg.weights,
              "frames": {"seen": frames.seen, "too_dark": frames.dark, "unsure": frames.unsure,
                         "train": len(train_set), "held_out": len(val_set), "teacher_boxes": frames.boxes},
              "settings": _settings(cfg, freeze), "before": before, "after": after,
              "best_epoch": summary["best_epoch"], "train_s": summary["train_s"]}
    _finish(cfg, report, summary)
    return report


class SensorsOff:
    """The CSP net's neck reads backbone 2's features beside RGB's, so with every aux sensor off the RGB
    detector sees backbone 2's answer to an empty input, a constant it was trained with. Training backbone 2
    moves that constant, and RGB alone stops detecting; this term (``ANCHOR_WEIGHT`` x the mean squared
    difference, at the crop size, backbone 2 in eval mode as at run time) keeps it where it started.
    The Darknet net needs none: with the aux sensors off its fusion adds nothing."""

    def __init__(self, model: FusionNet, crop: tuple[int, int]) -> None:
        n = len(model.spec.aux_modalities)
        self.planes, self.presence = torch.zeros(1, n, crop[1], crop[0]), torch.zeros(1, n)
        with torch.no_grad():
            self.target = [f.detach() for f in self.features(model)]

    def features(self, model: FusionNet) -> list[torch.Tensor]:
        modes = [(m, m.training) for m in model.aux.modules()]
        model.aux.eval()
        try:
            return list(model.encode_aux(self.planes, self.presence))
        finally:
            for module, training in modes:
                module.training = training

    def __call__(self, model: nn.Module) -> torch.Tensor:
        assert isinstance(model, FusionNet)
        drift = [F.mse_loss(f, t) for f, t in zip(self.features(model), self.target, strict=True)]
        return ANCHOR_WEIGHT * torch.stack(drift).sum()


def label_frames(recordings: list[Recording], spec: ModelSpec, cfg: AdaptConfig) -> Frames:
    """The teacher's boxes on every usable frame pair, as aligned samples of the student's input."""
    from respecd.perception.align import Aligner
    from respecd.perception.detector import FusionDetector

    teacher_weights = cfg.teacher or cfg.weights
    teacher = FusionDetector.load(PerceptionConfig(weights=teacher_weights, score_threshold=cfg.unsure,
                                                   model=checkpoint.spec_of(teacher_weights)))
    out = Frames()
    for index, rec in enumerate(recordings):
        alignment = {k: v for k, v in rec.perception.items() if k in ALIGNMENT_KEYS}
        aligner = Aligner(PerceptionConfig(model=spec, **alignment), rec.calibration)
        start = None
        pairs = paired_frames(rec, spec.aux_modalities, cfg.every_s, cfg.max_skew_s)
        for frames in progress(pairs, cfg.progress, desc=f"label {rec.path.name}", unit="frame"):
            out.seen += 1
            start = frames["rgb"].t if start is None else start
            rgb = _scaled(frames["rgb"], cfg.width)
            if float(rgb.data.mean()) < cfg.min_light:
                out.dark += 1
                continue
            found = teacher.infer({"rgb": rgb}, attribute=False).detections
            if any(d.confidence < cfg.confident for d in found):
                out.unsure += 1
                continue
            aligned = aligner.align({**frames, "rgb": rgb})
            boxes = np.array([d.box for d in found], np.float32).reshape(-1, 4)
            sample = to_sample(aligned.tensor, aligned.presence, aligned.size, boxes, np.zeros(len(boxes), bool),
                               {"scenario": rec.path.stem, "t": frames["rgb"].t})
            out.samples.append(sample)
            out.keys.append((index, int((frames["rgb"].t - start) // cfg.block_s)))
            out.boxes += len(boxes)
    return out


def _scaled(frame: Frame, width: int) -> Frame:
    """The RGB frame at ``width`` (never enlarged); the aligner scales the intrinsics with it."""
    h, w = frame.data.shape[:2]
    if w <= width:
        return Frame(frame.modality, frame.t, frame.seq, frame.data, frame.meta)
    size = (width, max(1, round(h * width / w)))
    return Frame(frame.modality, frame.t, frame.seq, cv2.resize(frame.data, size, interpolation=cv2.INTER_AREA),
                 frame.meta)


def split_frames(frames: Frames, share: float, seed: int) -> tuple[list[Sample], list[Sample]]:
    """Whole blocks (a session's ``block_s`` stretches) held back, a seeded ``share`` of them; with
    fewer than two blocks, single frames instead."""
    keys = frames.keys if len(set(frames.keys)) >= 2 else [(0, i) for i in range(len(frames.samples))]
    blocks = sorted(set(keys))
    if len(blocks) < 2:
        return frames.samples, []
    order = np.random.default_rng([seed, 17]).permutation(len(blocks))
    held = {blocks[i] for i in order[:max(1, round(share * len(blocks)))]}
    train = [s for s, k in zip(frames.samples, keys, strict=True) if k not in held]
    val = [s for s, k in zip(frames.samples, keys, strict=True) if k in held]
    return train, val


def view(sample: Sample, name: str, aux: tuple[str, ...]) -> Sample:
    """The held-back frame as one of ``VIEWS`` sees it: sensors off as the daemon feeds them (zero, presence 0)."""
    planes, presence = sample.planes.copy(), sample.presence.copy()
    if name != "every sensor":
        for i, modality in enumerate(aux):
            if name == "RGB only" or modality != "thermal":
                planes[3 + i] = 0
                presence[i] = 0
    if name == "thermal only":
        planes[:3] = 0
    return Sample(planes, presence, sample.boxes.copy(), sample.ignore.copy(), sample.labels.copy(), dict(sample.meta))


def scores(model: checkpoint.Net, views: dict[str, list[Sample]]) -> dict[str, float | None]:
    """mAP@0.5 against the teacher's boxes per view of the held-back frames."""
    from respecd.lab.detector.finetune import finite, validation_map

    return {name: finite(validation_map(model, samples)) for name, samples in views.items()}


def _crops(samples: list[Sample], tcfg: Any, spec: ModelSpec) -> Any:
    from respecd.lab.detector.train import CropSource

    return CropSource([(samples, tcfg.augment, 1.0)], tcfg, spec.aux_modalities)


def _settings(cfg: AdaptConfig, freeze: tuple[str, ...]) -> dict[str, Any]:
    keys = ("confident", "unsure", "min_light", "every_s", "max_skew_s", "width", "val_share", "block_s", "epochs",
            "steps", "batch", "lr", "seed")
    return {**{k: getattr(cfg, k) for k in keys}, "crop": list(cfg.crop), "freeze": list(freeze)}


def _finish(cfg: AdaptConfig, report: dict[str, Any], summary: dict[str, Any]) -> None:
    """The adapted checkpoint keeps the start's confidence calibration (its RGB path did not move),
    and its card says how it was made."""
    start = checkpoint.read(checkpoint.resolve(cfg.weights))
    payload = checkpoint.read(cfg.out)
    if start.get("score_calibration") is not None:
        payload["score_calibration"] = start["score_calibration"]
    payload["adapt"] = report
    checkpoint.save_payload(cfg.out, payload)
    model = checkpoint.load(str(cfg.out))[0]
    card = {"name": cfg.out.stem, "data": f"adapted from {len(cfg.logs)} recorded sessions (respecd adapt)",
            "adapt": report, "train": summary}
    checkpoint.write_card(cfg.out, model, card)
