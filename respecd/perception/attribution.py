"""Contribution attribution: how much each modality carried the top detections.

For the top-K detections (after NMS) each method gives a per-target vector over the
modalities (``rgb`` and the aux modalities), normalized to sum 1; the scene score is the
confidence-weighted mean over targets. Two methods (profile ``perception.attribution_method``):

* ``ablation`` (the default): the confidence each target box loses when one modality is
  switched off exactly as the daemon feeds a disabled sensor (zero plane, presence 0): with
  the sensor off, the box's confidence is the best one among the anchors whose box overlaps
  it with IoU >= 0.5, wherever the net now places it (not only the target's own anchor: with
  one sensor off a neighbouring anchor often takes the detection over, and the deletion test
  counts what is left of the box). The drops, clipped at 0 and normalized, are the
  contributions, so the ranking is what a controller acts on: the top-ranked sensor is the
  one whose loss costs the box the most. Cost: the RGB backbone on a zero frame depends only
  on the input size (cached), the aux backbone runs once more per aux modality that is on,
  the neck once per modality, and the head once per modality on the cells near the targets
  only (``candidate_windows``: no other anchor can hold a matching box). docs/PERCEPTION.md
  has the figures.
* ``gradient`` (the paper's): the pre-NMS confidences of the K anchors back-propagated to the
  input; |gradient x input| summed over each box per channel. One backward pass serves all
  K targets (the gradient of the sum of their confidences), so overlapping boxes share some
  credit. It also reports R, G and B apart. A zero channel gets exactly 0.

Neither changes the weights: attribution runs on a frozen model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch

from respecd.perception.boxes import box_iou, postprocess
from respecd.perception.model import STRIDES, Features, FusionNet, Window, anchor_cells

RGB_CHANNELS = ("r", "g", "b")
Method = Literal["ablation", "gradient"]
MATCH_IOU = 0.5  # a box with a sensor off is "the same detection" if it overlaps the target this much
METHODS: tuple[Method, ...] = ("ablation", "gradient")
Detections = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]  # boxes, scores, labels, anchors


@dataclass(frozen=True)
class Attribution:
    """One attributed frame. Rows follow the detections' order (highest confidence first)."""

    detections: Detections
    modalities: tuple[str, ...]  # column names of ``shares`` and ``ranking``
    shares: torch.Tensor | None  # (K, M) per-target contributions, rows sum to 1 (all 0: no evidence)
    ranking: torch.Tensor | None  # (K, M) what the method ranks modalities by (ablation: confidence drop)
    scene: dict[str, float] | None  # scene score per modality (gradient: also r, g, b)


def box_channel_sums(saliency: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """(C, H, W) |grad x input| and (K, 4) pixel boxes -> (K, C) sums over each box, rows sum to 1.

    A box with no attribution at all (every channel zero there) gets a zero row.
    """
    return _normalized(_box_sums(saliency, boxes))


def _box_sums(saliency: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    _, h, w = saliency.shape
    rows = []
    for x1, y1, x2, y2 in boxes.tolist():
        c1, r1 = max(0, int(math.floor(x1))), max(0, int(math.floor(y1)))
        c2, r2 = min(w, max(c1 + 1, int(math.ceil(x2)))), min(h, max(r1 + 1, int(math.ceil(y2))))
        rows.append(saliency[:, r1:r2, c1:c2].sum((1, 2)))  # (C,)
    return torch.stack(rows)  # (K, C)


def _normalized(rows: torch.Tensor) -> torch.Tensor:
    total = rows.sum(1, keepdim=True)
    return torch.where(total > 0, rows / total.clamp(min=1e-12), torch.zeros_like(rows))


def scene_score(per_target: torch.Tensor, confidences: torch.Tensor) -> torch.Tensor | None:
    """Confidence-weighted mean of the targets' (K, M) rows; None when no row carries weight."""
    valid = per_target.sum(1) > 0
    weights = confidences * valid
    if float(weights.sum()) <= 0:
        return None
    return (per_target * weights[:, None]).sum(0) / weights.sum()


class Attributor:
    """Detections plus contributions for one (1, C, H, W) input, by ``method``.

    Holds the RGB-off features per input size (a zero frame's backbone output is a constant),
    so build one per model and keep it. A net without FusionNet's backbone/fusion split
    (another architecture) gets the same numbers from full forward passes.
    """

    def __init__(self, model: Any, method: Method = "ablation") -> None:
        if method not in METHODS:
            raise ValueError(f"attribution method {method!r}: expected one of {', '.join(METHODS)}")
        self.model: Any = model  # FusionNet, or any net with spec, forward(x, presence) and decode(raw, hw)
        self.method = method
        self.modalities = ("rgb", *model.spec.aux_modalities)
        self._split = isinstance(model, FusionNet)
        self._rgb_off: dict[tuple, Features] = {}

    def __call__(self, x: torch.Tensor, presence: torch.Tensor, score_threshold: float, iou_threshold: float,
                 max_det: int, top_k: int) -> Attribution:
        run = self._ablation if self.method == "ablation" else self._gradient
        return run(x, presence, (score_threshold, iou_threshold, max_det), top_k)

    def _detect(self, raw, hw: tuple[int, ...], nms: tuple) -> tuple[torch.Tensor, Detections]:
        """Class probabilities (B, N, nc) and the NMS'd detections of the first image."""
        boxes, scores = self.model.decode(raw, hw)
        return scores, postprocess(boxes.detach(), scores.detach(), hw, *nms)[0]

    def _ablation(self, x: torch.Tensor, presence: torch.Tensor, nms: tuple, top_k: int) -> Attribution:
        hw = tuple(x.shape[2:])
        with torch.inference_mode():
            parts = (self.model.encode_rgb(x[:, :3]), self.model.encode_aux(x[:, 3:], presence)) if self._split \
                else None
            raw = self.model.fuse(*parts) if parts is not None else self.model(x, presence)
            probabilities, dets = self._detect(raw, hw, nms)
            if len(dets[1]) == 0:
                return Attribution(dets, self.modalities, None, None, None)
            k = min(top_k, len(dets[1]))  # postprocess sorts by score: these are the top K
            targets, labels = dets[0][:k], dets[2][:k]
            base = dets[1][:k]
            windows = candidate_windows(targets, hw)
            drops = torch.zeros(k, len(self.modalities))
            for m in range(len(self.modalities)):
                on = bool(x[:, :3].any()) if m == 0 else float(presence[0, m - 1]) > 0
                if on:  # a sensor that is already off loses nothing by being switched off
                    off = self._detections_off(x, presence, parts, m, windows)
                    drops[:, m] = base - _box_confidence(*off, targets, labels)
        shares = _normalized(drops.clamp(min=0.0))
        scene = scene_score(shares, dets[1][:k])
        named = None if scene is None else dict(zip(self.modalities, scene.tolist(), strict=True))
        return Attribution(dets, self.modalities, shares, drops, named)

    def _detections_off(self, x: torch.Tensor, presence: torch.Tensor, parts, m: int,
                        windows: list[Window]) -> tuple[torch.Tensor, torch.Tensor]:
        """Boxes (N, 4) and class probabilities (N, nc) with modality ``m`` off (zero plane, presence 0):
        of every anchor, or (FusionNet) of the anchors in ``windows``, the only ones that can match a target."""
        hw = tuple(x.shape[2:])
        if parts is None:
            x_off, presence_off = _switched_off(x, presence, m)
            boxes, probabilities = self.model.decode(self.model(x_off, presence_off), hw)
        else:
            raw, anchors = self.model.fuse_window(*self._features_off(x, presence, parts, m), windows)
            boxes, probabilities = self.model.decode(raw, hw, anchors)
        return boxes[0], probabilities[0]

    def _features_off(self, x: torch.Tensor, presence: torch.Tensor, parts, m: int) -> tuple[Features, Features]:
        rgb, aux = parts
        if m == 0:
            rgb = self._rgb_off_features(x)
        else:
            _, presence_off = _switched_off(x, presence, m)
            aux_off = x[:, 3:].clone()
            aux_off[:, m - 1] = 0.0
            aux = self.model.encode_aux(aux_off, presence_off)
        return rgb, aux

    def _rgb_off_features(self, x: torch.Tensor) -> Features:
        key = (tuple(x.shape[2:]), x.dtype, x.device)
        if key not in self._rgb_off:
            self._rgb_off[key] = self.model.encode_rgb(x.new_zeros(1, 3, *x.shape[2:]))
        return self._rgb_off[key]

    def _gradient(self, x: torch.Tensor, presence: torch.Tensor, nms: tuple, top_k: int) -> Attribution:
        x = x.detach().requires_grad_(True)
        with torch.enable_grad():
            probabilities, dets = self._detect(self.model(x, presence), tuple(x.shape[2:]), nms)
            boxes, scores, labels, anchors = dets
            if len(scores) == 0:
                return Attribution(dets, self.modalities, None, None, None)
            k = min(top_k, len(scores))
            target = probabilities[0, anchors[:k], labels[:k]].sum()
            (grad,) = torch.autograd.grad(target, x)
        saliency = (grad[0] * x[0]).abs().detach()  # (C, H, W)
        channels = box_channel_sums(saliency, boxes[:k])  # (K, C), rows sum to 1
        shares = torch.cat([channels[:, :3].sum(1, keepdim=True), channels[:, 3:]], 1)  # (K, M)
        scene = scene_score(channels, scores[:k])
        named = None if scene is None else grouped(self.model.spec.channels, scene)
        return Attribution(dets, self.modalities, shares, shares, named)


def candidate_windows(targets: torch.Tensor, input_hw: tuple[int, ...]) -> list[Window]:
    """Per head level, the cells whose anchor could hold a box matching a target (IoU >= MATCH_IOU).

    A decoded box contains its anchor point (its four distances are >= 0), and a box B with
    IoU(B, T) >= t sticks out of T by at most (1/t - 1) of T's width on each side (B's width is at
    most its overlap's width / t), likewise in height; so every matching box's anchor lies in the
    targets widened so (plus a pixel for rounding). One rectangle per level holds all targets.
    """
    grow = 1.0 / MATCH_IOU - 1.0
    widths, heights = targets[:, 2] - targets[:, 0], targets[:, 3] - targets[:, 1]
    x0 = float((targets[:, 0] - grow * widths).min()) - 1.0
    x1 = float((targets[:, 2] + grow * widths).max()) + 1.0
    y0 = float((targets[:, 1] - grow * heights).min()) - 1.0
    y1 = float((targets[:, 3] + grow * heights).max()) + 1.0
    height, width = input_hw
    return [(*anchor_cells(y0, y1, s, height // s), *anchor_cells(x0, x1, s, width // s)) for s in STRIDES]


def _box_confidence(boxes: torch.Tensor, probabilities: torch.Tensor, targets: torch.Tensor,
                    labels: torch.Tensor) -> torch.Tensor:
    """Per target box, the best confidence of its class among the anchors whose box overlaps it with
    IoU >= 0.5: what is left of that detection, wherever the net now places it (0 if nothing)."""
    if len(boxes) == 0:
        return targets.new_zeros(len(targets))
    overlap = box_iou(targets, boxes) >= MATCH_IOU  # (K, N)
    scores = probabilities[:, labels].T  # (K, N)
    return torch.where(overlap, scores, torch.zeros_like(scores)).amax(1)


def _switched_off(x: torch.Tensor, presence: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The input with modality ``m`` (0 = RGB, then the aux modalities) as the daemon feeds a disabled sensor."""
    x_off, presence_off = x.clone(), presence.clone()
    if m == 0:
        x_off[:, :3] = 0.0
    else:
        x_off[:, 2 + m] = 0.0
        presence_off[:, m - 1] = 0.0
    return x_off, presence_off


def grouped(channels: tuple[str, ...], vector: torch.Tensor) -> dict[str, float]:
    """Channel vector -> {"r", "g", "b", "rgb", <aux modality>...}: R, G, B apart and summed."""
    values = {name: float(v) for name, v in zip(channels, vector.tolist(), strict=True)}
    values["rgb"] = sum(values[c] for c in RGB_CHANNELS)
    return values


def uniform_scores(channels: tuple[str, ...], per_channel: bool = False) -> dict[str, float]:
    """Equal share per modality (RGB counts as one); with ``per_channel`` R, G, B a third of RGB's each."""
    aux = [c for c in channels if c not in RGB_CHANNELS]
    share = 1.0 / (1 + len(aux))
    scores = {c: share / 3 for c in RGB_CHANNELS} if per_channel else {}
    scores.update({"rgb": share, **{c: share for c in aux}})
    return scores


class SceneScores:
    """The scene score the controller sees, held between attributions.

    When an attribution finds no target there is no evidence about the modalities; rather
    than jump, the last score decays toward uniform with time constant ``decay_s``:
    s <- u + (s - u) * exp(-dt / decay_s). Before the first attribution it is uniform.
    """

    def __init__(self, channels: tuple[str, ...], decay_s: float, per_channel: bool = False) -> None:
        self.uniform = uniform_scores(channels, per_channel)
        self.decay_s = decay_s
        self.value = dict(self.uniform)
        self._t: float | None = None

    def update(self, t: float, fresh: dict[str, float] | None) -> dict[str, float]:
        if fresh is not None:
            self.value = {k: fresh.get(k, v) for k, v in self.uniform.items()}
        elif self._t is not None:
            keep = math.exp(-max(0.0, t - self._t) / self.decay_s)
            self.value = {k: self.uniform[k] + (v - self.uniform[k]) * keep for k, v in self.value.items()}
        self._t = t
        return dict(self.value)
