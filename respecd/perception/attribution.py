"""Contribution attribution: how much each modality carried the top detections.

For the top-K detections (after NMS) each method gives a per-target vector over the
modalities (``rgb`` and the aux modalities), normalized to sum 1; the scene score is the
confidence-weighted mean over targets. Two methods (profile ``perception.attribution_method``):

* ``ablation`` (the default): the confidence each target box loses when one modality is
  switched off exactly as the daemon feeds a disabled sensor (``ablation.py``: the net re-run
  on sensor subsets through the ``SplitNet`` of ``split.py``, backbones once per input). The
  drops, clipped at 0 and normalized, are the contributions, so the ranking is what a
  controller acts on: the top-ranked sensor is the one whose loss costs the box the most.
  Beside them, per sensor, the scene's *dependence* (the share of the targets' confidence lost
  with the sensor off) and *sufficiency* (the share it keeps with only that sensor on): two
  sensors that each suffice show high sufficiency and low dependence each, which the
  normalized drops cannot show. Sufficiency is free with two sensors on (each alone is the
  other one off); with more it costs a fusion pass per sensor, run when ``sufficiency`` is
  ``"always"`` (``"auto"``: only when free). docs/PERCEPTION.md has the cost.
* ``gradient`` (the paper's): the pre-NMS confidences of the K anchors back-propagated to the
  input; |gradient x input| summed over each box per channel. One backward pass serves all
  K targets (the gradient of the sum of their confidences), so overlapping boxes share some
  credit. It also reports R, G and B apart. A zero channel gets exactly 0. No dependence or
  sufficiency.

Neither changes the weights: attribution runs on a frozen model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch

from respecd.perception.ablation import Ablation, SubsetRunner, kept_share
from respecd.perception.boxes import postprocess
from respecd.perception.split import as_split

RGB_CHANNELS = ("r", "g", "b")
Method = Literal["ablation", "gradient"]
METHODS: tuple[Method, ...] = ("ablation", "gradient")
Sufficiency = Literal["auto", "always"]  # profile ``perception.attribution_sufficiency``
Detections = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]  # boxes, scores, labels, anchors


@dataclass(frozen=True)
class Attribution:
    """One attributed frame. Rows follow the detections' order (highest confidence first)."""

    detections: Detections
    modalities: tuple[str, ...]  # column names of ``shares`` and ``ranking``
    shares: torch.Tensor | None  # (K, M) per-target contributions, rows sum to 1 (all 0: no evidence)
    ranking: torch.Tensor | None  # (K, M) what the method ranks modalities by (ablation: confidence drop)
    scene: dict[str, float] | None  # scene score per modality (gradient: also r, g, b)
    ablation: Ablation | None = None  # ablation: every subset's per-target confidences
    dependence: dict[str, float] | None = None  # ablation: share of the targets' confidence lost with it off
    sufficiency: dict[str, float] | None = None  # ablation: share of it kept with only that sensor on


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

    ``model``: a torch net, or any ``SplitNet`` (another runtime's; ``ablation`` only). The
    ablation keeps what does not depend on the frame (a black frame's features, per input
    size), so build one per model and keep it.
    """

    def __init__(self, model: Any, method: Method = "ablation", sufficiency: Sufficiency = "auto") -> None:
        if method not in METHODS:
            raise ValueError(f"attribution method {method!r}: expected one of {', '.join(METHODS)}")
        self.model: Any = model  # for ``gradient``: a torch net with spec, forward(x, presence), decode(raw, hw)
        self.method = method
        self.always_alone = sufficiency == "always"
        self.modalities = ("rgb", *model.spec.aux_modalities)
        self.subsets = SubsetRunner(as_split(model))

    def __call__(self, x: torch.Tensor, presence: torch.Tensor, score_threshold: float, iou_threshold: float,
                 max_det: int, top_k: int) -> Attribution:
        run = self._ablation if self.method == "ablation" else self._gradient
        return run(x, presence, (score_threshold, iou_threshold, max_det), top_k)

    def _ablation(self, x: torch.Tensor, presence: torch.Tensor, nms: tuple, top_k: int) -> Attribution:
        hw = tuple(x.shape[2:])
        with torch.inference_mode():
            (boxes, probabilities), frame = self.subsets.run(x, presence)
            dets: Detections = postprocess(boxes, probabilities, hw, *nms)[0]
            if len(dets[1]) == 0:
                return Attribution(dets, self.modalities, None, None, None)
            k = min(top_k, len(dets[1]))  # postprocess sorts by score: these are the top K
            ablation = self.subsets.ablate(frame, dets[0][:k], dets[2][:k], dets[1][:k], self.always_alone)
        shares = _normalized(ablation.drops.clamp(min=0.0))
        scene = scene_score(shares, ablation.base)
        return Attribution(dets, self.modalities, shares, ablation.drops, self._named(scene), ablation,
                           self._named(kept_share(ablation.drops, ablation.base)),
                           None if ablation.alone is None else self._named(kept_share(ablation.alone, ablation.base)))

    def _named(self, vector: torch.Tensor | None) -> dict[str, float] | None:
        return None if vector is None else dict(zip(self.modalities, vector.tolist(), strict=True))

    def _gradient(self, x: torch.Tensor, presence: torch.Tensor, nms: tuple, top_k: int) -> Attribution:
        x = x.detach().requires_grad_(True)
        hw = tuple(x.shape[2:])
        with torch.enable_grad():
            all_boxes, probabilities = self.model.decode(self.model(x, presence), hw)
            dets = postprocess(all_boxes.detach(), probabilities.detach(), hw, *nms)[0]
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
