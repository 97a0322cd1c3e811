"""Box geometry: IoU, non-maximum suppression and post-processing of the head's output.

NMS is our own torch code (no torchvision): sort by score, then suppress greedily with a
pairwise IoU matrix. With tens of candidates above the score threshold this is cheap.
"""

from __future__ import annotations

import math

import torch


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Pairwise IoU of (N, 4) and (M, 4) x1y1x2y2 boxes -> (N, M)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])  # (N, M, 2)
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).clamp(min=0).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).clamp(min=0).prod(-1)
    return inter / (area_a[:, None] + area_b[None, :] - inter + 1e-9)


def ciou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Complete IoU of matched (N, 4) box pairs (Zheng et al.), as YOLOv8's box loss uses."""
    eps = 1e-7
    w1, h1 = a[:, 2] - a[:, 0], (a[:, 3] - a[:, 1]).clamp(min=eps)
    w2, h2 = b[:, 2] - b[:, 0], (b[:, 3] - b[:, 1]).clamp(min=eps)
    inter = (torch.minimum(a[:, 2], b[:, 2]) - torch.maximum(a[:, 0], b[:, 0])).clamp(min=0) * (
        torch.minimum(a[:, 3], b[:, 3]) - torch.maximum(a[:, 1], b[:, 1])
    ).clamp(min=0)
    iou = inter / (w1 * h1 + w2 * h2 - inter + eps)
    cw = torch.maximum(a[:, 2], b[:, 2]) - torch.minimum(a[:, 0], b[:, 0])
    ch = torch.maximum(a[:, 3], b[:, 3]) - torch.minimum(a[:, 1], b[:, 1])
    c2 = cw**2 + ch**2 + eps
    rho2 = ((a[:, 0] + a[:, 2] - b[:, 0] - b[:, 2]) ** 2 + (a[:, 1] + a[:, 3] - b[:, 1] - b[:, 3]) ** 2) / 4
    v = (4 / math.pi**2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Indices of the boxes kept by greedy NMS, highest score first."""
    order = scores.argsort(descending=True)
    boxes = boxes[order]
    iou = box_iou(boxes, boxes)  # (K, K)
    keep = torch.ones(len(order), dtype=torch.bool, device=boxes.device)
    for i in range(len(order)):
        if keep[i]:
            suppress = iou[i] > iou_threshold
            suppress[: i + 1] = False
            keep &= ~suppress
    return order[keep]


def pad_to_stride(height: int, width: int, stride: int = 32) -> tuple[int, int]:
    """The letterboxed input size: each side rounded up to a multiple of ``stride``."""
    return math.ceil(height / stride) * stride, math.ceil(width / stride) * stride


def postprocess(
    boxes: torch.Tensor,
    scores_all: torch.Tensor,
    input_hw: tuple[int, ...],
    score_threshold: float,
    iou_threshold: float,
    max_det: int,
) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Per image: (boxes (K, 4), scores (K,), labels (K,), anchor indices (K,)) after NMS.

    Input is a net's ``decode`` output: boxes (B, N, 4) x1y1x2y2 pixels, class probabilities
    (B, N, nc). The anchor index lets attribution go back to the pre-NMS score that produced
    a box. Class-aware NMS by offsetting boxes per class.
    """
    out = []
    for b in range(boxes.shape[0]):
        scores, labels = scores_all[b].max(-1)  # (N,)
        idx = torch.nonzero(scores > score_threshold).flatten()
        if len(idx) > 30 * max_det:  # bound the O(K^2) NMS
            idx = idx[scores[idx].topk(30 * max_det).indices]
        cand = boxes[b, idx]
        offset = labels[idx, None].to(cand.dtype) * (max(input_hw) + 1)
        keep = nms(cand + offset, scores[idx], iou_threshold)[:max_det]
        sel = idx[keep]
        out.append((boxes[b, sel], scores[sel], labels[sel], sel))
    return out
