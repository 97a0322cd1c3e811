"""Training objective of an anchor-based Darknet yolo head (YOLOv3/v4 assignment, YOLOv5 weighting).

Assignment as Darknet's yolo layer does it: every ground-truth box goes to the anchor
whose shape fits it best, and also to every other anchor with shape IoU above
``iou_thresh`` (0.213 in the Yolo-Fastest cfgs), at the cell holding its centre.
Predictions that already overlap a ground-truth box by more than ``ignore_thresh`` (0.5)
are not pushed toward "no object". Losses: CIoU on the assigned boxes, BCE on
objectness (all cells) and classes (assigned cells); gains and the per-level objectness
balance follow YOLOv5 (box 0.05, obj 1.0, cls 0.5; the finer level weighs more).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from respecd.perception.boxes import box_iou, ciou
from respecd.perception.darknet import YoloSpec, decode_yolo


@dataclass(frozen=True)
class YoloGains:
    box: float = 0.05
    obj: float = 1.0
    cls: float = 0.5
    iou_thresh: float = 0.213
    ignore_thresh: float = 0.5
    balance: tuple[float, ...] = (1.0, 0.4)  # objectness weight per yolo layer, finest first


def _shape_iou(wh: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """(G, 2) box sizes x (K, 2) anchor sizes -> (G, K) IoU of the two boxes centred together."""
    inter = torch.minimum(wh[:, None], anchors[None]).prod(-1)
    return inter / (wh.prod(-1)[:, None] + anchors.prod(-1)[None] - inter + 1e-9)


def yolo_loss(raw: list[torch.Tensor], specs: list[YoloSpec], input_hw: tuple[int, int], gt_boxes: torch.Tensor,
              gt_labels: torch.Tensor, gt_mask: torch.Tensor, g: YoloGains = YoloGains()
              ) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and parts. ``raw``: one (B, A(5+nc), h, w) map per yolo layer; gt padded (B, M, .)."""
    bsz = raw[0].shape[0]
    anchors = torch.tensor([a for s in specs for a in s.anchors], dtype=raw[0].dtype, device=raw[0].device)
    img, slot = torch.nonzero(gt_mask, as_tuple=True)  # (G,) which image, which padded slot
    boxes, labels = gt_boxes[img, slot], gt_labels[img, slot]  # (G, 4), (G,)
    wh = (boxes[:, 2:] - boxes[:, :2]).clamp(min=1.0)
    shape_iou = _shape_iou(wh, anchors)  # (G, K)
    assigned = shape_iou > g.iou_thresh
    if len(boxes):
        assigned[torch.arange(len(boxes)), shape_iou.argmax(1)] = True  # the best anchor even below the threshold
    first = 0
    loss_box = loss_obj = loss_cls = raw[0].new_zeros(())
    n_pos = 0
    for level, (out, spec) in enumerate(zip(raw, specs, strict=True)):
        a = len(spec.anchors)
        k = torch.arange(first, first + a, device=out.device)
        first += a
        parts = _level_loss(out, spec, input_hw, boxes, labels, img, assigned[:, k], gt_boxes, gt_mask, g)
        loss_box = loss_box + parts[0]
        loss_obj = loss_obj + g.balance[min(level, len(g.balance) - 1)] * parts[1]
        loss_cls = loss_cls + parts[2]
        n_pos += parts[3]
    total = (g.box * loss_box + g.obj * loss_obj + g.cls * loss_cls) * bsz
    return total, {"box": float(loss_box.detach()), "obj": float(loss_obj.detach()),
                   "cls": float(loss_cls.detach()), "positives": n_pos}


def _level_loss(out: torch.Tensor, spec: YoloSpec, input_hw: tuple[int, int], boxes: torch.Tensor,
                labels: torch.Tensor, img: torch.Tensor, assigned: torch.Tensor, gt_boxes: torch.Tensor,
                gt_mask: torch.Tensor, g: YoloGains) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int]:
    bsz, _, h, w = out.shape
    a, nc = len(spec.anchors), spec.classes
    rows = decode_yolo(out, spec, input_hw)  # (B, h*w*A, 5+nc): cx, cy, bw, bh, obj, cls (probabilities)
    logits = out.view(bsz, a, 5 + nc, h, w).permute(0, 3, 4, 1, 2).reshape(bsz, h * w * a, 5 + nc)
    pred = torch.cat([rows[..., :2] - rows[..., 2:4] / 2, rows[..., :2] + rows[..., 2:4] / 2], -1)  # (B, N, 4)
    obj_target = torch.zeros(bsz, h * w * a, dtype=out.dtype, device=out.device)
    with torch.no_grad():  # already-good predictions of a real box are not pushed toward "no object"
        weight = torch.ones_like(obj_target)
        for b in range(bsz):
            if gt_mask[b].any():
                best = box_iou(pred[b].detach(), gt_boxes[b][gt_mask[b]]).amax(1)
                weight[b][best > g.ignore_thresh] = 0.0
    gi, ai = torch.nonzero(assigned, as_tuple=True)  # ground truth index, anchor within this level
    if len(gi) == 0:
        loss_obj = F.binary_cross_entropy_with_logits(logits[..., 4], obj_target, weight, reduction="mean")
        return out.new_zeros(()), loss_obj, out.new_zeros(()), 0
    centre = (boxes[gi, :2] + boxes[gi, 2:]) / 2
    cx = (centre[:, 0] / (input_hw[1] / w)).long().clamp(0, w - 1)
    cy = (centre[:, 1] / (input_hw[0] / h)).long().clamp(0, h - 1)
    index = (cy * w + cx) * a + ai  # row of (cell, anchor) in decode_yolo's order
    owner = img[gi]  # the image of each assigned box
    loss_box = (1.0 - ciou(pred[owner, index], boxes[gi])).mean()
    obj_target[owner, index] = 1.0
    weight[owner, index] = 1.0
    loss_obj = F.binary_cross_entropy_with_logits(logits[..., 4], obj_target, weight, reduction="mean")
    cls_target = F.one_hot(labels[gi], nc).to(out.dtype)
    loss_cls = F.binary_cross_entropy_with_logits(logits[owner, index, 5:], cls_target, reduction="mean")
    return loss_box, loss_obj, loss_cls, len(gi)
