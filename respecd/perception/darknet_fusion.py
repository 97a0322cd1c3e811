"""The fusion detector on a pretrained Darknet backbone (``ModelSpec.backbone = "darknet:NAME"``).

The paper's shape with real-photo features: backbone 1 (RGB) and backbone 2 (thermal and
the other aligned planes, plus one presence plane per modality) are both the backbone of
the Darknet cfg ``NAME`` (layers up to the last residual block); at every feature map the
head reads (for Yolo-Fastest: stride 16 and 32) the two are concatenated and mixed by a
1x1 convolution (mid-level fusion), then one Darknet yolo head detects:

    fused = conv1x1([rgb, g * (aux - f0)]),   g = 1 if any aux modality is present, else 0

``f0`` is backbone 1's feature map of a black image of the same size (computed once per
input size while backbone 1 is frozen). ``from_darknet`` starts every part from a Darknet
``.weights`` file: RGB backbone and head as trained, backbone 2 with the same kernels
applied to thermal replicated to three channels (its first kernel summed over R, G, B;
radar, depth and presence kernels zero), and each fusion convolution ``[I, I]`` without
bias. So a sensor that is off adds nothing: with the aux sensors off the net is exactly the
pretrained RGB detector; with RGB off (a black image, ``rgb = f0``) it is exactly backbone
2 on the head; with both on, their evidence adds in the head's feature space.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import torch
from torch import nn

from respecd.errors import InputError
from respecd.perception import darknet
from respecd.perception.config import ModelSpec


def cfg_text(backbone: str) -> tuple[str, str]:
    """'darknet:NAME' -> (the packaged cfg's text, its name)."""
    name = backbone.split(":", 1)[1]
    resource = resources.files("respecd.perception") / "cfg" / f"{name}.cfg"
    if not resource.is_file():
        shipped = sorted(p.name[:-4] for p in (resources.files("respecd.perception") / "cfg").iterdir()
                         if p.name.endswith(".cfg"))
        raise InputError(f"backbone {backbone!r}: no packaged Darknet cfg {name}.cfg (shipped: {', '.join(shipped)})")
    return resource.read_text(encoding="utf-8"), f"{name}.cfg"


class DarknetFusionNet(nn.Module):
    """RGB Darknet backbone + aux Darknet backbone -> concat + 1x1 at each head input -> Darknet head."""

    def __init__(self, spec: ModelSpec) -> None:
        super().__init__()
        self.spec = spec
        text, source = cfg_text(spec.backbone)
        sections = darknet.with_classes(darknet.parse_cfg(text, source), len(spec.classes))
        layout = darknet.DarknetNet(sections, 3, source, keep=range(0))
        self.split, self.taps = layout.head_split()
        n = len(layout.layers)
        n_aux = len(spec.aux_modalities)
        self.rgb = darknet.DarknetNet(sections, 3, source, keep=range(self.split))
        self.aux = darknet.DarknetNet(sections, 2 * n_aux, source, keep=range(self.split))
        self.head = darknet.DarknetNet(sections, 3, source, keep=range(self.split, n))
        widths = [layout.layers[t].channels for t in self.taps]
        self.fuse = nn.ModuleList(nn.Conv2d(2 * c, c, 1, bias=False) for c in widths)
        self._black: dict[tuple[int, int, str], dict[int, torch.Tensor]] = {}  # f0 per input size
        self.yolo_specs = self.head.yolo_specs

    def forward(self, x: torch.Tensor, presence: torch.Tensor | None = None) -> list[torch.Tensor]:
        """``x``: (B, 3 + A, H, W) in 0..1, H and W multiples of 32; ``presence``: (B, A) 0/1.

        Returns the raw yolo maps (B, anchors x (5 + nc), H/s, W/s), one per [yolo] layer.
        """
        b, _, h, w = x.shape
        if presence is None:
            presence = x.new_ones(b, x.shape[1] - 3)
        planes = presence.to(x.dtype)[:, :, None, None].expand(b, presence.shape[1], h, w)
        rgb: dict[int, torch.Tensor] = {}
        aux: dict[int, torch.Tensor] = {}
        black = self.black_features(h, w, x)
        if bool((x[:, :3] == 0).all()) and not self.rgb.training:  # RGB off in the whole batch: f0, no pass
            rgb = {t: f.expand(b, -1, -1, -1) for t, f in black.items()}
        else:
            self.rgb.run(x[:, :3], 0, self.split, rgb)
        self.aux.run(torch.cat([x[:, 3:], planes], 1), 0, self.split, aux)
        gate = (presence.amax(1) > 0).to(x.dtype)[:, None, None, None] if presence.shape[1] else x.new_zeros(b, 1, 1, 1)
        store = {t: fuse(torch.cat([rgb[t], gate * (aux[t] - black[t])], 1))
                 for t, fuse in zip(self.taps, self.fuse, strict=True)}
        self.head.run(None, self.split, len(self.head.layers), store)
        return [store[i] for i in self.head.yolo_indices]

    def black_features(self, h: int, w: int, like: torch.Tensor) -> dict[int, torch.Tensor]:
        """Backbone 1's tap features of a black h x w image: cached while backbone 1 cannot change."""
        frozen = not self.rgb.training and not any(p.requires_grad for p in self.rgb.parameters())
        key = (h, w, str(like.device))
        if frozen and key in self._black:
            return self._black[key]
        store: dict[int, torch.Tensor] = {}
        with torch.no_grad():
            self.rgb.run(like.new_zeros(1, 3, h, w), 0, self.split, store)
        black = {t: store[t] for t in self.taps}
        if frozen:
            self._black[key] = black
        return black

    def fold_batchnorm(self) -> None:
        """For inference (the detector does it): batch norms folded into their convolutions, ~25 % less CPU
        time per forward here; outputs equal to float precision. The net cannot be trained or saved after."""
        for module in self.modules():
            if isinstance(module, darknet.ConvLayer):
                module.fold_batchnorm()
        self._black.clear()

    def train(self, mode: bool = True) -> DarknetFusionNet:
        self._black.clear()  # backbone 1 may change
        return super().train(mode)

    def decode(self, raw: list[torch.Tensor], input_hw: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw maps -> boxes (B, N, 4) x1y1x2y2 in input pixels and scores objectness x class (B, N, nc)."""
        rows = torch.cat([darknet.decode_yolo(r, s, input_hw) for r, s in zip(raw, self.yolo_specs, strict=True)], 1)
        centre, size = rows[..., :2], rows[..., 2:4]
        boxes = torch.cat([centre - size / 2, centre + size / 2], -1)
        return boxes, rows[..., 4:5] * rows[..., 5:]


def from_darknet(spec: ModelSpec, weights: Path) -> DarknetFusionNet:
    """A DarknetFusionNet started from a Darknet .weights file for the spec's cfg (see module doc).

    A model with other classes (COCO's 80) keeps the spec's classes, found by name in the
    ``.names`` file beside the weights (``coco.names``, ``NAME.names``).
    """
    model = DarknetFusionNet(spec)
    text, source = cfg_text(spec.backbone)
    ref = darknet.DarknetNet(darknet.parse_cfg(text, source), 3, source)
    darknet.load_weights(ref, weights)
    pretrained = ref.state_dict()
    if ref.yolo_specs[0].classes != len(spec.classes):
        pretrained = _keep_classes(ref, pretrained, _class_ids(Path(weights), spec.classes, ref.yolo_specs[0].classes))
    for part in (model.rgb, model.head):
        part.load_state_dict({k: v for k, v in pretrained.items() if k in part.state_dict()}, strict=True)
    _init_aux(model, pretrained)
    with torch.no_grad():
        for fuse in model.fuse:
            assert isinstance(fuse, nn.Conv2d)
            eye = torch.eye(fuse.out_channels)[:, :, None, None]
            fuse.weight.copy_(torch.cat([eye, eye], 1))
    return model


def _class_ids(weights: Path, classes: tuple[str, ...], total: int) -> list[int]:
    """Indices of ``classes`` in the model's names file (person is COCO's 'person', the body model's 'body')."""
    aliases = {"person": ("person", "body", "pedestrian")}
    for names_file in (weights.with_suffix(".names"), weights.parent / "coco.names"):
        if names_file.is_file():
            names = [n.strip().lower() for n in names_file.read_text(encoding="utf-8").splitlines() if n.strip()]
            if len(names) == total:
                found = [next((names.index(a) for a in aliases.get(c, (c,)) if a in names), None) for c in classes]
                if None not in found:
                    return found  # type: ignore[return-value]
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
    """Backbone 2 = backbone 1 on thermal replicated to R, G, B; other planes start with zero kernels."""
    own = model.aux.state_dict()
    first = next(k for k in own if k.endswith("conv.weight"))
    state = {k: v for k, v in pretrained.items() if k in own and k != first}
    kernel = torch.zeros_like(own[first])  # (c_out, 2A, k, k)
    aux = model.spec.aux_modalities
    if "thermal" in aux:
        kernel[:, aux.index("thermal")] = pretrained[first].sum(1)
    state[first] = kernel
    model.aux.load_state_dict(state, strict=True)

