"""The fusion detector on pretrained Darknet backbones (``ModelSpec.backbone = "darknet:NAME"``).

The paper's shape with real-photo features: backbone 1 (RGB) is the backbone of the Darknet
cfg ``NAME`` (layers up to its last residual block); backbone 2 (thermal and the other aligned
planes, plus one presence plane per modality) is the backbone of the same cfg or of another
one (``ModelSpec.aux_backbone``, e.g. a wider model on thermal), optionally run on the aux
planes at a lower resolution (``ModelSpec.aux_scale``; its features are resized back). At
every feature map the head reads (Yolo-Fastest: strides 16 and 32) the two are mixed by a
1x1 convolution over their concatenation (mid-level fusion), then one Darknet yolo head
detects:

    fused = W_rgb * rgb + W_aux * g * (aux - a0),   g = 1 if any aux modality is present, else 0

With ``ModelSpec.rgb_aware_fusion`` the evidence has one map per case, ``W_aux`` while the RGB image is
black (the aux sensors alone) and ``W_both`` while it is not, both started where ``W_aux`` starts:
thermal alone and thermal beside an RGB camera that also sees are then learned (or kept) apart, and
training one does not move the other (one ``W_aux`` trained to carry detection alone adds too much
where RGB already sees).

``a0`` is what the aux side gives for an input with nothing in it: backbone 1's features of
a black image when both backbones share a cfg (so a black thermal image adds exactly nothing
at import), else backbone 2's features of an all-zero input. It is computed once per input
size while that backbone is frozen. ``from_darknet`` starts every part from Darknet
``.weights`` files: RGB backbone and head as trained, backbone 2 with its pretrained kernels
applied to thermal replicated to three channels (its first kernel summed over R, G, B; radar,
depth and presence kernels zero), ``W_rgb = I`` and ``W_aux = I`` (same cfg) or ``0`` (another
cfg: its features are not the head's, the fusion learns the mapping). So a sensor that is
off adds nothing: with the aux sensors off the net is exactly the pretrained RGB detector;
same cfg and RGB off (a black image, ``rgb = f0``), it is exactly backbone 2 on the head.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from importlib import resources
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from respecd.errors import InputError
from respecd.perception import darknet
from respecd.perception.calibration import ScoreCalibration, calibrated
from respecd.perception.config import ModelSpec
from respecd.perception.parts import Call, Engine, Part, names

Taps = tuple[torch.Tensor, ...]  # one backbone's features at the head's inputs, in tap order


def cfg_text(backbone: str) -> tuple[str, str]:
    """'darknet:NAME' -> (the packaged cfg's text, its name)."""
    name = backbone.split(":", 1)[1]
    resource = resources.files("respecd.perception") / "cfg" / f"{name}.cfg"
    if not resource.is_file():
        shipped = sorted(p.name[:-4] for p in (resources.files("respecd.perception") / "cfg").iterdir()
                         if p.name.endswith(".cfg"))
        raise InputError(f"backbone {backbone!r}: no packaged Darknet cfg {name}.cfg (shipped: {', '.join(shipped)})")
    return resource.read_text(encoding="utf-8"), f"{name}.cfg"


class Fuse(nn.Module):
    """One fusion point: a 1x1 convolution over [rgb, aux], held as its two halves so that either can be
    trained alone (``--freeze fuse.*.rgb``); the sum of the halves is the convolution of the concatenation.
    With ``rgb_aware`` a third map ``both`` replaces the aux half where the RGB camera is on."""

    def __init__(self, c_rgb: int, c_aux: int, rgb_aware: bool = False) -> None:
        super().__init__()
        self.rgb = nn.Conv2d(c_rgb, c_rgb, 1, bias=False)
        self.aux = nn.Conv2d(c_aux, c_rgb, 1, bias=False)
        self.both = nn.Conv2d(c_aux, c_rgb, 1, bias=False) if rgb_aware else None

    def forward(self, rgb: torch.Tensor, aux: torch.Tensor, rgb_on: torch.Tensor | None = None) -> torch.Tensor:
        """``rgb_on``: (B, 1, 1, 1) 1 where the RGB image is not black (read only with ``rgb_aware``, needed then)."""
        if self.both is None:
            return self.rgb(rgb) + self.aux(aux)
        if rgb_on is None:
            raise ValueError("an rgb-aware fusion needs rgb_on (DarknetFusionNet.encode_rgb gives it)")
        return self.rgb(rgb) + (1 - rgb_on) * self.aux(aux) + rgb_on * self.both(aux)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        joint = state_dict.pop(prefix + "weight", None)  # checkpoints before the split: one (c, 2c) kernel
        if joint is not None:
            c = self.rgb.in_channels
            state_dict[prefix + "rgb.weight"], state_dict[prefix + "aux.weight"] = joint[:, :c], joint[:, c:]
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


class DarknetFusionNet(nn.Module):
    """RGB Darknet backbone + aux Darknet backbone -> 1x1 fusion at each head input -> Darknet head."""

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        self.spec = spec
        self.score_calibration: ScoreCalibration | None = None  # set by FusionDetector.load, never trained
        text, source = cfg_text(spec.backbone)
        sections = darknet.with_classes(darknet.parse_cfg(text, source), len(spec.classes))
        layout = darknet.DarknetNet(sections, 3, source, keep=range(0))
        self.split, self.taps = layout.head_split()
        self.same_backbone = spec.aux_backbone in (None, spec.backbone)
        aux_sections, aux_layout, aux_source = sections, layout, source
        if not self.same_backbone:
            aux_text, aux_source = cfg_text(str(spec.aux_backbone))
            aux_sections = darknet.parse_cfg(aux_text, aux_source)
            aux_layout = darknet.DarknetNet(aux_sections, 3, aux_source, keep=range(0))
        self.aux_split, self.aux_taps_at = aux_layout.head_split()
        if [layout.layers[t].stride for t in self.taps] != [aux_layout.layers[t].stride for t in self.aux_taps_at]:
            raise InputError(f"aux_backbone {spec.aux_backbone}: its feature strides differ from {spec.backbone}'s")
        n_aux = len(spec.aux_modalities)
        self.rgb = darknet.DarknetNet(sections, 3, source, keep=range(self.split))
        self.aux = darknet.DarknetNet(aux_sections, 2 * n_aux, aux_source, keep=range(self.aux_split))
        self.head = darknet.DarknetNet(sections, 3, source, keep=range(self.split, len(layout.layers)))
        self.fuse = nn.ModuleList(Fuse(layout.layers[t].channels, aux_layout.layers[a].channels, spec.rgb_aware_fusion)
                                  for t, a in zip(self.taps, self.aux_taps_at, strict=True))
        self._empty: dict[tuple[str, int, int, str], Taps] = {}  # f0 and a0 per input size
        self.engine: Engine | None = None  # set by FusionDetector.load for runtime onnxruntime / openvino
        self.yolo_specs = self.head.yolo_specs

    def forward(self, x: torch.Tensor, presence: torch.Tensor | None = None) -> list[torch.Tensor]:
        """``x``: (B, 3 + A, H, W) in 0..1, H and W multiples of 32; ``presence``: (B, A) 0/1.

        Returns the raw yolo maps (B, anchors x (5 + nc), H/s, W/s), one per [yolo] layer.
        """
        return self.fuse_taps(self.encode_rgb(x[:, :3]), self.encode_aux(x[:, 3:], presence))

    def encode_rgb(self, rgb: torch.Tensor) -> Taps:
        """(B, 3, H, W) -> backbone 1's features at the head's taps, a black image's (RGB off) from the cache;
        with ``rgb_aware_fusion`` one more tensor after them, (B, 1, 1, 1) 1 where the image is not black
        (``rgb_on``: the fusion reads it, and an exported fusion graph takes it as its input ``rgb_on``)."""
        b, _, h, w = rgb.shape
        on = (rgb.flatten(1).amax(1) > 0).to(rgb.dtype)[:, None, None, None]
        if not bool(on.any()) and not self.rgb.training:
            taps = tuple(f.expand(b, -1, -1, -1) for f in self.black_features(h, w, rgb))  # RGB off: no pass
        else:
            taps = self.rgb_taps(rgb)
        return (*taps, on) if self.spec.rgb_aware_fusion else taps

    def encode_aux(self, planes: torch.Tensor, presence: torch.Tensor | None = None) -> Taps:
        """(B, A, H, W) aux planes -> the evidence backbone 2 adds at each tap: its features less those of an
        empty input (``a0``), zero where every aux sensor is off; at backbone 2's resolution."""
        b, a, h, w = planes.shape
        if presence is None:
            presence = planes.new_ones(b, a)
        aux = self.aux_taps(self.aux_input(planes, presence))
        empty = self.empty_features(h, w, planes)
        gate = (presence.amax(1) > 0).to(planes.dtype)[:, None, None, None] if a else planes.new_zeros(b, 1, 1, 1)
        return tuple(gate * (f - f0) for f, f0 in zip(aux, empty, strict=True))

    def fuse_taps(self, rgb: Taps, evidence: Taps) -> list[torch.Tensor]:
        """Each tap's 1x1 fusion of backbone 1's features (``encode_rgb``: with ``rgb_on`` last when the fusion
        is rgb-aware) and the evidence (resized to them), then the head."""
        if self.engine is not None:
            return list(self.engine("fuse", *rgb, *evidence))
        store: dict[int, torch.Tensor] = {}
        features, rgb_on = (rgb[:-1], rgb[-1]) if self.spec.rgb_aware_fusion else (rgb, None)
        for t, r, e, fuse in zip(self.taps, features, evidence, self.fuse, strict=True):
            if e.shape[-2:] != r.shape[-2:]:
                e = F.interpolate(e, size=r.shape[-2:], mode="bilinear", align_corners=False)
            store[t] = fuse(r, e, rgb_on)
        self.head.run(None, self.split, len(self.head.layers), store)
        return [store[i] for i in self.head.yolo_indices]

    def rgb_taps(self, rgb: torch.Tensor) -> Taps:
        """Backbone 1 (a part: ``engine`` runs it when set)."""
        if self.engine is not None:
            return self.engine("rgb", rgb)
        store: dict[int, torch.Tensor] = {}
        self.rgb.run(rgb, 0, self.split, store)
        return tuple(store[t] for t in self.taps)

    def aux_taps(self, z: torch.Tensor) -> Taps:
        """Backbone 2 on its input (``aux_input``), at its taps (a part, like ``rgb_taps``)."""
        if self.engine is not None:
            return self.engine("aux", z)
        store: dict[int, torch.Tensor] = {}
        self.aux.run(z, 0, self.aux_split, store)
        return tuple(store[t] for t in self.aux_taps_at)

    def aux_input(self, planes: torch.Tensor, presence: torch.Tensor) -> torch.Tensor:
        """Backbone 2's input: the aux planes and one presence plane each, at ``aux_scale``."""
        b, _, h, w = planes.shape
        flags = presence.to(planes.dtype)[:, :, None, None].expand(b, presence.shape[1], h, w)
        z = torch.cat([planes, flags], 1)
        if self.spec.aux_scale != 1.0:
            z = F.interpolate(z, size=self.aux_size(h, w), mode="bilinear", align_corners=False, antialias=True)
        return z

    def aux_size(self, h: int, w: int) -> tuple[int, int]:
        """Backbone 2's input size for an h x w input."""
        s = self.spec.aux_scale
        return (h, w) if s == 1.0 else (max(1, round(h * s)), max(1, round(w * s)))

    def black_features(self, h: int, w: int, like: torch.Tensor) -> Taps:
        """Backbone 1's tap features of a black h x w image (``f0``), cached while backbone 1 cannot change."""
        return self._constant(("rgb", h, w, str(like.device)), self.rgb,
                              lambda: self.rgb_taps(like.new_zeros(1, 3, h, w)))

    def empty_features(self, h: int, w: int, like: torch.Tensor) -> Taps:
        """``a0`` at each aux tap for an h x w input (see module doc), at backbone 2's resolution."""
        if self.same_backbone:
            return self.black_features(*self.aux_size(h, w), like)

        def run() -> Taps:
            n = len(self.spec.aux_modalities)
            return self.aux_taps(self.aux_input(like.new_zeros(1, n, h, w), like.new_zeros(1, n)))
        return self._constant(("aux", h, w, str(like.device)), self.aux, run)

    def export_parts(self, x: torch.Tensor, presence: torch.Tensor) -> list[Part]:
        """The parts a runtime runs (``engine``), with example inputs from ``x`` (1, C, H, W): each backbone
        (backbone 2 on its prepared input) and fusion + head. The caches and the gate stay in Python."""
        with torch.no_grad():
            z = self.aux_input(x[:, 3:], presence)
            rgb, evidence = self.encode_rgb(x[:, :3]), self.encode_aux(x[:, 3:], presence)
        n, heads = len(self.taps), len(self.head.yolo_indices)
        fuse_in = (*names("rgb", n), *(("rgb_on",) if self.spec.rgb_aware_fusion else ()), *names("aux", n))
        cut = len(rgb)
        return [
            Part("rgb", Call(self, lambda m, r: m.rgb_taps(r)), (x[:, :3],), ("rgb",), names("rgb", n)),
            Part("aux", Call(self, lambda m, a: m.aux_taps(a)), (z,), ("aux",), names("aux", n)),
            Part("fuse", Call(self, lambda m, *f: m.fuse_taps(f[:cut], f[cut:])), (*rgb, *evidence), fuse_in,
                 names("yolo", heads)),
        ]

    def _constant(self, key: tuple[str, int, int, str], part: nn.Module, run: Callable[[], Taps]) -> Taps:
        """``run()`` without gradients in eval mode (a one-image batch has no statistics of its own); kept
        while ``part`` is frozen and in eval mode."""
        frozen = not part.training and not any(p.requires_grad for p in part.parameters())
        if frozen and key in self._empty:
            return self._empty[key]
        with torch.no_grad(), _eval_mode(part):
            value = run()
        if frozen:
            self._empty[key] = value
        return value

    def fold_batchnorm(self) -> None:
        """For inference (the detector does it): batch norms folded into their convolutions, one pass over
        each feature map less; outputs equal to float precision. The net cannot be trained or saved after."""
        for module in self.modules():
            if isinstance(module, darknet.ConvLayer):
                module.fold_batchnorm()
        self._empty.clear()

    def train(self, mode: bool = True) -> DarknetFusionNet:
        self._empty.clear()  # the backbones may change
        return super().train(mode)

    def decode(self, raw: list[torch.Tensor], input_hw: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw maps -> boxes (B, N, 4) x1y1x2y2 in input pixels and scores objectness x class (B, N, nc)."""
        rows = torch.cat([darknet.decode_yolo(r, s, input_hw) for r, s in zip(raw, self.yolo_specs, strict=True)], 1)
        centre, size = rows[..., :2], rows[..., 2:4]
        boxes = torch.cat([centre - size / 2, centre + size / 2], -1)
        return boxes, calibrated(self.score_calibration, rows[..., 4:5] * rows[..., 5:], input_hw)


@contextlib.contextmanager
def _eval_mode(module: nn.Module) -> Iterator[None]:
    """``module`` and all its parts in eval mode for the block; each part's own mode restored after."""
    modes = [(m, m.training) for m in module.modules()]
    module.eval()
    try:
        yield
    finally:
        for m, training in modes:
            m.training = training


def from_darknet(spec: ModelSpec, weights: Path, aux_weights: Path | None = None) -> DarknetFusionNet:
    """A DarknetFusionNet started from Darknet .weights files for the spec's cfgs (see module doc).

    ``weights`` fill backbone 1 and the head; ``aux_weights`` backbone 2 when the spec names
    another ``aux_backbone`` (required then). A model with other classes (COCO's 80) keeps the
    spec's classes, found by name in the ``.names`` file beside the weights (``coco.names``,
    ``NAME.names``).
    """
    model = DarknetFusionNet(spec)
    pretrained = _pretrained_state(spec.backbone, Path(weights), spec.classes)
    for part in (model.rgb, model.head):
        part.load_state_dict({k: v for k, v in pretrained.items() if k in part.state_dict()}, strict=True)
    if not model.same_backbone:
        if aux_weights is None:
            raise InputError(f"aux_backbone {spec.aux_backbone}: needs its own .weights file")
        pretrained = _pretrained_state(str(spec.aux_backbone), Path(aux_weights), None)
    _init_aux(model, pretrained)
    with torch.no_grad():
        for fuse in model.fuse:
            assert isinstance(fuse, Fuse)
            fuse.rgb.weight.copy_(torch.eye(fuse.rgb.out_channels)[:, :, None, None])
            if model.same_backbone:
                fuse.aux.weight.copy_(torch.eye(fuse.aux.out_channels)[:, :, None, None])
            else:
                fuse.aux.weight.zero_()
            if fuse.both is not None:
                fuse.both.weight.copy_(fuse.aux.weight)
    return model


def _pretrained_state(backbone: str, weights: Path, classes: tuple[str, ...] | None) -> dict[str, torch.Tensor]:
    """The cfg's net filled from ``weights``; with ``classes``, only their rows of the yolo convolutions."""
    text, source = cfg_text(backbone)
    ref = darknet.DarknetNet(darknet.parse_cfg(text, source), 3, source)
    darknet.load_weights(ref, weights)
    state = ref.state_dict()
    if classes is not None and ref.yolo_specs[0].classes != len(classes):
        state = _keep_classes(ref, state, _class_ids(weights, classes, ref.yolo_specs[0].classes))
    return state


def _class_ids(weights: Path, classes: tuple[str, ...], total: int) -> list[int]:
    """Indices of ``classes`` in the model's names file (person is COCO's 'person', the body model's 'body')."""
    aliases = {"person": ("person", "body", "pedestrian")}
    for names_file in (weights.with_suffix(".names"), weights.parent / "coco.names"):
        if names_file.is_file():
            names = [n.strip().lower() for n in names_file.read_text(encoding="utf-8").splitlines() if n.strip()]
            if len(names) == total:
                found = [next((names.index(a) for a in aliases.get(c, (c,)) if a in names), None) for c in classes]
                if all(i is not None for i in found):
                    return [int(i) for i in found if i is not None]
    raise InputError(f"{weights}: its {total} classes need a names file beside it naming {', '.join(classes)}")


def _keep_classes(ref: darknet.DarknetNet, state: dict[str, torch.Tensor], ids: list[int]) -> dict[str, torch.Tensor]:
    """Only the kept classes' rows of each convolution feeding a [yolo] layer."""
    state = dict(state)
    for index in ref.yolo_indices:
        conv = max(j for j in range(index) if isinstance(ref.layers[j].module, darknet.ConvLayer))
        spec = ref.layers[index].extra["yolo"]
        per = 5 + spec.classes
        rows = [a * per + k for a in range(len(spec.anchors)) for k in (0, 1, 2, 3, 4, *(5 + i for i in ids))]
        for name in ("conv.weight", "conv.bias"):
            key = f"blocks.{conv}.{name}"
            if key in state:
                state[key] = state[key][rows]
    return state


def _init_aux(model: DarknetFusionNet, pretrained: dict[str, torch.Tensor]) -> None:
    """Backbone 2 = its pretrained backbone on thermal replicated to R, G, B; other planes start with zero kernels."""
    own = model.aux.state_dict()
    first = next(k for k in own if k.endswith("conv.weight"))
    state = {k: v for k, v in pretrained.items() if k in own and k != first}
    kernel = torch.zeros_like(own[first])  # (c_out, 2A, k, k)
    aux = model.spec.aux_modalities
    if "thermal" in aux:
        kernel[:, aux.index("thermal")] = pretrained[first].sum(1)
    state[first] = kernel
    model.aux.load_state_dict(state, strict=True)
