"""Contribution attribution: how much each input channel carried the top detections.

For the top-K detections (after NMS) we take the pre-NMS confidence of the anchor that
produced each box and back-propagate to the C-channel input. Gradient x input, in
absolute value, summed over each box region per channel and normalized to sum 1, is the
target's contribution vector; the scene score is the confidence-weighted mean over
targets. R, G and B are reported separately and grouped as "rgb".

One backward pass serves all K targets (the gradient of the sum of their confidences):
K separate passes would cost K times as much. Inside box k the gradient of the other
targets' confidences is small (they are spatially apart), so the per-box sums are a close
approximation of per-target attributions; overlapping boxes share some credit.
The network's weights are frozen while attributing, so backward computes input gradients
only (about one forward pass of extra cost, not two).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch

from respecd.perception.boxes import postprocess

if TYPE_CHECKING:
    from respecd.perception.checkpoint import Net

RGB_CHANNELS = ("r", "g", "b")


def box_channel_sums(saliency: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(C, H, W) |grad x input| and (K, 4) pixel boxes -> (K, C) sums over each box, rows sum to 1.

    A box with no attribution at all (every channel zero there) gets a zero row.
    """
    _, h, w = saliency.shape
    rows = []
    for x1, y1, x2, y2 in boxes.tolist():
        c1, r1 = max(0, int(math.floor(x1))), max(0, int(math.floor(y1)))
        c2, r2 = min(w, max(c1 + 1, int(math.ceil(x2)))), min(h, max(r1 + 1, int(math.ceil(y2))))
        rows.append(saliency[:, r1:r2, c1:c2].sum((1, 2)))  # (C,)
    sums = torch.stack(rows)  # (K, C)
    total = sums.sum(1, keepdim=True)
    return torch.where(total > 0, sums / total.clamp(min=1e-12), torch.zeros_like(sums))


def scene_score(per_target: torch.Tensor, confidences: torch.Tensor) -> torch.Tensor | None:
    """Confidence-weighted mean of the targets' (K, C) rows; None when no row carries weight."""
    valid = per_target.sum(1) > 0
    weights = confidences * valid
    if float(weights.sum()) <= 0:
        return None
    return (per_target * weights[:, None]).sum(0) / weights.sum()


def attribute(
    model: Net, x: torch.Tensor, presence: torch.Tensor, score_threshold: float, iou_threshold: float,
    max_det: int, top_k: int,
) -> tuple[list, torch.Tensor | None, torch.Tensor | None]:
    """Forward with gradients, NMS, one backward from the top-K confidences.

    ``x`` is (1, C, H, W). Returns the detections (as ``postprocess`` gives them for the one
    image), the (K, C) per-target contributions (None if nothing detected) and the scene
    vector (C,) (None if nothing detected).
    """
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        boxes_all, scores_all = model.decode(model(x, presence), tuple(x.shape[2:]))
        dets = postprocess(boxes_all.detach(), scores_all.detach(), tuple(x.shape[2:]), score_threshold,
                           iou_threshold, max_det)[0]
        boxes, scores, labels, anchors = dets
        if len(scores) == 0:
            return list(dets), None, None
        k = min(top_k, len(scores))  # postprocess sorts by score, so these are the top K
        target = scores_all[0, anchors[:k], labels[:k]].sum()
        (grad,) = torch.autograd.grad(target, x)
    saliency = (grad[0] * x[0]).abs().detach()  # (C, H, W)
    per_target = box_channel_sums(saliency, boxes[:k])
    return list(dets), per_target, scene_score(per_target, scores[:k])


def grouped(channels: tuple[str, ...], vector: np.ndarray | torch.Tensor) -> dict[str, float]:
    """Channel vector -> {"r", "g", "b", "rgb", <aux modality>...}: R, G, B apart and summed."""
    values = {name: float(v) for name, v in zip(channels, vector.tolist(), strict=True)}
    values["rgb"] = sum(values[c] for c in RGB_CHANNELS)
    return values


def uniform_scores(channels: tuple[str, ...]) -> dict[str, float]:
    """Equal share per modality (RGB counts as one modality, split evenly over R, G, B)."""
    aux = [c for c in channels if c not in RGB_CHANNELS]
    share = 1.0 / (1 + len(aux))
    scores = {c: share / 3 for c in RGB_CHANNELS}
    scores.update({c: share for c in aux})
    scores["rgb"] = share
    return scores


class SceneScores:
    """The scene score the controller sees, held between attributions.

    When an attribution finds no target there is no evidence about the modalities; rather
    than jump, the last score decays toward uniform with time constant ``decay_s``:
    s <- u + (s - u) * exp(-dt / decay_s). Before the first attribution it is uniform.
    """

    def __init__(self, channels: tuple[str, ...], decay_s: float) -> None:
        self.uniform = uniform_scores(channels)
        self.decay_s = decay_s
        self.value = dict(self.uniform)
        self._t: float | None = None

    def update(self, t: float, fresh: dict[str, float] | None) -> dict[str, float]:
        if fresh is not None:
            self.value = dict(fresh)
        elif self._t is not None:
            keep = math.exp(-max(0.0, t - self._t) / self.decay_s)
            self.value = {k: self.uniform[k] + (v - self.uniform[k]) * keep for k, v in self.value.items()}
        self._t = t
        return dict(self.value)
