"""Evaluation: accuracy per RGB resolution, the cost of each sensor, contributions and whether
their ranking is faithful.

Held-out simulated instants come from a world seed training never uses (``EVAL_SEED``),
two per scenario run, at the profile's default sensor settings and the daemon's alignment.
Per instant:

* at each RGB resolution the controller can choose, the detector with every sensor on:
  mAP@0.5 per condition (``by_resolution``) and which head level each detection came from, and
  ``delivered_map50``: mAP@0.5 of only the boxes the daemon delivers (its score threshold) —
  what the robot gets, and what the benchmark of docs/RESULTS.md scores;
* at the attribution resolution (640x360 unless asked), every sensor on and each one off
  (zero plane, presence 0: what the daemon feeds a disabled sensor): mAP per condition
  (``ablation``, and ``map`` with mAP@0.5:0.95 too);
* at the daemon's operating point (its score threshold and ``attribution_targets``), the
  contributions of the configured method (``contributions``: mean scene score over frames
  with a detection); with ``ablation`` also per sensor the share of the attributed boxes'
  confidence lost with it off (``dependence``), kept with only it on (``sufficiency``) and its
  exact Shapley value over the sensor subsets (``shapley``, same share; while at most three
  sensors are on), and the share the whole sensor-off pass below measures them to lose
  (``lost_when_off``: what ``dependence`` predicts), means over the same frames; and the
  deletion test (``faithfulness``): for each attributed box its
  confidence with a sensor off is the best detection overlapping it (IoU >= 0.5) in that
  sensor-off pass, 0 if none; the box counts as faithful when switching off its top-ranked
  modality costs more confidence than switching off its second-ranked one.

Detections are scored down to confidence 0.01 for mAP (the usual protocol).
"""

from __future__ import annotations

import itertools
from collections import defaultdict
from collections.abc import Iterator

import numpy as np
import torch

from respecd.lab.detector.data import Sample
from respecd.lab.detector.metrics import ImageResult, average_precision, false_box_kinds, iou_matrix, mean_ap
from respecd.perception.ablation import Ablation, kept_share, shapley
from respecd.perception.attribution import Attribution, Attributor
from respecd.perception.boxes import pad_to_stride, postprocess
from respecd.perception.config import PerceptionConfig
from respecd.perception.detector import FusionDetector
from respecd.perception.model import STRIDES

EVAL_SEED = 1_000_003  # far from any training seed
OPERATING_THRESHOLD = PerceptionConfig().score_threshold  # the daemon's: what it attributes


def ablations(aux: tuple[str, ...]) -> dict[str, tuple[str, ...]]:
    """Name -> modalities removed: all on, each one off, and each one alone (with one aux sensor,
    ``thermal_only`` is ``no_rgb``: the same pass)."""
    out: dict[str, tuple[str, ...]] = {"none": ()}
    for name in ("rgb", *aux):
        out[f"no_{name}"] = (name,)
    out["rgb_only"] = tuple(aux)
    for name in aux:
        out[f"{name}_only"] = ("rgb", *(m for m in aux if m != name))
    return out


def sample_input(sample: Sample, aux: tuple[str, ...], removed: tuple[str, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample -> padded (1, C, Hp, Wp) tensor and (1, A) presence, with ``removed`` zeroed."""
    c, h, w = sample.planes.shape
    hp, wp = pad_to_stride(h, w)
    x = np.zeros((1, c, hp, wp), dtype=np.float32)
    x[0, :, :h, :w] = sample.planes / np.float32(255) if sample.planes.dtype == np.uint8 else sample.planes
    presence = sample.presence.copy()
    for name in removed:
        if name == "rgb":
            x[0, :3] = 0
        else:
            i = aux.index(name)
            x[0, 3 + i] = 0
            presence[i] = 0
    return torch.from_numpy(x), torch.from_numpy(presence[None])


class Evaluation:
    """Accumulates per-instant results; ``report()`` gives the JSON body of ``eval.json``."""

    def __init__(self, detector: FusionDetector, attribution_threshold: float = OPERATING_THRESHOLD) -> None:
        self.detector, self.attribution_threshold = detector, attribution_threshold
        self.aux = detector.model.spec.aux_modalities
        self.attributor = Attributor(detector.model, detector.config.attribution_method, "always")  # every number
        self.by_resolution: dict[str, dict[str, list[ImageResult]]] = defaultdict(lambda: defaultdict(list))
        self.levels: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(len(STRIDES), dtype=np.int64))
        self.tallest: dict[str, float] = defaultdict(float)
        self.ablation: dict[str, dict[str, list[ImageResult]]] = defaultdict(lambda: defaultdict(list))
        self.contributions: dict[str, list[dict[str, float]]] = defaultdict(list)
        self.redundancy: dict[str, dict[str, list[dict[str, float]]]] = defaultdict(lambda: defaultdict(list))
        self.faithful: dict[str, list[bool]] = defaultdict(list)
        self.attributed_frames: dict[str, int] = defaultdict(int)
        self.attribution_size: str | None = None
        self._all_on: tuple[int, ImageResult | None] = (0, None)

    def _predict(self, x: torch.Tensor, presence: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg, model = self.detector.config, self.detector.model
        hw = tuple(x.shape[2:])
        with torch.inference_mode():
            all_boxes, all_scores = model.decode(model(x, presence), hw)
            boxes, scores, _, anchors = postprocess(all_boxes, all_scores, hw, cfg.score_threshold,
                                                    cfg.iou_threshold, cfg.max_detections)[0]
        return boxes.numpy(), scores.numpy(), anchors.numpy()

    def add_resolution(self, sample: Sample, conditions: list[str]) -> None:
        """Every sensor on at this sample's RGB size: mAP and head levels."""
        h, w = sample.planes.shape[1:]
        key = f"{w}x{h}"
        x, presence = sample_input(sample, self.aux, ())
        boxes, scores, anchors = self._predict(x, presence)
        image = ImageResult(boxes, scores, sample.boxes, sample.ignore)
        self._all_on = (id(sample), image)  # add_attributed on the same sample reuses it
        for cond in conditions:
            self.by_resolution[key][cond].append(image)
        strong = scores >= OPERATING_THRESHOLD
        self.levels[key] += np.bincount(_level_of(anchors[strong], *x.shape[2:]), minlength=len(STRIDES))
        if strong.any():
            self.tallest[key] = max(self.tallest[key], float((boxes[strong, 3] - boxes[strong, 1]).max()))

    def add_attributed(self, sample: Sample, conditions: list[str]) -> None:
        """Each sensor off (mAP), contributions and the deletion test at this sample's size."""
        h, w = sample.planes.shape[1:]
        self.attribution_size = f"{w}x{h}"
        cfg = self.detector.config
        x, presence = sample_input(sample, self.aux, ())
        result = self.attributor(x, presence, self.attribution_threshold, cfg.iou_threshold, cfg.max_detections,
                                 cfg.attribution_targets)
        k = 0 if result.ranking is None else len(result.ranking)
        targets, confidences = result.detections[0][:k].numpy(), result.detections[1][:k].numpy()
        after = np.zeros((k, len(result.modalities)))
        passes: dict[frozenset[str], ImageResult] = {}  # one pass per set of sensors off
        if self._all_on[0] == id(sample) and self._all_on[1] is not None:
            passes[frozenset()] = self._all_on[1]
        for name, removed in ablations(self.aux).items():
            image = passes.get(frozenset(removed))
            if image is None:
                boxes, scores, _ = self._predict(*sample_input(sample, self.aux, removed))
                image = passes[frozenset(removed)] = ImageResult(boxes, scores, sample.boxes, sample.ignore)
            boxes, scores = image.pred_boxes, image.pred_scores
            for cond in conditions:
                self.ablation[cond][name].append(image)
            if len(removed) == 1 and k:
                after[:, result.modalities.index(removed[0])] = _matched_confidence(targets, boxes, scores)
        faithful = _faithful(result.ranking.numpy(), confidences[:, None] - after) if result.ranking is not None else []
        for cond in conditions:
            if k:
                self.faithful[cond].extend(faithful)
            if result.scene is not None:
                self.contributions[cond].append(result.scene)
                self.attributed_frames[cond] += 1
            for name, values in redundancy_numbers(result, confidences[:, None] - after).items():
                self.redundancy[name][cond].append(values)

    def report(self) -> dict:
        ablation = {c: {n: mean_ap(images) for n, images in by.items()} for c, by in self.ablation.items()}
        by_resolution = {}
        for size, by in sorted(self.by_resolution.items(), key=lambda kv: int(kv[0].split("x")[0])):
            overall = mean_ap(by["all"])
            by_resolution[size] = {
                "map50": overall["map50"], "map50_95": overall["map50_95"],
                "by_condition": {c: mean_ap(images)["map50"] for c, images in by.items() if c != "all"},
                "levels": dict(zip((f"P{int(np.log2(s))}" for s in STRIDES), self.levels[size].tolist(), strict=True)),
                "tallest_detection_px": round(self.tallest[size], 1),
                "recall_by_height": {c: recall_by_height(images, int(size.split("x")[1])) for c, images in by.items()},
                "false_boxes": {c: false_box_kinds(images, OPERATING_THRESHOLD) for c, images in by.items()},
                "delivered_map50": {c: average_precision(delivered(images), 0.5) for c, images in by.items()},
            }
        cfg = self.detector.config
        return {
            "by_resolution": by_resolution,
            "ablation": {c: {n: v["map50"] for n, v in by.items()} for c, by in ablation.items()},
            "map": ablation,
            "contributions": {c: _mean_dict(rows) for c, rows in self.contributions.items()},
            **{name: {c: _mean_dict(rows) for c, rows in self.redundancy.get(name, {}).items()}
               for name in (REDUNDANCY if cfg.attribution_method == "ablation" else ())},  # {} when nothing attributed
            "faithfulness": {c: float(np.mean(v)) for c, v in self.faithful.items() if v},
            "frames": {c: len(by["none"]) for c, by in self.ablation.items()},
            "detections": {c: {n: detection_count(images) for n, images in by.items()}
                           for c, by in self.ablation.items()},
            "attributed": dict(self.attributed_frames),
            "attributed_detections": {c: len(v) for c, v in self.faithful.items()},
            "attribution": {"method": cfg.attribution_method, "rgb": self.attribution_size,
                            "score_threshold": self.attribution_threshold, "targets": cfg.attribution_targets},
        }


# eval.json's per-sensor numbers beside the contributions
REDUNDANCY = ("dependence", "sufficiency", "shapley", "lost_when_off")


def redundancy_numbers(result: Attribution, measured_drops: np.ndarray) -> dict[str, dict[str, float]]:
    """The frame's dependence, sufficiency and Shapley share per sensor (those it has: ablation with a target),
    and what a whole sensor-off pass measured the attributed boxes to lose (``measured_drops``, (K, M))."""
    out = {name: values for name, values in (("dependence", result.dependence), ("sufficiency", result.sufficiency))
           if values is not None}
    if result.ablation is None:
        return out
    shares = shapley_share(result.ablation)
    if shares is not None:
        out["shapley"] = shares
    lost = kept_share(torch.from_numpy(measured_drops).float(), result.ablation.base)
    if lost is not None:
        out["lost_when_off"] = dict(zip(result.modalities, lost.tolist(), strict=True))
    return out


def shapley_share(ablation: Ablation) -> dict[str, float] | None:
    """Per sensor, its Shapley values summed over the targets, as a share of their confidence."""
    values, total = shapley(ablation), float(ablation.base.sum())
    if values is None or total <= 0:
        return None
    return {m: float(v) / total for m, v in zip(ablation.modalities, values.sum(0).tolist(), strict=True)}


HEIGHT_BINS = (0.0, 0.1, 0.2, 0.4, 0.7)  # person height as a share of the frame height


def recall_by_height(images: list[ImageResult], frame_height: int,
                     threshold: float = OPERATING_THRESHOLD) -> dict[str, list[int]]:
    """[found, people] per person-height bin: a person counts as found when a detection at the daemon's
    threshold overlaps it with IoU >= 0.5. Binned by share of the frame, so the same people land in the same
    bin at every resolution and a resolution's weak sizes show (ignored boxes are left out)."""
    names = [f"{lo:g}-{hi:g}" for lo, hi in itertools.pairwise(HEIGHT_BINS)] + [f">={HEIGHT_BINS[-1]:g}"]
    found, people = np.zeros(len(names), np.int64), np.zeros(len(names), np.int64)
    for image in images:
        targets = image.gt_boxes[~image.gt_ignore]
        if not len(targets):
            continue
        bins = np.searchsorted(HEIGHT_BINS, (targets[:, 3] - targets[:, 1]) / frame_height, side="right") - 1
        strong = image.pred_scores >= threshold
        hit = _matched_confidence(targets, image.pred_boxes[strong], image.pred_scores[strong]) > 0
        np.add.at(people, bins, 1)
        np.add.at(found, bins, hit.astype(np.int64))
    return {name: [int(f), int(p)] for name, f, p in zip(names, found, people, strict=True)}


def delivered(images: list[ImageResult], threshold: float = OPERATING_THRESHOLD) -> list[ImageResult]:
    """The images with only the boxes at or above the daemon's score threshold: AP ranks boxes down to
    0.01, the daemon hands on none under its threshold, so a person found at 0.2 is missed on the robot."""
    out = []
    for image in images:
        keep = image.pred_scores >= threshold
        out.append(ImageResult(image.pred_boxes[keep], image.pred_scores[keep], image.gt_boxes, image.gt_ignore))
    return out


def detection_count(images: list[ImageResult], threshold: float = OPERATING_THRESHOLD) -> int:
    """Detections at the daemon's operating threshold (the profile default), as the paper counts them."""
    return int(sum((im.pred_scores >= threshold).sum() for im in images))


def _level_of(anchors: np.ndarray, height: int, width: int) -> np.ndarray:
    """Head level index (0 = P3) of each anchor index, in the head's output order."""
    ends = np.cumsum([(height // s) * (width // s) for s in STRIDES])
    return np.searchsorted(ends, anchors, side="right")


def _matched_confidence(targets: np.ndarray, boxes: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """Per target box, the best confidence among ``boxes`` overlapping it with IoU >= 0.5 (0 if none)."""
    if len(boxes) == 0:
        return np.zeros(len(targets))
    overlap = iou_matrix(targets, boxes) >= 0.5  # (K, P)
    return np.where(overlap, scores[None, :], 0.0).max(1)


def _faithful(ranking: np.ndarray, drops: np.ndarray) -> list[bool]:
    """Per target: does switching off its top-ranked modality cost more than its second-ranked?"""
    order = np.argsort(-ranking, axis=1, kind="stable")
    rows = np.arange(len(ranking))
    return (drops[rows, order[:, 0]] > drops[rows, order[:, 1]]).tolist()


def _mean_dict(rows: list[dict[str, float]]) -> dict[str, float]:
    if not rows:
        return {}
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def condition_order(report: dict) -> list[str]:
    from respecd.lab.detector.simdata import CONDITIONS

    known = [c for c in ("all", *CONDITIONS) if c in report["map"]]
    return known + sorted(c for c in report["map"] if c not in known)


def evaluate_samples(detector: FusionDetector, samples, progress: bool = False,
                     attribution_threshold: float = OPERATING_THRESHOLD) -> dict:
    """A dataset (anything with len and [i]): ablation, contributions and the deletion test at its size."""
    from respecd.lab.detector.data import progress as progress_bar

    evaluation = Evaluation(detector, attribution_threshold)
    for i in progress_bar(range(len(samples)), progress, desc="eval"):
        sample = samples[i]
        evaluation.add_attributed(sample, ["all", sample.meta.get("scenario", "data")])
    return evaluation.report()


def sim_instants(detector: FusionDetector, per_scenario: int, seed: int, sizes: list[tuple[int, int]],
                 progress: bool = False) -> Iterator[tuple[tuple[int, int], Sample, list[str]]]:
    """Held-out simulated instants, ``per_scenario`` of each scenario (two per scenario run), each
    rendered at every size in ``sizes`` with the same noise draws: (size, sample, its conditions)."""
    from respecd.lab.detector.data import progress as progress_bar
    from respecd.lab.detector.simdata import SimFrames, condition_of

    frames = SimFrames(detector.config, seed)
    n = len(frames.sim.scenarios)
    instants = [(run * n + s, fraction) for run in range(max(1, per_scenario // 2)) for s in range(n)
                for fraction in (0.3, 0.7)]  # two instants per scenario run
    for segment, fraction in progress_bar(instants, progress, desc="eval", unit="instant"):
        t = frames.time_in(segment, fraction)
        for size in sizes:
            rng = np.random.default_rng([seed, segment, int(fraction * 10), 0])  # same noise draws per size
            sample = frames.sample(t, size, rng, randomize=False)
            yield size, sample, ["all", *condition_of(sample.meta["scenario"])]


def evaluate_sim(detector: FusionDetector, per_scenario: int, attribution_size: tuple[int, int] = (640, 360),
                 seed: int = EVAL_SEED, progress: bool = False,
                 attribution_threshold: float = OPERATING_THRESHOLD) -> dict:
    """Held-out simulated instants, ``per_scenario`` of each scenario, at every RGB resolution."""
    from respecd.lab.detector.simdata import RESOLUTIONS

    sizes: list[tuple[int, int]] = sorted({*RESOLUTIONS, (attribution_size[0], attribution_size[1])})
    evaluation = Evaluation(detector, attribution_threshold)
    for size, sample, conditions in sim_instants(detector, per_scenario, seed, sizes, progress):
        if size in RESOLUTIONS:
            evaluation.add_resolution(sample, conditions)
        if size == tuple(attribution_size):
            evaluation.add_attributed(sample, conditions)
    return {**evaluation.report(), "world_seed": seed}
