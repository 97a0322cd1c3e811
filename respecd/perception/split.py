"""The detector split into the stages attribution runs, and the interface a runtime provides.

Attribution asks what the detector finds with some sensors switched off (zero plane, presence 0:
what the daemon feeds a disabled sensor): each sensor off, each sensor alone. The backbones see
the frame once; only fusion, neck and head run again per subset of sensors. A runtime (PyTorch
here, an exported graph elsewhere) provides that split as a ``SplitNet``:

* ``encode_rgb(rgb)``: (1, 3, H, W) float 0..1, H and W multiples of 32 -> RGB features;
* ``encode_aux(aux, presence)``: (1, A, H, W) aligned aux planes and (1, A) 0/1 presence flags, in
  ``spec.aux_modalities`` order -> aux features;
* ``detect(rgb, aux, input_hw, near=None)``: fusion + neck + head + decoding of one pair of
  features -> boxes (1, N, 4) x1y1x2y2 in input pixels and class probabilities (1, N, nc), as
  torch tensors, as the net's ``decode`` gives them (its score calibration applied). Without
  ``near``: every anchor, in the head's order (what NMS reads). With ``near`` (K, 4) target
  boxes: at least every anchor that could hold a box overlapping one of them with IoU >=
  ``MATCH_IOU`` (a runtime may return more, e.g. all; never fewer);
* ``spec``: the ``ModelSpec`` (aux modalities, classes).

A forward pass is ``detect(encode_rgb(x[:, :3]), encode_aux(x[:, 3:], presence), hw)``
(``forward``): ``FusionDetector`` runs every frame through ``self.split`` and hands the same net
to ``Attributor``, which takes any ``SplitNet`` (``as_split`` passes one through), so a runtime
that provides the split serves detection and the default attribution alike.

Features are opaque to the caller: whatever the runtime hands between its own stages (the
P3-P5 tensors of each backbone, a dict of Darknet taps, numpy arrays). The caller caches what
does not depend on the frame: the RGB features of a black frame and the aux features with every
aux sensor off, per input size. ``as_split(model)`` gives the PyTorch split of ``FusionNet`` and
``DarknetFusionNet``; any other net with ``forward(x, presence)`` and ``decode(raw, hw)`` gets a
split whose "features" are its inputs and whose ``detect`` is a whole forward pass (the same
numbers, more compute).
"""

from __future__ import annotations

from typing import Any, Protocol

import torch

from respecd.perception.config import ModelSpec
from respecd.perception.darknet_fusion import DarknetFusionNet
from respecd.perception.model import STRIDES, FusionNet, Window, anchor_cells

MATCH_IOU = 0.5  # a box with a sensor off is "the same detection" if it overlaps the target this much
Scored = tuple[torch.Tensor, torch.Tensor]  # boxes (1, N, 4), class probabilities (1, N, nc)


class SplitNet(Protocol):
    """The detector as attribution runs it (module doc)."""

    spec: ModelSpec

    def encode_rgb(self, rgb: torch.Tensor) -> Any: ...

    def encode_aux(self, aux: torch.Tensor, presence: torch.Tensor) -> Any: ...

    def detect(self, rgb: Any, aux: Any, input_hw: tuple[int, int], near: torch.Tensor | None = None) -> Scored: ...


class FusionNetSplit:
    """``FusionNet``: P3-P5 of each backbone; with ``near`` the head runs on the candidate windows only."""

    def __init__(self, model: FusionNet) -> None:
        self.model, self.spec = model, model.spec

    def encode_rgb(self, rgb: torch.Tensor) -> Any:
        return self.model.encode_rgb(rgb)

    def encode_aux(self, aux: torch.Tensor, presence: torch.Tensor) -> Any:
        return self.model.encode_aux(aux, presence)

    def detect_all(self, x: torch.Tensor, presence: torch.Tensor) -> Scored:
        """``forward`` in one call of the net: an exported runtime runs it as one graph (parts.py "net")."""
        return self.model.decode(self.model(x, presence), (x.shape[2], x.shape[3]))

    def detect(self, rgb: Any, aux: Any, input_hw: tuple[int, int], near: torch.Tensor | None = None) -> Scored:
        if near is None:
            return self.model.decode(self.model.fuse(rgb, aux), input_hw)
        raw, anchors = self.model.fuse_window(rgb, aux, candidate_windows(near, input_hw))
        return self.model.decode(raw, input_hw, anchors)


class DarknetSplit:
    """``DarknetFusionNet``: backbone 1's taps and backbone 2's gated evidence; the head runs whole."""

    def __init__(self, model: DarknetFusionNet) -> None:
        self.model, self.spec = model, model.spec

    def encode_rgb(self, rgb: torch.Tensor) -> Any:
        return self.model.encode_rgb(rgb)

    def encode_aux(self, aux: torch.Tensor, presence: torch.Tensor) -> Any:
        return self.model.encode_aux(aux, presence)

    def detect(self, rgb: Any, aux: Any, input_hw: tuple[int, int], near: torch.Tensor | None = None) -> Scored:
        return self.model.decode(self.model.fuse_taps(rgb, aux), input_hw)


class WholeNetSplit:
    """Any net with ``forward(x, presence)`` and ``decode(raw, hw)``: the inputs are the "features"."""

    def __init__(self, model: Any) -> None:
        self.model, self.spec = model, model.spec

    def encode_rgb(self, rgb: torch.Tensor) -> Any:
        return rgb

    def encode_aux(self, aux: torch.Tensor, presence: torch.Tensor) -> Any:
        return aux, presence

    def detect(self, rgb: Any, aux: Any, input_hw: tuple[int, int], near: torch.Tensor | None = None) -> Scored:
        planes, presence = aux
        return self.model.decode(self.model(torch.cat([rgb, planes], 1), presence), input_hw)


def forward(split: SplitNet, x: torch.Tensor, presence: torch.Tensor) -> Scored:
    """Every sensor as given, (1, 3 + A, H, W) and (1, A): all anchors' boxes and class probabilities
    (through the split's ``detect_all`` where it has one: the same numbers, one call)."""
    whole = getattr(split, "detect_all", None)
    if whole is not None:
        return whole(x, presence)
    return split.detect(split.encode_rgb(x[:, :3]), split.encode_aux(x[:, 3:], presence), (x.shape[2], x.shape[3]))


def as_split(model: Any) -> SplitNet:
    """``model`` itself when it already is a ``SplitNet`` (another runtime's), else its PyTorch split."""
    if isinstance(model, FusionNet):
        return FusionNetSplit(model)
    if isinstance(model, DarknetFusionNet):
        return DarknetSplit(model)
    if all(callable(getattr(model, name, None)) for name in ("encode_rgb", "encode_aux", "detect")):
        return model
    return WholeNetSplit(model)


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
