"""Darknet ``.cfg`` + ``.weights`` -> PyTorch modules, so pretrained Darknet detectors get gradients.

Supported sections: ``[net]``, ``[convolutional]`` (groups, hence depthwise; batch norm;
leaky / linear / relu / logistic / mish / swish), ``[shortcut]``, ``[route]`` (several
layers, or ``groups`` / ``group_id`` channel slices), ``[upsample]``, ``[maxpool]``,
``[dropout]`` (identity at inference) and ``[yolo]``. That covers Yolo-Fastest and the
YOLOv3/v4(-tiny) family.

The ``.weights`` layout is Darknet's (``parser.c``: ``load_weights_upto``,
``load_convolutional_weights``): an int32 header ``major, minor, revision``, then the
images seen (uint64 when ``major * 10 + minor >= 2`` and both < 1000, else int32), then for
every convolutional layer in cfg order: ``filters`` biases, with batch norm ``filters``
scales, rolling means and rolling variances, then ``filters x (channels / groups) x size x
size`` kernel values, all float32 little-endian. Other layers hold no weights. A file that
ends early, or has bytes left after the last layer, is refused with the byte offset.

``DarknetNet.run`` evaluates any slice of the layer list with an explicit store of layer
outputs, which is how the fusion detector shares one Darknet head between two backbones.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from respecd.errors import InputError
from respecd.perception import fold

SUPPORTED = ("net", "convolutional", "shortcut", "route", "upsample", "maxpool", "dropout", "yolo")
BN_EPS = 1e-6  # Darknet (blas.c normalize_cpu) divides by sqrt(variance) + .000001; the same to float precision


@dataclass(frozen=True)
class Section:
    kind: str
    options: dict[str, str]
    line: int  # 1-based line of the section header in the cfg


@dataclass(frozen=True)
class YoloSpec:
    """One ``[yolo]`` output: its anchors (pixels of the network input) and classes."""

    anchors: tuple[tuple[float, float], ...]  # the masked anchors, (w, h)
    classes: int
    scale_x_y: float = 1.0


def parse_cfg(text: str, source: str = "<cfg>") -> list[Section]:
    """Sections in file order; ``key=value`` lines; ``#`` and ``;`` start comments."""
    sections: list[Section] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].split(";", 1)[0].strip()
        if not line:
            continue
        if line.startswith("["):
            if not line.endswith("]"):
                raise InputError(f"{source}:{number}: section header {line!r} has no closing ']'")
            sections.append(Section(line[1:-1].strip().lower(), {}, number))
        elif "=" in line and sections:
            key, value = line.split("=", 1)
            sections[-1].options[key.strip()] = value.strip()
        else:
            raise InputError(f"{source}:{number}: expected [section] or key=value, found {line!r}")
    if not sections or sections[0].kind not in ("net", "network"):
        raise InputError(f"{source}: a Darknet cfg starts with a [net] section")
    for s in sections[1:]:
        if s.kind not in SUPPORTED:
            raise InputError(f"{source}:{s.line}: unsupported Darknet layer [{s.kind}] (supported: "
                             + ", ".join(SUPPORTED[1:]) + ")")
    return sections


def with_classes(sections: list[Section], classes: int) -> list[Section]:
    """The same network with ``classes`` outputs per anchor in every [yolo] layer (and the convolution
    feeding it): how a COCO model becomes a person detector (``darknet_fusion.from_darknet`` keeps the
    chosen classes' kernels)."""
    out = list(sections)
    for i, s in enumerate(sections):
        if s.kind != "yolo" or int(s.options.get("classes", 20)) == classes:
            continue
        opts = _Opts(s, "<cfg>")
        mask = opts.ints("mask", ",".join(str(k) for k in range(len(opts.floats("anchors")) // 2)))
        conv = max(j for j in range(i) if sections[j].kind == "convolutional")
        out[i] = Section(s.kind, {**s.options, "classes": str(classes)}, s.line)
        out[conv] = Section("convolutional", {**sections[conv].options,
                                              "filters": str(len(mask) * (5 + classes))}, sections[conv].line)
    return out


class _Opts:
    """Typed access to one section's options; errors name the cfg line."""

    def __init__(self, section: Section, source: str) -> None:
        self.s, self.source = section, source

    def integer(self, key: str, default: int | None = None) -> int:
        return int(self._number(key, default))

    def real(self, key: str, default: float | None = None) -> float:
        return self._number(key, default)

    def ints(self, key: str, default: str | None = None) -> list[int]:
        text = self.s.options.get(key, default)
        if text is None:
            self.fail(f"needs {key}=")
        try:
            return [int(v) for v in text.split(",") if v.strip()]
        except ValueError:
            self.fail(f"{key}={text!r}: expected a comma-separated list of integers")

    def floats(self, key: str) -> list[float]:
        try:
            return [float(v) for v in self.s.options.get(key, "").split(",") if v.strip()]
        except ValueError:
            self.fail(f"{key}: expected a comma-separated list of numbers")

    def word(self, key: str, default: str) -> str:
        return self.s.options.get(key, default).strip().lower()

    def _number(self, key: str, default: float | None) -> float:
        text = self.s.options.get(key)
        if text is None:
            if default is None:
                self.fail(f"needs {key}=")
            return float(default)
        try:
            return float(text)
        except ValueError:
            self.fail(f"{key}={text!r}: expected a number")

    def fail(self, what: str) -> NoReturn:
        raise InputError(f"{self.source}:{self.s.line}: [{self.s.kind}] {what}")


ACTIVATIONS: dict[str, Callable[[], nn.Module]] = {
    "linear": nn.Identity,
    "leaky": lambda: nn.LeakyReLU(0.1),
    "relu": nn.ReLU,
    "logistic": nn.Sigmoid,
    "mish": nn.Mish,
    "swish": nn.SiLU,
}


class ConvLayer(nn.Module):
    """Darknet convolutional: conv (bias only without batch norm) -> BN -> activation."""

    def __init__(self, c_in: int, o: _Opts) -> None:
        super().__init__()
        filters, size, stride = o.integer("filters"), o.integer("size", 1), o.integer("stride", 1)
        groups = o.integer("groups", 1)
        padding = size // 2 if o.integer("pad", 0) else o.integer("padding", 0)
        self.batch_normalize = bool(o.integer("batch_normalize", 0))
        if c_in % groups or filters % groups:
            o.fail(f"groups={groups} does not divide the {c_in} input channels and {filters} filters")
        activation = o.word("activation", "logistic")
        if activation not in ACTIVATIONS:
            o.fail(f"activation={activation} not supported ({', '.join(ACTIVATIONS)})")
        self.conv = nn.Conv2d(c_in, filters, size, stride, padding, groups=groups, bias=not self.batch_normalize)
        self.bn = nn.BatchNorm2d(filters, eps=BN_EPS) if self.batch_normalize else None
        self.act = ACTIVATIONS[activation]()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv(x)
        return self.act(self.bn(x) if self.bn is not None else x)

    def fold_batchnorm(self) -> None:
        """Inference only: the batch norm folded into the convolution (one op less per layer, same output)."""
        if self.bn is not None:
            fold.fold_batchnorm(self.conv, self.bn)
            self.bn = None


def _running_stats(bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch norm's running mean and variance (Darknet's rolling statistics; always tracked here)."""
    if bn.running_mean is None or bn.running_var is None:
        raise ValueError("batch norm without running statistics")
    return bn.running_mean, bn.running_var


class MaxPool(nn.Module):
    """Darknet maxpool: output (w + padding - size) / stride + 1, input offset -padding/2."""

    def __init__(self, size: int, stride: int, padding: int) -> None:
        super().__init__()
        self.size, self.stride = size, stride
        self.pad = (padding // 2, padding - padding // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lo, hi = self.pad
        x = F.pad(x, (lo, hi, lo, hi), value=float("-inf"))
        return F.max_pool2d(x, self.size, self.stride)


@dataclass
class Layer:
    kind: str
    module: nn.Module | None
    channels: int  # output channels
    stride: int  # output stride relative to the network input
    inputs: tuple[int, ...]  # absolute indices of the layers it reads (the previous one by default)
    extra: dict[str, Any] = field(default_factory=dict)


class DarknetNet(nn.Module):
    """The layers of a Darknet cfg as PyTorch modules, evaluated in order."""

    def __init__(self, sections: list[Section], in_channels: int | None = None, source: str = "<cfg>",
                 keep: range | None = None) -> None:
        """``keep``: the layer indices that get modules (others are bookkeeping only, no parameters)."""
        super().__init__()
        net = _Opts(sections[0], source)
        self.source = source
        self.in_channels = in_channels or net.integer("channels", 3)
        self.input_size = (net.integer("width", 416), net.integer("height", 416))
        self.layers: list[Layer] = []
        self.blocks = nn.ModuleList()
        for index, section in enumerate(sections[1:]):
            layer = self._build(section, _Opts(section, source))
            if keep is not None and index not in keep:
                layer.module = None
            self.layers.append(layer)
            self.blocks.append(layer.module or nn.Identity())
        self.yolo_indices = [i for i, layer in enumerate(self.layers) if layer.kind == "yolo"]

    def _previous(self) -> tuple[int, int, int]:
        if not self.layers:
            return -1, self.in_channels, 1
        last = self.layers[-1]
        return len(self.layers) - 1, last.channels, last.stride

    def _absolute(self, ref: int, o: _Opts) -> int:
        index = len(self.layers) + ref if ref < 0 else ref
        if not 0 <= index < len(self.layers):
            o.fail(f"refers to layer {ref}, which is not an earlier layer")
        return index

    def _build(self, section: Section, o: _Opts) -> Layer:
        prev, c, stride = self._previous()
        kind = section.kind
        if kind == "convolutional":
            module = ConvLayer(c, o)
            return Layer(kind, module, module.conv.out_channels, stride * module.conv.stride[0], (prev,))
        if kind == "shortcut":
            src = self._absolute(o.ints("from")[0], o)
            if self.layers[src].channels != c or self.layers[src].stride != stride:
                o.fail(f"adds layer {src} ({self.layers[src].channels} channels) to {c} channels")
            activation = o.word("activation", "linear")
            if activation not in ACTIVATIONS or o.word("weights_type", "none") != "none":
                o.fail("only a weightless shortcut with a plain activation is supported")
            return Layer(kind, ACTIVATIONS[activation](), c, stride, (prev, src))
        if kind == "route":
            srcs = tuple(self._absolute(r, o) for r in o.ints("layers"))
            groups, group_id = o.integer("groups", 1), o.integer("group_id", 0)
            strides = {self.layers[i].stride for i in srcs}
            if len(strides) != 1:
                o.fail("concatenates layers of different strides")
            channels = sum(self.layers[i].channels // groups for i in srcs)
            return Layer(kind, None, channels, strides.pop(), srcs, {"groups": groups, "group_id": group_id})
        if kind == "upsample":
            factor = o.integer("stride", 2)
            return Layer(kind, nn.Upsample(scale_factor=factor, mode="nearest"), c, stride // factor, (prev,))
        if kind == "maxpool":
            size = o.integer("size", 2)
            step = o.integer("stride", 1)
            pool = MaxPool(size, step, o.integer("padding", size - 1))
            return Layer(kind, pool, c, stride * step, (prev,))
        if kind == "dropout":
            return Layer(kind, None, c, stride, (prev,))
        return self._yolo(o, prev, c, stride)

    def _yolo(self, o: _Opts, prev: int, c: int, stride: int) -> Layer:
        values = o.floats("anchors")
        pairs = [(values[i], values[i + 1]) for i in range(0, len(values) - 1, 2)]
        mask = o.ints("mask", ",".join(str(i) for i in range(len(pairs))))
        classes = o.integer("classes", 20)
        if any(not 0 <= m < len(pairs) for m in mask):
            o.fail(f"mask {mask} refers to anchors beyond the {len(pairs)} given")
        if c != len(mask) * (5 + classes):
            o.fail(f"expects {len(mask)} x (5 + {classes}) = {len(mask) * (5 + classes)} input channels, got {c}")
        spec = YoloSpec(tuple(pairs[m] for m in mask), classes, o.real("scale_x_y", 1.0))
        return Layer("yolo", None, c, stride, (prev,), {"yolo": spec})

    @property
    def yolo_specs(self) -> list[YoloSpec]:
        return [self.layers[i].extra["yolo"] for i in self.yolo_indices]

    def run(self, x: torch.Tensor | None, start: int, stop: int, store: dict[int, torch.Tensor]) -> None:
        """Evaluate layers ``start..stop-1``; ``x`` feeds layer ``start`` when it reads the net input.

        Outputs go into ``store`` by layer index (earlier outputs must already be there).
        """
        def fetch(j: int) -> torch.Tensor:
            if j >= 0:
                return store[j]
            if x is None:
                raise ValueError(f"layer {start} onwards read the network input, but none was given")
            return x

        for i in range(start, stop):
            layer, block = self.layers[i], self.blocks[i]
            inputs = [fetch(j) for j in layer.inputs]
            if layer.kind == "shortcut":
                store[i] = block(inputs[0] + inputs[1])
            elif layer.kind == "route":
                g, gid = layer.extra["groups"], layer.extra["group_id"]
                parts = [t.chunk(g, 1)[gid] if g > 1 else t for t in inputs]
                store[i] = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
            elif layer.kind in ("dropout", "yolo"):
                store[i] = inputs[0]
            else:
                store[i] = block(inputs[0])

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Raw outputs (B, A x (5 + nc), h, w) of the convolutions feeding each [yolo] layer."""
        store: dict[int, torch.Tensor] = {}
        self.run(x, 0, len(self.layers), store)
        return [store[i] for i in self.yolo_indices]

    def conv_layers(self) -> list[ConvLayer]:
        return [layer.module for layer in self.layers if isinstance(layer.module, ConvLayer)]

    def head_split(self) -> tuple[int, tuple[int, ...]]:
        """Where the backbone ends: after the last [shortcut] before the first [yolo].

        Returns that index and the backbone layers the head reads (the fusion taps).
        """
        first_yolo = self.yolo_indices[0] if self.yolo_indices else len(self.layers)
        shortcuts = [i for i in range(first_yolo) if self.layers[i].kind == "shortcut"]
        if not shortcuts:
            raise InputError(f"{self.source}: no [shortcut] before the first [yolo]: cannot tell backbone from head")
        split = shortcuts[-1] + 1
        taps = {j for layer in self.layers[split:] for j in layer.inputs if 0 <= j < split}
        return split, tuple(sorted(taps))


def load_weights(net: DarknetNet, path: Path) -> dict[str, int]:
    """Fill ``net`` from a Darknet .weights file; returns the header fields."""
    data = Path(path).read_bytes()
    if len(data) < 16:
        raise InputError(f"{path}: {len(data)} bytes is too short for a Darknet weights header")
    major, minor, revision = (int(v) for v in np.frombuffer(data, "<i4", 3))
    wide = major * 10 + minor >= 2 and major < 1000 and minor < 1000
    seen = int(np.frombuffer(data, "<u8" if wide else "<i4", 1, 12)[0])
    offset = 20 if wide else 16
    if (len(data) - offset) % 4:
        raise InputError(f"{path}: {len(data) - offset} bytes after the header is not a whole number of float32")
    values = np.frombuffer(data, "<f4", offset=offset)
    cursor = 0
    for index, conv in ((i, layer.module) for i, layer in enumerate(net.layers) if isinstance(layer.module, ConvLayer)):
        cursor = _load_conv(conv, values, cursor, path, index, offset)
    if cursor != len(values):
        raise InputError(f"{path}: {4 * (len(values) - cursor)} bytes left over at byte {offset + 4 * cursor} "
                         "after the last convolutional layer (weights for another cfg?)")
    return {"major": major, "minor": minor, "revision": revision, "seen": seen}


def _load_conv(conv: ConvLayer, values: np.ndarray, cursor: int, path: Path, index: int, offset: int) -> int:
    n = conv.conv.out_channels
    if conv.bn is not None:
        mean, variance = _running_stats(conv.bn)
        parts = [("bias", conv.bn.bias), ("scale", conv.bn.weight), ("mean", mean), ("variance", variance)]
    elif conv.conv.bias is not None:
        parts = [("bias", conv.conv.bias)]
    else:
        raise ValueError(f"layer {index}: a convolution without batch norm has a bias")
    parts.append(("kernel", conv.conv.weight))
    with torch.no_grad():
        for what, target in parts:
            count = target.numel()
            if cursor + count > len(values):
                raise InputError(f"{path}: ends at byte {offset + 4 * len(values)} while reading the {what} "
                                 f"of layer {index} (convolutional, {n} filters): the file is shorter than the cfg")
            target.copy_(torch.from_numpy(values[cursor:cursor + count].copy()).view_as(target))
            cursor += count
    return cursor


def load(cfg_path: Path, weights_path: Path | None = None, in_channels: int | None = None) -> DarknetNet:
    """Parse ``cfg_path`` and, when given, load ``weights_path``; the net is in eval mode."""
    cfg_path = Path(cfg_path)
    try:
        text = cfg_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{cfg_path}: cannot read the Darknet cfg ({err})") from err
    net = DarknetNet(parse_cfg(text, str(cfg_path)), in_channels, str(cfg_path))
    if weights_path is not None:
        load_weights(net, Path(weights_path))
    return net.eval()


def decode_yolo(raw: torch.Tensor, spec: YoloSpec, input_hw: tuple[int, ...]) -> torch.Tensor:
    """Raw (B, A(5+nc), h, w) -> (B, h*w*A, 5 + nc): cx, cy, w, h in input pixels, objectness, class probs.

    Darknet's yolo layer (scale_x_y, new_coords=0): x = (cell + (sigmoid(tx) - 0.5) s + 0.5) * stride,
    w = exp(tw) * anchor_w. Rows run over cells (row-major) then anchors, as OpenCV emits them.
    """
    b, _, h, w = raw.shape
    a = len(spec.anchors)
    t = raw.view(b, a, 5 + spec.classes, h, w).permute(0, 3, 4, 1, 2)  # (B, h, w, A, 5+nc)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=raw.dtype, device=raw.device),
                            torch.arange(w, dtype=raw.dtype, device=raw.device), indexing="ij")
    s = spec.scale_x_y
    stride_y, stride_x = input_hw[0] / h, input_hw[1] / w
    cx = (xs[..., None] + (t[..., 0].sigmoid() - 0.5) * s + 0.5) * stride_x
    cy = (ys[..., None] + (t[..., 1].sigmoid() - 0.5) * s + 0.5) * stride_y
    anchors = torch.tensor(spec.anchors, dtype=raw.dtype, device=raw.device)  # (A, 2)
    bw = t[..., 2].exp() * anchors[:, 0]
    bh = t[..., 3].exp() * anchors[:, 1]
    out = torch.cat([torch.stack([cx, cy, bw, bh], -1), t[..., 4:].sigmoid()], -1)
    return out.reshape(b, h * w * a, 5 + spec.classes)
