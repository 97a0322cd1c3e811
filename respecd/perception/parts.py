"""The pure-tensor parts of a fusion net, so an exported runtime can run them instead of torch.

Each net (``FusionNet``, ``DarknetFusionNet``) splits its forward pass into named parts — the
backbone per modality, the fusion with neck and head, the head's branches per level — and
keeps the glue between them (caches, presence gates, crops) in Python. ``export_parts`` lists
them with example inputs for ``torch.onnx.export``; a net whose ``engine`` is set runs every
part through it (ONNX Runtime, OpenVINO) while the glue stays the same code, so the attribution
that switches sensors off goes through the same runtime as the forward pass.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import nn


class Engine(Protocol):
    """Runs one exported part by name: tensors in, tensors out (CPU tensors, the graph's output order)."""

    def __call__(self, name: str, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]: ...


@dataclass(frozen=True)
class Part:
    """One graph to export: ``module(*example)`` gives the outputs named ``outputs``."""

    name: str
    module: nn.Module
    example: tuple[torch.Tensor, ...]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]


class Call(nn.Module):
    """``fn(net, *inputs)`` as a module that owns ``net`` (so the exporter sees its weights)."""

    def __init__(self, net: nn.Module, fn: Callable[..., tuple[torch.Tensor, ...] | list[torch.Tensor]]) -> None:
        super().__init__()
        self.net = net
        self.fn = fn

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.fn(self.net, *inputs))


def names(prefix: str, count: int) -> tuple[str, ...]:
    """``prefix0``, ``prefix1``, ...: the graph's input or output names for a tuple of tensors."""
    return tuple(f"{prefix}{i}" for i in range(count))
