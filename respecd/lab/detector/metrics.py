"""Detection metrics: COCO-style average precision at IoU 0.5 and averaged over 0.5:0.95.

Per IoU threshold, detections of all images are sorted by confidence and greedily matched
to the unmatched ground-truth box of highest IoU; AP is the area under the interpolated
precision/recall curve sampled at 101 recall points (the COCO definition). Ground truth
marked ``ignore`` (a person hidden behind a solid occluder) neither counts as a miss nor
turns a detection on it into a false positive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

IOU_THRESHOLDS = tuple(np.round(np.arange(0.5, 0.96, 0.05), 2))


@dataclass
class ImageResult:
    """One image's predictions and ground truth (single class), pixel x1y1x2y2."""

    pred_boxes: np.ndarray  # (P, 4)
    pred_scores: np.ndarray  # (P,)
    gt_boxes: np.ndarray  # (G, 4)
    gt_ignore: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (G,)

    def __post_init__(self) -> None:
        if len(self.gt_ignore) != len(self.gt_boxes):
            self.gt_ignore = np.zeros(len(self.gt_boxes), dtype=bool)


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 4) x (M, 4) -> (N, M) IoU."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((len(a), len(b)))
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(-1)
    area_a = np.clip(a[:, 2:] - a[:, :2], 0, None).prod(-1)
    area_b = np.clip(b[:, 2:] - b[:, :2], 0, None).prod(-1)
    return inter / (area_a[:, None] + area_b[None, :] - inter + 1e-9)


def _greedy(image: ImageResult, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Detection order (highest score first), true-positive and keep flags (False = matched an ignored
    box) in that order, and which ground-truth boxes a detection took."""
    order = np.argsort(-image.pred_scores, kind="stable")
    ious = iou_matrix(image.pred_boxes[order], image.gt_boxes)
    taken = np.zeros(len(image.gt_boxes), dtype=bool)
    tp = np.zeros(len(order), dtype=bool)
    keep = np.ones(len(order), dtype=bool)
    for i in range(len(order)):
        if ious.shape[1] == 0:
            break
        # real boxes first, then ignored ones (a hit on an ignored box is not scored)
        cand = np.where(~taken & ~image.gt_ignore & (ious[i] >= threshold))[0]
        if len(cand):
            j = cand[np.argmax(ious[i, cand])]
            taken[j], tp[i] = True, True
            continue
        if np.any(image.gt_ignore & (ious[i] >= threshold)):
            keep[i] = False
    return order, tp, keep, taken


def _match(image: ImageResult, threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scores, true-positive flags and keep flags (False = matched an ignored box) for one image."""
    order, tp, keep, _ = _greedy(image, threshold)
    return image.pred_scores[order], tp, keep


def detection_f1(image: ImageResult, threshold: float = 0.5) -> float:
    """F1 of one image's boxes at IoU ``threshold``, matched as AP matches them (a box on an ignored
    person counts neither way); 1.0 when there is nothing to find and nothing was found. A per-image
    quality that, unlike the detector's confidence, falls when a person is missed."""
    _, tp, keep, _ = _greedy(image, threshold)
    hits = int(tp.sum())
    false = int((~tp & keep).sum())
    missed = int((~image.gt_ignore).sum()) - hits
    return 1.0 if hits + false + missed == 0 else 2 * hits / (2 * hits + false + missed)


FALSE_BOX_KINDS = ("second", "misplaced", "clutter")


def false_box_kinds(images: list[ImageResult], score_threshold: float, near: float = 0.1) -> dict[str, int]:
    """What the false positives at ``score_threshold`` are, matched as AP@0.5 matches them: a *second* box on
    a person another box already found, a *misplaced* box on a person no box found (IoU in [near, 0.5)), or
    *clutter* (IoU < near with every person). Each kind has its own cure (NMS or training against duplicates,
    box regression, background), so the split says where a resolution loses its precision."""
    counts = dict.fromkeys(FALSE_BOX_KINDS, 0)
    for image in images:
        strong = image.pred_scores >= score_threshold
        kept = ImageResult(image.pred_boxes[strong], image.pred_scores[strong], image.gt_boxes, image.gt_ignore)
        order, tp, keep, taken = _greedy(kept, IOU_THRESHOLDS[0])
        false = order[~tp & keep]
        real = ~kept.gt_ignore
        if not len(false):
            continue
        if not real.any():
            counts["clutter"] += len(false)
            continue
        ious = iou_matrix(kept.pred_boxes[false], kept.gt_boxes[real])
        clutter = ious.max(1) < near
        found = taken[real][ious.argmax(1)]
        counts["second"] += int((~clutter & found).sum())
        counts["misplaced"] += int((~clutter & ~found).sum())
        counts["clutter"] += int(clutter.sum())
    return counts


def ap_parts(images: list[ImageResult], threshold: float) -> tuple[np.ndarray, np.ndarray, int]:
    """What AP needs of a set of images, which pools by concatenation: the scored detections'
    confidences, their true-positive flags, and the number of (non-ignored) ground-truth boxes."""
    n_gt = int(sum((~im.gt_ignore).sum() for im in images))
    parts = [_match(im, threshold) for im in images]
    scores = np.concatenate([p[0][p[2]] for p in parts]) if parts else np.zeros(0)
    tp = np.concatenate([p[1][p[2]] for p in parts]) if parts else np.zeros(0, dtype=bool)
    return scores, tp, n_gt


def ap_from_parts(scores: np.ndarray, tp: np.ndarray, n_gt: int) -> float:
    """COCO 101-point interpolated AP of pooled ``ap_parts``; NaN when there is no ground truth."""
    if n_gt == 0:
        return float("nan")
    if len(scores) == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    tp = tp[order]
    ctp, cfp = np.cumsum(tp), np.cumsum(~tp)
    recall = ctp / n_gt
    precision = ctp / np.maximum(ctp + cfp, 1)
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # monotone envelope
    points = np.linspace(0, 1, 101)
    idx = np.searchsorted(recall, points, side="left")
    sampled = np.where(idx < len(precision), precision[np.minimum(idx, len(precision) - 1)], 0.0)
    return float(sampled.mean())


def average_precision(images: list[ImageResult], threshold: float) -> float:
    """COCO 101-point interpolated AP at one IoU threshold; NaN when there is no ground truth."""
    return ap_from_parts(*ap_parts(images, threshold))


def mean_ap(images: list[ImageResult]) -> dict[str, float]:
    """{"map50": AP@0.5, "map50_95": mean AP over IoU 0.5..0.95}."""
    aps = [average_precision(images, t) for t in IOU_THRESHOLDS]
    return {"map50": aps[0], "map50_95": float(np.mean(aps))}
