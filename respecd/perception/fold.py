"""Inference-time rewrites of a trained net: fewer ops for the same outputs.

At inference a batch norm is a fixed per-channel affine map, so it can be merged into the
convolution before it: one pass over the feature map less per layer. On CPU, channels-last
memory (NHWC) lets oneDNN run the convolutions without reordering every tensor (what the
two save: docs/PERFORMANCE.md "perception"). Both are for inference only: a folded net has
no batch norms left to train, and the detector never saves it.
"""

from __future__ import annotations

from typing import TypeVar

import torch
from torch import nn

NetT = TypeVar("NetT", bound=nn.Module)


@torch.no_grad()
def fold_batchnorm(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> None:
    """``conv`` becomes ``bn(conv(x))`` with ``bn``'s running statistics (it gains a bias)."""
    if bn.running_mean is None or bn.running_var is None:
        raise ValueError("batch norm without running statistics")
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    bias = conv.bias if conv.bias is not None else torch.zeros_like(bn.running_mean)
    conv.weight.mul_(scale.reshape(-1, *([1] * (conv.weight.dim() - 1))))
    conv.bias = nn.Parameter((bias - bn.running_mean) * scale + bn.bias, requires_grad=conv.weight.requires_grad)


def for_inference(model: NetT, device: torch.device) -> NetT:
    """``model`` in eval mode with its batch norms folded (a net that offers ``fold_batchnorm``)
    and, on CPU, in channels-last memory; feed it ``channels_last(x)``."""
    model.eval()
    fold_all = getattr(model, "fold_batchnorm", None)
    if fold_all is not None:
        fold_all()
    if device.type == "cpu":
        model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stub lacks it
    return model


def channels_last(x: torch.Tensor) -> torch.Tensor:
    """A (B, C, H, W) input in the layout ``for_inference`` put the net in on CPU."""
    return x.contiguous(memory_format=torch.channels_last) if x.device.type == "cpu" else x
