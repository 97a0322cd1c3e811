"""Fine-tuning support for ``respecd train``: the starting model, frozen parts, validation, the curve.

* ``--init`` names a respecd checkpoint (``builtin:NAME`` or a path) or a Darknet ``.weights``
  file (its cfg must be packaged, see ``darknet_fusion.cfg_text``): training starts there.
* ``--freeze rgb,head,...`` keeps those top-level parts of the net as they are (no gradient,
  batch-norm statistics untouched), e.g. the RGB backbone and the head of a pretrained
  detector while backbone 2 learns thermal.
* After every epoch the EMA weights are scored on the validation split (mAP@0.5); the best
  epoch's weights are the result, and training stops after ``patience`` epochs without a
  better score (``respecd train`` draws loss and validation mAP per epoch).
"""

from __future__ import annotations

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

        path = Path(init)
        if not path.is_file():
            raise InputError(f"--init {init}: no such Darknet weights file")
        darknet_spec = spec.model_copy(update={"backbone": f"darknet:{path.stem}"})
        return from_darknet(darknet_spec, path)
    model, _ = checkpoint.load(init)
    return model


def freeze(model: nn.Module, parts: tuple[str, ...]) -> None:
    """No gradients for the named top-level children; ``keep_frozen_eval`` keeps their BN still."""
    children = dict(model.named_children())
    for name in parts:
        if name not in children:
            raise InputError(f"--freeze {name}: the net has no part {name!r} (it has {', '.join(children)})")
        for p in children[name].parameters():
            p.requires_grad_(False)
    setattr(model, "_frozen_parts", tuple(parts))  # noqa: B010 (read back by keep_frozen_eval)


def keep_frozen_eval(model: nn.Module) -> None:
    """After ``model.train()``: frozen parts back to eval mode (running statistics stay pretrained)."""
    children = dict(model.named_children())
    for name in getattr(model, "_frozen_parts", ()):
        children[name].eval()


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
