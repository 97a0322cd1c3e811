"""The two-backbone YOLOv8-style fusion detector, in plain PyTorch.

Backbone 1 sees R, G, B; backbone 2 sees the aligned non-RGB channels (thermal, radar,
optionally depth) plus one constant presence plane per modality, so that "sensor off"
and "cold, empty scene" are different inputs. Their P3-P5 features are concatenated
(mid-level fusion) and go through a YOLOv8 FPN/PAN neck into an anchor-free decoupled
head with DFL box regression. Everything is convolutional: any input whose sides are
multiples of 32 works, and the cost scales with the pixel count.

Layer recipe follows ultralytics' ``yolov8.yaml`` (Conv-BN-SiLU, C2f, SPPF); the code is
our own.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch
from torch import nn

from respecd.perception import fold
from respecd.perception.calibration import ScoreCalibration, calibrated
from respecd.perception.config import ModelSpec
from respecd.perception.parts import Call, Engine, Part, names

STRIDES = (8, 16, 32)  # P3, P4, P5
HEAD_HALO = 2  # cells of context a head cell needs: each branch has two 3x3 convolutions before its 1x1
Window = tuple[int, int, int, int]  # cells of one head level: first row, end row, first column, end column
Branch = Callable[[int, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]  # (level, crop) -> box, class maps


class Conv(nn.Module):
    """Conv2d (no bias) -> BatchNorm -> SiLU; ``k`` odd, 'same' padding before striding."""

    def __init__(self, c_in: int, c_out: int, k: int = 1, s: int = 1) -> None:
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, k, s, k // 2, bias=False)
        self.bn: nn.Module = nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.03)
        self.act = nn.SiLU(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))

    def fold_batchnorm(self) -> None:
        """Inference only: the batch norm merged into the convolution (same output, one op less)."""
        if isinstance(self.bn, nn.BatchNorm2d):
            fold.fold_batchnorm(self.conv, self.bn)
            self.bn = nn.Identity()


class Bottleneck(nn.Module):
    def __init__(self, c: int, shortcut: bool) -> None:
        super().__init__()
        self.cv1 = Conv(c, c, 3)
        self.cv2 = Conv(c, c, 3)
        self.add = shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.cv2(self.cv1(x))
        return x + y if self.add else y


class C2f(nn.Module):
    """CSP block with two convolutions: split, n bottlenecks, concat every stage's output."""

    def __init__(self, c_in: int, c_out: int, n: int = 1, shortcut: bool = False) -> None:
        super().__init__()
        self.c = c_out // 2
        self.cv1 = Conv(c_in, 2 * self.c, 1)
        self.cv2 = Conv((2 + n) * self.c, c_out, 1)
        self.m = nn.ModuleList(Bottleneck(self.c, shortcut) for _ in range(n))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = list(self.cv1(x).chunk(2, dim=1))  # 2 x (B, c, H, W)
        for block in self.m:
            y.append(block(y[-1]))
        return self.cv2(torch.cat(y, dim=1))  # (B, (2+n)c, H, W) -> (B, c_out, H, W)


class SPPF(nn.Module):
    """Spatial pyramid pooling (fast): three chained 5x5 max-pools, concatenated."""

    def __init__(self, c_in: int, c_out: int, k: int = 5) -> None:
        super().__init__()
        c_hidden = c_in // 2
        self.cv1 = Conv(c_in, c_hidden, 1)
        self.cv2 = Conv(c_hidden * 4, c_out, 1)
        self.pool = nn.MaxPool2d(k, 1, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = [self.cv1(x)]
        for _ in range(3):
            y.append(self.pool(y[-1]))
        return self.cv2(torch.cat(y, dim=1))  # (B, 4*c_hidden, H, W) -> (B, c_out, H, W)


class Backbone(nn.Module):
    """CSPDarknet as in YOLOv8: returns features at strides 8, 16, 32."""

    def __init__(self, c_in: int, w: tuple[int, ...], d: tuple[int, ...]) -> None:
        super().__init__()
        self.stem = nn.Sequential(Conv(c_in, w[0], 3, 2), Conv(w[0], w[1], 3, 2), C2f(w[1], w[1], d[0], True))
        self.p3 = nn.Sequential(Conv(w[1], w[2], 3, 2), C2f(w[2], w[2], d[1], True))
        self.p4 = nn.Sequential(Conv(w[2], w[3], 3, 2), C2f(w[3], w[3], d[2], True))
        self.p5 = nn.Sequential(Conv(w[3], w[4], 3, 2), C2f(w[4], w[4], d[3], True), SPPF(w[4], w[4]))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        p3 = self.p3(self.stem(x))  # (B, w2, H/8, W/8)
        p4 = self.p4(p3)  # (B, w3, H/16, W/16)
        return p3, p4, self.p5(p4)  # P5: (B, w4, H/32, W/32)


class Neck(nn.Module):
    """YOLOv8 FPN (top-down) + PAN (bottom-up) over the fused P3, P4, P5."""

    def __init__(self, c: tuple[int, int, int], w: tuple[int, int, int], n: int) -> None:
        super().__init__()
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        self.td4 = C2f(c[2] + c[1], w[1], n)
        self.td3 = C2f(w[1] + c[0], w[0], n)
        self.down3 = Conv(w[0], w[0], 3, 2)
        self.bu4 = C2f(w[0] + w[1], w[1], n)
        self.down4 = Conv(w[1], w[1], 3, 2)
        self.bu5 = C2f(w[1] + c[2], w[2], n)

    def forward(self, f3: torch.Tensor, f4: torch.Tensor, f5: torch.Tensor) -> list[torch.Tensor]:
        t4 = self.td4(torch.cat([self.up(f5), f4], 1))  # (B, w1, H/16, W/16)
        o3 = self.td3(torch.cat([self.up(t4), f3], 1))  # (B, w0, H/8, W/8)
        o4 = self.bu4(torch.cat([self.down3(o3), t4], 1))  # (B, w1, H/16, W/16)
        o5 = self.bu5(torch.cat([self.down4(o4), f5], 1))  # (B, w2, H/32, W/32)
        return [o3, o4, o5]


class Head(nn.Module):
    """Anchor-free decoupled head: a box branch (4 x reg_max DFL logits) and a class branch."""

    def __init__(self, c: tuple[int, int, int], nc: int, reg_max: int) -> None:
        super().__init__()
        self.nc, self.reg_max = nc, reg_max
        cb = max(16, c[0] // 4, reg_max * 4)
        cc = max(c[0], min(nc, 100))
        self.box = nn.ModuleList(
            nn.Sequential(Conv(ci, cb, 3), Conv(cb, cb, 3), nn.Conv2d(cb, 4 * reg_max, 1)) for ci in c
        )
        self.cls = nn.ModuleList(nn.Sequential(Conv(ci, cc, 3), Conv(cc, cc, 3), nn.Conv2d(cc, nc, 1)) for ci in c)
        for box, cls, s in zip(self.box, self.cls, STRIDES, strict=True):  # each an nn.Sequential
            nn.init.constant_(box[-1].bias, 1.0)  # type: ignore[index]
            # prior: ~5 objects per 640x640 image (ultralytics' bias init)
            nn.init.constant_(cls[-1].bias, math.log(5 / nc / (640 / s) ** 2))  # type: ignore[index]

    def forward(self, feats: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        boxes = [box(f).flatten(2) for f, box in zip(feats, self.box, strict=True)]  # (B, 4*reg_max, h*w)
        # (B, N, 4*reg_max) and (B, N, nc), N = sum of h*w over P3..P5
        return torch.cat(boxes, 2).transpose(1, 2), self.classify(feats)

    def classify(self, feats: list[torch.Tensor]) -> torch.Tensor:
        logits = [cls(f).flatten(2) for f, cls in zip(feats, self.cls, strict=True)]  # (B, nc, h*w)
        return torch.cat(logits, 2).transpose(1, 2)

    def branches(self, level: int, crop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One level's box and class maps (B, 4*reg_max, h, w), (B, nc, h, w) of a feature map or a crop."""
        return self.box[level](crop), self.cls[level](crop)

    def window(self, feats: list[torch.Tensor] | tuple[torch.Tensor, ...], windows: list[Window],
               branch: Branch | None = None) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """The head on each level's window only (a crop with HEAD_HALO cells of context): attribution needs
        the anchors near its targets, and the head is a quarter of a forward pass. Returns the raw output of
        those cells, as ``forward`` orders it, and their (n,) indices among ``forward``'s N anchors.
        ``branch``: what runs a level's branches on a crop (default ``branches``: these modules)."""
        branch = branch or self.branches
        boxes, classes, index = [], [], []
        offset = 0
        for level, (f, (r0, r1, c0, c1)) in enumerate(zip(feats, windows, strict=True)):
            h, w = f.shape[2:]
            if r1 > r0 and c1 > c0:
                a0, b0 = max(0, r0 - HEAD_HALO), max(0, c0 - HEAD_HALO)
                crop = f[:, :, a0 : min(h, r1 + HEAD_HALO), b0 : min(w, c1 + HEAD_HALO)]
                inner = (..., slice(r0 - a0, r1 - a0), slice(c0 - b0, c1 - b0))
                box, cls = branch(level, crop)
                boxes.append(box[inner].flatten(2))
                classes.append(cls[inner].flatten(2))
                cells = torch.arange(r0, r1, device=f.device)[:, None] * w + torch.arange(c0, c1, device=f.device)
                index.append(offset + cells.flatten())
            offset += h * w
        if not index:
            b = feats[0].shape[0]
            empty = feats[0].new_zeros(b, 0, 4 * self.reg_max), feats[0].new_zeros(b, 0, self.nc)
            return empty, torch.zeros(0, dtype=torch.long, device=feats[0].device)
        raw = torch.cat(boxes, 2).transpose(1, 2), torch.cat(classes, 2).transpose(1, 2)
        return raw, torch.cat(index)


Features = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # P3, P4, P5 of one backbone


class FusionNet(nn.Module):
    """RGB backbone + aux backbone -> concat at P3-P5 -> neck -> head.

    ``forward`` is ``fuse(encode_rgb(rgb), encode_aux(aux, presence))``; the parts are
    public so that attribution can switch one sensor off without re-running the other
    backbone (a sensor that is off feeds a zero plane, so its features depend only on the
    input size). With ``engine`` set (an exported runtime, ``respecd.perception.runtimes``)
    each part runs there instead of in torch: ``export_parts`` names them.
    """

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        self.spec = spec
        self.score_calibration: ScoreCalibration | None = None  # set by FusionDetector.load, never trained
        self.engine: Engine | None = None  # set by FusionDetector.load for runtime onnxruntime / openvino
        n_aux = len(spec.aux_modalities)
        self.rgb = Backbone(3, spec.rgb_widths, spec.depths)
        self.aux = Backbone(2 * n_aux, spec.aux_widths, spec.depths)  # data planes + presence planes
        fused = tuple(a + b for a, b in zip(spec.rgb_widths[2:], spec.aux_widths[2:], strict=True))
        self.neck = Neck(fused, spec.neck_widths, spec.depths[0])  # type: ignore[arg-type]
        self.head = Head(spec.neck_widths, len(spec.classes), spec.reg_max)

    def forward(self, x: torch.Tensor, presence: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``x``: (B, 3 + A, H, W) in 0..1, H and W multiples of 32; ``presence``: (B, A) 0/1.

        Returns DFL box logits (B, N, 4 * reg_max) and class logits (B, N, nc).
        """
        if self.engine is not None:  # one graph: the runtime keeps its own layout between backbones and fusion
            aux = x[:, 3:]
            presence = aux.new_ones(aux.shape[:2]) if presence is None else presence.to(aux.dtype)
            return self.engine("net", x[:, :3], aux, presence)  # type: ignore[return-value]
        return self.fuse(self.encode_rgb(x[:, :3]), self.encode_aux(x[:, 3:], presence))

    def fold_batchnorm(self) -> None:
        """For inference (the detector does it): every batch norm folded into its convolution, one pass over
        each feature map less; outputs equal to float precision. Not trainable after."""
        for module in self.modules():
            if isinstance(module, Conv):
                module.fold_batchnorm()

    def encode_rgb(self, rgb: torch.Tensor) -> Features:
        """(B, 3, H, W) -> the RGB backbone's P3, P4, P5."""
        if self.engine is not None:
            return self.engine("rgb", rgb)  # type: ignore[return-value]
        return self.rgb(rgb)

    def encode_aux(self, aux: torch.Tensor, presence: torch.Tensor | None = None) -> Features:
        """(B, A, H, W) aligned non-RGB planes and (B, A) presence flags -> the aux backbone's P3, P4, P5."""
        b, a, h, w = aux.shape
        if presence is None:
            presence = aux.new_ones(b, a)
        if self.engine is not None:
            return self.engine("aux", aux, presence.to(aux.dtype))  # type: ignore[return-value]
        planes = presence.to(aux.dtype)[:, :, None, None].expand(b, a, h, w)  # (B, A, H, W)
        return self.aux(torch.cat([aux, planes], 1))  # input (B, 2A, H, W)

    def fuse(self, rgb: Features, aux: Features) -> tuple[torch.Tensor, torch.Tensor]:
        """Concat per level -> neck -> head: the raw output (box logits, class logits)."""
        if self.engine is not None:
            return self.engine("fuse", *rgb, *aux)  # type: ignore[return-value]
        return self.head(self._neck(rgb, aux))

    def fuse_window(self, rgb: Features, aux: Features,
                    windows: list[Window]) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``fuse`` with the head run on each level's window only (``Head.window``): raw output and anchor indices."""
        if self.engine is None:
            return self.head.window(self._neck(rgb, aux), windows)
        engine = self.engine
        return self.head.window(engine("neck", *rgb, *aux), windows, lambda i, crop: engine(f"head{i}", crop))  # type: ignore[arg-type,return-value]

    def _neck(self, rgb: Features, aux: Features) -> list[torch.Tensor]:
        return self.neck(*(torch.cat([r, a], 1) for r, a in zip(rgb, aux, strict=True)))

    def export_parts(self, x: torch.Tensor, presence: torch.Tensor) -> list[Part]:
        """The parts a runtime runs (``engine``), with example inputs from ``x`` (1, C, H, W): the whole net (a
        forward pass), the backbone per modality, neck + head, the neck alone and each level's head branches
        (attribution's windows)."""
        with torch.no_grad():
            rgb, aux = self.rgb(x[:, :3]), self.encode_aux(x[:, 3:], presence)
            feats = self._neck(rgb, aux)
        features = (*names("rgb", 3), *names("aux", 3))
        parts = [
            Part("net", Call(self, lambda n, r, a, p: n.fuse(n.rgb(r), n.encode_aux(a, p))),
                 (x[:, :3], x[:, 3:], presence), ("rgb", "aux", "presence"), ("box", "cls")),
            Part("rgb", Call(self, lambda n, r: n.rgb(r)), (x[:, :3],), ("rgb",), names("rgb", 3)),
            Part("aux", Call(self, lambda n, a, p: n.encode_aux(a, p)), (x[:, 3:], presence), ("aux", "presence"),
                 names("aux", 3)),
            Part("fuse", Call(self, lambda n, *f: n.fuse(f[:3], f[3:])), (*rgb, *aux), features, ("box", "cls")),
            Part("neck", Call(self, lambda n, *f: n._neck(f[:3], f[3:])), (*rgb, *aux), features, names("p", 3)),
        ]
        for level, f in enumerate(feats):
            parts.append(Part(f"head{level}", Call(self, lambda n, c, i=level: n.head.branches(i, c)), (f,),
                              ("p",), ("box", "cls")))
        return parts

    def decode(self, raw: tuple[torch.Tensor, torch.Tensor], input_hw: tuple[int, ...],
               anchors: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw head output -> boxes (B, N, 4) x1y1x2y2 in input pixels and class probabilities (B, N, nc),
        calibrated for the input size when the checkpoint carries a calibration. ``anchors``: the raw output
        holds only these anchors (``fuse_window``'s indices)."""
        box_logits, cls_logits = raw
        height, width = input_hw
        points, strides = cached_anchor_grid(height, width, box_logits.device)
        if anchors is not None:
            points, strides = points[anchors], strides[anchors]
        boxes = decode_boxes(box_logits, points, strides, self.spec.reg_max)
        return boxes, calibrated(self.score_calibration, cls_logits.sigmoid(), input_hw)


def anchor_grid(height: int, width: int, device: torch.device | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor centres (N, 2) in pixels and their strides (N, 1), in the head's output order."""
    points, strides = [], []
    for s in STRIDES:
        ys, xs = torch.meshgrid(
            torch.arange(height // s, device=device, dtype=torch.float32),
            torch.arange(width // s, device=device, dtype=torch.float32),
            indexing="ij",
        )
        points.append((torch.stack([xs, ys], -1).reshape(-1, 2) + 0.5) * s)  # (h*w, 2) cell centres
        strides.append(torch.full((xs.numel(), 1), float(s), device=device))
    return torch.cat(points), torch.cat(strides)


@functools.lru_cache(maxsize=16)
def cached_anchor_grid(height: int, width: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``anchor_grid``, made once per input size (every frame decodes at the same few sizes; building it
    costs as much as NMS). Made outside inference mode so autograd may read it; callers never write to it."""
    with torch.inference_mode(False):
        return anchor_grid(height, width, device)


def anchor_cells(lo: float, hi: float, stride: int, count: int) -> tuple[int, int]:
    """Along one axis of a level with ``count`` cells: the cells (first, end) whose anchor centre, (i + 0.5) x
    ``stride`` as ``anchor_grid`` places it, lies in [lo, hi]."""
    return max(0, math.ceil(lo / stride - 0.5)), min(count, math.floor(hi / stride - 0.5) + 1)


def dfl_expectation(box_logits: torch.Tensor, reg_max: int) -> torch.Tensor:
    """(B, N, 4*reg_max) logits -> (B, N, 4) expected distances left, top, right, bottom in stride units."""
    b, n, _ = box_logits.shape
    prob = box_logits.view(b, n, 4, reg_max).softmax(-1)  # (B, N, 4, reg_max)
    bins = torch.arange(reg_max, device=box_logits.device, dtype=prob.dtype)
    return prob @ bins  # (B, N, 4)


def decode_boxes(box_logits: torch.Tensor, points: torch.Tensor, strides: torch.Tensor, reg_max: int) -> torch.Tensor:
    """Box logits -> (B, N, 4) boxes x1, y1, x2, y2 in input pixels."""
    ltrb = dfl_expectation(box_logits, reg_max) * strides  # (B, N, 4) pixels
    return torch.cat([points - ltrb[..., :2], points + ltrb[..., 2:]], -1)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
