"""Fine-tuning support for ``respecd train``: the starting model, frozen parts, validation, the curve.

* ``--init`` names a respecd checkpoint (``builtin:NAME`` or a path) or a Darknet ``.weights``
  file (its cfg must be packaged, see ``darknet_fusion.cfg_text``): training starts there.
  ``RGB.weights,AUX.weights`` takes backbone 2 from another Darknet model (``aux_backbone``).
* ``--reinit aux,...`` gives those parts fresh weights first (module paths as ``--freeze``).
* ``--freeze rgb,head,...`` keeps those parts of the net as they are (no gradient, batch-norm
  statistics untouched), e.g. the RGB backbone and the head of a pretrained detector while
  backbone 2 learns thermal. A part is a module path, ``*`` matching one name (``fuse.*.rgb``).
* After every epoch the EMA weights are scored on the validation split (mAP@0.5); the best
  epoch's weights are the result, and training stops after ``patience`` epochs without a
  better score (``respecd train`` draws loss and validation mAP per epoch).
"""

from __future__ import annotations

from fnmatch import fnmatchcase
from pathlib import Path

import numpy as np
import torch
from torch import nn

from respecd.errors import InputError
from respecd.perception import checkpoint
from respecd.perception.config import ModelSpec

VAL_SCORE_THRESHOLD = 0.01  # the usual mAP protocol: rank everything the net proposes


def initial_model(init: str | None, spec: ModelSpec) -> checkpoint.Net:
    """The net training starts from: ``spec`` from scratch, or ``init``'s weights (its own spec)."""
    if not init:
        return checkpoint.build(spec)
    if init.endswith(".weights"):
        from respecd.perception.darknet_fusion import from_darknet

        paths = [Path(p) for p in init.split(",")]
        for path in paths:
            if not path.is_file() or path.suffix != ".weights":
                raise InputError(f"--init {init}: no such Darknet weights file {path}")
        if len(paths) > 2:
            raise InputError(f"--init {init}: at most two Darknet weights files (RGB and head, backbone 2)")
        update = {"backbone": f"darknet:{paths[0].stem}"}
        if len(paths) == 2:
            update["aux_backbone"] = f"darknet:{paths[1].stem}"
        return from_darknet(spec.model_copy(update=update), paths[0], paths[-1] if len(paths) == 2 else None)
    model, _ = checkpoint.load(init)
    return model


def frozen_modules(model: nn.Module, parts: tuple[str, ...]) -> list[nn.Module]:
    """The modules ``parts`` names (module paths, ``*`` for one name); an unknown part is an InputError."""
    named = dict(model.named_modules())
    found: list[nn.Module] = []
    for pattern in parts:
        hits = [m for n, m in named.items() if n and fnmatchcase(n, pattern) and n.count(".") == pattern.count(".")]
        if not hits:
            children = ", ".join(n for n, _ in model.named_children())
            raise InputError(f"--freeze {pattern}: the net has no part {pattern!r} (it has {children})")
        found += hits
    return found


def freeze(model: nn.Module, parts: tuple[str, ...]) -> None:
    """No gradients for the named parts; ``keep_frozen_eval`` keeps their BN still."""
    for module in frozen_modules(model, parts):
        for p in module.parameters():
            p.requires_grad_(False)
    setattr(model, "_frozen_parts", tuple(parts))  # noqa: B010 (read back by keep_frozen_eval)


def reinit(model: checkpoint.Net, parts: tuple[str, ...], seed: int = 0) -> None:
    """Fresh weights for the named parts, as a new net of the same spec (seeded) has them: a new thermal
    branch under a pretrained RGB detector, or a thermal path damaged on purpose (``respecd adapt``'s test)."""
    if not parts:
        return
    torch.manual_seed(seed)
    fresh = checkpoint.build(model.spec)
    for module, new in zip(frozen_modules(model, parts), frozen_modules(fresh, parts), strict=True):
        module.load_state_dict(new.state_dict())


def keep_frozen_eval(model: nn.Module) -> None:
    """After ``model.train()``: frozen parts back to eval mode (running statistics stay pretrained)."""
    for module in frozen_modules(model, getattr(model, "_frozen_parts", ())):
        module.eval()


@torch.no_grad()
def validation_map(model: checkpoint.Net, samples, iou_threshold: float = 0.5, max_det: int = 100) -> float:
    """mAP@0.5 of ``model`` (eval mode) on a list/source of Samples, all modalities as given."""
    from respecd.lab.detector.evaluate import sample_input
    from respecd.lab.detector.metrics import ImageResult, mean_ap
    from respecd.perception.boxes import postprocess

    was_training = model.training
    model.eval()
    aux = model.spec.aux_modalities
    images = []
    for i in range(len(samples)):
        s = samples[i]
        x, presence = sample_input(s, aux, ())
        hw = tuple(x.shape[2:])
        boxes, scores = model.decode(model(x, presence), hw)
        b, sc, _, _ = postprocess(boxes, scores, hw, VAL_SCORE_THRESHOLD, iou_threshold, max_det)[0]
        images.append(ImageResult(b.numpy(), sc.numpy(), s.boxes, s.ignore))
    model.train(was_training)
    return float(mean_ap(images)["map50"])


def finite(value: float | None) -> float | None:
    return None if value is None or not np.isfinite(value) else round(float(value), 4)
