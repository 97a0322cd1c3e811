"""The CSP net rewritten for ONNX Runtime's blocked convolutions: the same outputs, fewer copies.

ONNX Runtime's CPU provider runs a convolution in MLAS's NCHWc layout (channels in blocks of 16 on
AVX-512, 8 on AVX2) and converts a tensor back to plain NCHW for any op it cannot run blocked.
``for_export`` gives ``export`` a copy of the net with two such ops rewritten:

* A C2f block splits ``cv1``'s output into two channel halves (a Slice), so each C2f paid three
  layout conversions and ran its residual add and concat in NCHW. ``BlockedC2f`` computes the
  halves with two convolutions and zero-pads each to a multiple of ``BLOCK`` channels, so the
  concat stays blocked. The zero channels stay zero (bias 0, SiLU(0) = 0, 0 + 0) and meet zero
  weights in ``cv2``. A half that padding would widen by more than a third (8 -> 16) is left as
  it was: its extra multiply-adds cost more than the conversions they save.
* The head's (B, C, h, w) maps were flattened, concatenated and transposed to (B, N, C): two
  passes. ``ChannelsLastHead`` permutes each map first, which ONNX Runtime folds into the layout
  conversion it does anyway.

The torch path never runs this (docs/PERFORMANCE.md "inference runtimes" has what it saves).
"""

from __future__ import annotations

import copy
from typing import cast

import torch
from torch import nn

from respecd.perception.model import Bottleneck, C2f, Conv, Head

BLOCK = 16  # MLAS's NCHWc block on AVX-512 (a multiple of AVX2's 8)


def padded(c: int, block: int = BLOCK) -> int:
    """``c`` rounded up to a multiple of ``block``."""
    return -(-c // block) * block


def worth_blocking(c: int, block: int = BLOCK) -> bool:
    """Whether a C2f with halves of ``c`` channels is rewritten: padding adds at most a third."""
    return 3 * (padded(c, block) - c) <= c


def for_export(net: nn.Module, block: int = BLOCK) -> nn.Module:
    """A copy of a folded CSP net (``FusionNet``) with ``BlockedC2f`` blocks where ``worth_blocking`` and a
    ``ChannelsLastHead``; a net without C2f blocks (the Darknet nets) as it is."""
    if not any(isinstance(m, C2f) for m in net.modules()):
        return net
    net = copy.deepcopy(net)
    for parent in list(net.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, C2f) and worth_blocking(child.c, block):
                setattr(parent, name, BlockedC2f(child, padded(child.c, block)))
            elif isinstance(child, Head):
                setattr(parent, name, ChannelsLastHead(child))
    return net


class BlockedC2f(nn.Module):
    """A C2f with ``cv1`` as two convolutions and each half ``width`` channels wide (zero-padded)."""

    def __init__(self, block: C2f, width: int) -> None:
        super().__init__()
        c, n_in = block.c, block.cv1.conv.in_channels
        inner, whole = torch.arange(c), torch.arange(n_in)
        self.cv1a = _placed(block.cv1, inner, whole, width, n_in, rows=slice(0, c))
        self.cv1b = _placed(block.cv1, inner, whole, width, n_in, rows=slice(c, 2 * c))
        self.m = nn.ModuleList(_bottleneck(cast(Bottleneck, b), inner, width) for b in block.m)
        halves = len(block.m) + 2
        concat = torch.cat([k * width + inner for k in range(halves)])  # channel k*c + r sits at k*width + r
        out = block.cv2.conv.out_channels
        self.cv2 = _placed(block.cv2, torch.arange(out), concat, out, halves * width)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1a(x), self.cv1b(x)]
        for bottleneck in self.m:
            y.append(bottleneck(y[-1]))
        return self.cv2(torch.cat(y, dim=1))


class ChannelsLastHead(nn.Module):
    """``Head`` whose forward permutes each level's maps to (B, h*w, C) before the concat (same numbers)."""

    def __init__(self, head: Head) -> None:
        super().__init__()
        self.head = head

    def forward(self, feats: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        head = self.head
        return _levels(feats, head.box, 4 * head.reg_max), _levels(feats, head.cls, head.nc)

    def branches(self, level: int, crop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.head.branches(level, crop)


def _levels(feats: list[torch.Tensor], branches: nn.ModuleList, channels: int) -> torch.Tensor:
    """Each level's branch output as (B, h*w, channels), concatenated along the anchors."""
    batch = int(feats[0].shape[0])  # a constant in the graph: the exported batch is fixed
    return torch.cat([b(f).permute(0, 2, 3, 1).reshape(batch, -1, channels)
                      for f, b in zip(feats, branches, strict=True)], 1)


def _bottleneck(bottleneck: Bottleneck, inner: torch.Tensor, width: int) -> Bottleneck:
    """``bottleneck`` (two c -> c convolutions, maybe a residual add) at ``width`` channels."""
    wide = copy.deepcopy(bottleneck)
    wide.cv1 = _placed(bottleneck.cv1, inner, inner, width, width)
    wide.cv2 = _placed(bottleneck.cv2, inner, inner, width, width)
    return wide


def _placed(conv: Conv, out_index: torch.Tensor, in_index: torch.Tensor, n_out: int, n_in: int,
            rows: slice = slice(None)) -> Conv:
    """A folded ``Conv`` whose output channels ``rows`` sit at ``out_index`` of ``n_out`` and whose input
    channel i reads channel ``in_index[i]`` of ``n_in``; every other weight and bias is zero."""
    source, bias = conv.conv, conv.conv.bias
    if source.groups != 1 or not isinstance(conv.bn, nn.Identity) or bias is None:
        raise ValueError("blocking needs a folded, ungrouped convolution")
    with torch.no_grad():
        weight = source.weight.new_zeros(n_out, n_in, *source.kernel_size)
        weight[out_index[:, None], in_index[None, :]] = source.weight[rows]
        wide_bias = bias.new_zeros(n_out)
        wide_bias[out_index] = bias[rows]
    wide = nn.Conv2d(n_in, n_out, source.kernel_size, source.stride, source.padding)  # type: ignore[arg-type]
    wide.weight = nn.Parameter(weight.contiguous(memory_format=torch.channels_last), requires_grad=False)
    wide.bias = nn.Parameter(wide_bias, requires_grad=False)
    result = copy.deepcopy(conv)
    result.conv = wide
    return result.eval()
