"""Evaluation: mAP with and without each modality, and mean contributions per condition.

Held-out simulated frames come from world seeds the training never uses (training uses
``seed``; evaluation ``EVAL_SEED`` onwards), at the profile's default sensor settings.
Removing a modality zeroes its channel and clears its presence flag, exactly what the
daemon feeds the detector when that sensor is off.
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import torch

from respecd.lab.detector.data import CONDITIONS, Sample, condition_of
from respecd.lab.detector.metrics import ImageResult, mean_ap
from respecd.perception.attribution import grouped
from respecd.perception.detector import FusionDetector

EVAL_SEED = 1_000_003  # far from any training seed


def ablations(aux: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    """Name -> modalities removed: all on, each one off, and RGB alone."""
    out: dict[str, tuple[str, ...]] = {"all": ()}
    for name in ("rgb", *aux):
        out[f"no-{name}"] = (name,)
    out["rgb-only"] = tuple(aux)
    return out


def sim_eval_set(pcfg, per_scenario: int, rgb_size: tuple[int, int] = (640, 360), seed: int = EVAL_SEED,
                 progress: bool = False) -> list[Sample]:
    """``per_scenario`` frames of each scenario, one random draw (segment) per 2 frames."""
    from respecd.lab.detector.data import sim_samples

    segments = max(1, per_scenario // 2) * 6
    return sim_samples(pcfg, seed, segments, 2, rgb_size, randomize_sensors=False, show_progress=progress)


def sample_input(sample: Sample, aux: tuple[str, ...], removed: tuple[str, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample -> padded (1, C, Hp, Wp) tensor and (1, A) presence, with ``removed`` zeroed."""
    from respecd.perception.boxes import pad_to_stride

    c, h, w = sample.planes.shape
    hp, wp = pad_to_stride(h, w)
    x = np.zeros((1, c, hp, wp), dtype=np.float32)
    x[0, :, :h, :w] = sample.planes / np.float32(255)
    presence = sample.presence.copy()
    for name in removed:
        if name == "rgb":
            x[0, :3] = 0
        else:
            i = aux.index(name)
            x[0, 3 + i] = 0
            presence[i] = 0
    return torch.from_numpy(x), torch.from_numpy(presence[None])


def evaluate(detector: FusionDetector, samples: list[Sample], attribute: bool = True, progress: bool = False) -> dict:
    """{"map": {condition: {ablation: {map50, map50_95}}}, "contributions": {condition: {...}}, "frames": {...}}."""
    from respecd.lab.detector.data import progress as progress_bar

    aux = detector.model.spec.aux_modalities
    results: dict[str, dict[str, list[ImageResult]]] = defaultdict(lambda: defaultdict(list))
    contrib: dict[str, list[dict[str, float]]] = defaultdict(list)
    for sample in progress_bar(samples, progress, desc="eval"):
        conds = ["all", *(condition_of(sample.meta.get("scenario", "")) or [sample.meta.get("scenario", "data")])]
        for name, removed in ablations(aux).items():
            x, presence = sample_input(sample, aux, removed)
            scores = _predict(detector, x, presence, attribute and name == "all")
            image = ImageResult(scores[0], scores[1], sample.boxes, sample.ignore)
            for cond in conds:
                results[cond][name].append(image)
            if scores[2] is not None:
                for cond in conds:
                    contrib[cond].append(scores[2])
    return {
        "map": {cond: {name: mean_ap(images) for name, images in by.items()} for cond, by in results.items()},
        "contributions": {cond: _mean_dict(rows) for cond, rows in contrib.items()},
        "frames": {cond: len(by["all"]) for cond, by in results.items()},
        "attributed": {cond: len(rows) for cond, rows in contrib.items()},
        "detections": {cond: {name: detection_count(images) for name, images in by.items()}
                       for cond, by in results.items()},
    }


def detection_count(images: list[ImageResult], threshold: float | None = None) -> int:
    """Detections at the daemon's operating threshold (the profile default), as the paper counts them."""
    if threshold is None:
        from respecd.perception.config import PerceptionConfig

        threshold = PerceptionConfig().score_threshold
    return int(sum((im.pred_scores >= threshold).sum() for im in images))


def _predict(detector: FusionDetector, x: torch.Tensor, presence: torch.Tensor, attribute: bool):
    from respecd.perception.attribution import attribute as attribute_fn
    from respecd.perception.boxes import postprocess

    cfg, model = detector.config, detector.model
    if attribute:
        dets, _, scene = attribute_fn(model, x, presence, cfg.score_threshold, cfg.iou_threshold,
                                      cfg.max_detections, cfg.attribution_targets)
        contributions = grouped(model.spec.channels, scene) if scene is not None else None
    else:
        with torch.inference_mode():
            boxes, scores = model.decode(model(x, presence), tuple(x.shape[2:]))
            dets = postprocess(boxes, scores, tuple(x.shape[2:]), cfg.score_threshold, cfg.iou_threshold,  # type: ignore[assignment]
                               cfg.max_detections)[0]
        contributions = None
    return dets[0].detach().numpy(), dets[1].detach().numpy(), contributions


def _mean_dict(rows: list[dict[str, float]]) -> dict[str, float]:
    if not rows:
        return {}
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def condition_order(report: dict) -> list[str]:
    known = [c for c in ("all", *CONDITIONS) if c in report["map"]]
    return known + sorted(c for c in report["map"] if c not in known)
