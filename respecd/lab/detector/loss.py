"""YOLOv8's training objective: task-aligned assignment, BCE classes, CIoU boxes, DFL.

The assigner (Feng et al., TOOD) picks, for every ground-truth box, the ``topk`` anchors
inside it with the best alignment ``score^alpha * IoU^beta`` and soft-labels them with the
normalized alignment, so classification confidence learns to track localisation quality.
Gains and hyper-parameters are ultralytics' defaults for YOLOv8.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from respecd.perception.boxes import box_iou, ciou
from respecd.perception.model import anchor_grid, decode_boxes


@dataclass(frozen=True)
class LossGains:
    box: float = 7.5
    cls: float = 0.5
    dfl: float = 1.5
    topk: int = 10
    alpha: float = 0.5
    beta: float = 6.0


def assign(
    scores: torch.Tensor, boxes: torch.Tensor, points: torch.Tensor, strides: torch.Tensor, gt_boxes: torch.Tensor,
    gt_labels: torch.Tensor, gt_mask: torch.Tensor, g: LossGains, reg_max: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Task-aligned assignment for one batch.

    scores (B, N, nc) sigmoid, boxes (B, N, 4) px, points (N, 2) px, strides (N, 1) px,
    gt_boxes (B, M, 4), gt_labels (B, M) long, gt_mask (B, M) bool. Returns target boxes
    (B, N, 4), target scores (B, N, nc) and the foreground mask (B, N).

    Candidates are the anchors inside a box that can also *represent* it: the DFL head
    reaches at most reg_max - 1 strides to each side, so a P3 anchor (stride 8, 16 bins)
    cannot draw a box taller than 240 px, nor a P4 one taller than 480. Without this a tall
    person lands on P4 anchors that learn to stop at 480 px, and P5 is never trained.
    """
    bsz, n, nc = scores.shape
    inside = _inside(points, gt_boxes) & _reachable(points, strides, gt_boxes, reg_max) & gt_mask[:, :, None]
    iou = torch.stack([box_iou(gt_boxes[i], boxes[i]) for i in range(bsz)]).clamp(0)  # (B, M, N)
    cls_score = scores.gather(2, gt_labels[:, None, :].expand(bsz, n, -1)).transpose(1, 2)  # (B, M, N)
    metric = cls_score.pow(g.alpha) * iou.pow(g.beta) * inside
    k = min(g.topk, n)
    top = metric.topk(k, dim=-1).indices  # (B, M, k)
    pos = torch.zeros_like(metric, dtype=torch.bool).scatter_(-1, top, True) & inside & (metric > 0)
    # an anchor claimed by several boxes goes to the one it overlaps most
    multi = pos.sum(1, keepdim=True) > 1  # (B, 1, N)
    best = F.one_hot((iou * inside).argmax(1), pos.shape[1]).transpose(1, 2).bool()  # (B, M, N)
    pos = torch.where(multi, best & pos.any(1, keepdim=True), pos)
    fg = pos.any(1)  # (B, N)
    gt_idx = pos.float().argmax(1)  # (B, N)
    t_boxes = gt_boxes.gather(1, gt_idx[..., None].expand(-1, -1, 4))  # (B, N, 4)
    t_labels = gt_labels.gather(1, gt_idx)  # (B, N)
    metric = metric * pos
    norm = metric * (iou * pos).amax(-1, keepdim=True) / (metric.amax(-1, keepdim=True) + 1e-9)
    t_scores = F.one_hot(t_labels, nc).float() * norm.amax(1)[..., None] * fg[..., None]  # (B, N, nc)
    return t_boxes, t_scores, fg


def _reachable(points: torch.Tensor, strides: torch.Tensor, gt_boxes: torch.Tensor, reg_max: int) -> torch.Tensor:
    """(B, M, N): every side of the box within the anchor's DFL range (reg_max - 1 strides)."""
    p = points[None, None]  # (1, 1, N, 2)
    ltrb = torch.cat([p - gt_boxes[:, :, None, :2], gt_boxes[:, :, None, 2:] - p], -1)  # (B, M, N, 4) px
    return ltrb.amax(-1) <= (reg_max - 1) * strides[None, None, :, 0]


def _inside(points: torch.Tensor, gt_boxes: torch.Tensor) -> torch.Tensor:
    """(B, M, N): anchor centre strictly inside the box."""
    p = points[None, None]  # (1, 1, N, 2)
    lt = p - gt_boxes[:, :, None, :2]
    rb = gt_boxes[:, :, None, 2:] - p
    return torch.cat([lt, rb], -1).amin(-1) > 1e-9


def detection_loss(
    box_logits: torch.Tensor, cls_logits: torch.Tensor, input_hw: tuple[int, int], gt_boxes: torch.Tensor,
    gt_labels: torch.Tensor, gt_mask: torch.Tensor, reg_max: int, g: LossGains = LossGains(),
) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss (scalar) and its parts; ground truth padded to (B, M, ...) with ``gt_mask``."""
    points, strides = anchor_grid(*input_hw, device=box_logits.device)
    boxes = decode_boxes(box_logits, points, strides, reg_max)  # (B, N, 4) px
    with torch.no_grad():
        t_boxes, t_scores, fg = assign(cls_logits.sigmoid(), boxes, points, strides, gt_boxes, gt_labels, gt_mask, g,
                                       reg_max)
    norm = t_scores.sum().clamp(min=1.0)
    loss_cls = F.binary_cross_entropy_with_logits(cls_logits, t_scores, reduction="sum") / norm
    loss_box = box_logits.new_zeros(())
    loss_dfl = box_logits.new_zeros(())
    if fg.any():
        weight = t_scores.sum(-1)[fg]  # (P,)
        loss_box = ((1.0 - ciou(boxes[fg], t_boxes[fg])) * weight).sum() / norm
        loss_dfl = (_dfl(box_logits[fg], t_boxes[fg], points.expand_as(boxes[..., :2])[fg],
                         strides.expand(*fg.shape, 1)[fg], reg_max) * weight).sum() / norm
    total = g.box * loss_box + g.cls * loss_cls + g.dfl * loss_dfl
    return total, {"box": float(loss_box.detach()), "cls": float(loss_cls.detach()), "dfl": float(loss_dfl.detach())}


def _dfl(logits: torch.Tensor, t_boxes: torch.Tensor, points: torch.Tensor, strides: torch.Tensor, reg_max: int):
    """Distribution focal loss: cross-entropy to the two bins around each target distance."""
    ltrb = torch.cat([points - t_boxes[:, :2], t_boxes[:, 2:] - points], -1) / strides  # (P, 4) stride units
    target = ltrb.clamp(0, reg_max - 1 - 0.01)
    left = target.long()
    w_left = left + 1 - target
    logits = logits.view(-1, reg_max)  # (P*4, reg_max)
    ce_l = F.cross_entropy(logits, left.view(-1), reduction="none").view(-1, 4)
    ce_r = F.cross_entropy(logits, (left + 1).view(-1), reduction="none").view(-1, 4)
    return (ce_l * w_left + ce_r * (1 - w_left)).mean(-1)  # (P,)
