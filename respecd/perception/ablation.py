"""What each sensor's detections depend on: the detector re-run on subsets of its sensors.

For the top-K detections with every sensor on, the net runs again with sensors switched off
exactly as the daemon feeds a disabled sensor (zero plane, presence 0), through a ``SplitNet``
(``split.py``): the backbones once per input, fusion + neck + head once per subset. A target's
confidence in a subset is the best one of its class among the anchors whose box overlaps it with
IoU >= 0.5, wherever the net now places it (with a sensor off a neighbouring anchor often takes
the detection over). The subsets run, for the sensors that are on: each one off (its *dependence*:
the confidence lost), and each one alone (its *sufficiency*: the confidence it keeps alone). With
two sensors on, each alone is the other one off: no pass more. With three or more, each alone is
one fusion pass more per sensor, run only when asked (``alone=True``); then nothing on is run
too (a constant per input size), and with at most three sensors on that is every subset, so the
exact Shapley value over sensors (``shapley``) needs no pass more.

Two sensors that each suffice are redundant: each alone keeps the detection (high sufficiency),
and turning either off costs little (low dependence). The normalized drops (the controller's
contribution scores) cannot show that: both drops are small, and their shares say nothing of it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from respecd.perception.boxes import box_iou
from respecd.perception.split import MATCH_IOU, Scored, SplitNet

Subset = frozenset[str]  # the sensors on


@dataclass(frozen=True)
class Ablation:
    """Per target (rows, the detections' order) and sensor (columns, ``modalities``)."""

    modalities: tuple[str, ...]
    on: Subset  # the sensors that were on
    base: torch.Tensor  # (K,) confidence with every sensor on
    drops: torch.Tensor  # (K, M) confidence lost with that sensor off (0 for a sensor already off)
    alone: torch.Tensor | None  # (K, M) confidence with only that sensor on (0 for one already off); None: not run
    subsets: dict[Subset, torch.Tensor]  # (K,) confidence per subset run, the all-on one included


class SubsetRunner:
    """Runs a ``SplitNet`` on sensor subsets of one input. Build one per net and keep it: it holds,
    per input size, what does not depend on the frame (a black RGB frame's features, the aux
    features with every aux sensor off, and the net's output with nothing on)."""

    def __init__(self, split: SplitNet) -> None:
        self.split = split
        self.modalities = ("rgb", *split.spec.aux_modalities)
        self._constant: dict[tuple, Any] = {}

    def run(self, x: torch.Tensor, presence: torch.Tensor) -> tuple[Scored, _Frame]:
        """Every sensor on: all anchors' boxes and probabilities, and the frame's features for ``ablate``."""
        frame = _Frame(self, x, presence)
        return self.split.detect(frame.rgb_on, frame.aux_on, frame.hw), frame

    def ablate(self, frame: _Frame, targets: torch.Tensor, labels: torch.Tensor, base: torch.Tensor,
               alone: bool = False) -> Ablation:
        """Each sensor that is on switched off; each one alone where that is free or ``alone`` asks (module doc)."""
        on = frame.on
        confidence: dict[Subset, torch.Tensor] = {on: base}
        for subset in needed_subsets(on, alone):
            boxes, probabilities = self._scored(frame, subset, targets)
            confidence[subset] = box_confidence(boxes[0], probabilities[0], targets, labels)
        drops, kept = torch.zeros(len(base), len(self.modalities)), torch.zeros(len(base), len(self.modalities))
        for m, name in enumerate(self.modalities):
            if name in on:
                drops[:, m] = base - confidence[on - {name}]
                kept[:, m] = confidence.get(frozenset({name}), torch.nan)
        return Ablation(self.modalities, on, base, drops, None if kept.isnan().any() else kept, confidence)

    def _scored(self, frame: _Frame, subset: Subset, targets: torch.Tensor) -> Scored:
        if not subset:  # nothing on: the same output for every frame of this size
            return self._cached(("nothing", *frame.key), lambda: self.split.detect(
                self.black_rgb(frame), self.aux_off(frame), frame.hw))
        rgb = frame.rgb_on if "rgb" in subset else self.black_rgb(frame)
        return self.split.detect(rgb, frame.aux(subset), frame.hw, targets)

    def black_rgb(self, frame: _Frame) -> object:
        x = frame.x
        return self._cached(("rgb", *frame.key), lambda: self.split.encode_rgb(x.new_zeros(1, 3, *frame.hw)))

    def aux_off(self, frame: _Frame) -> object:
        x, a = frame.x, frame.presence.shape[1]
        return self._cached(("aux", *frame.key), lambda: self.split.encode_aux(
            x.new_zeros(1, a, *frame.hw), frame.presence.new_zeros(1, a)))

    def _cached(self, key: tuple, make: Callable[[], Any]) -> Any:
        if key not in self._constant:
            self._constant[key] = make()
        return self._constant[key]


class _Frame:
    """One input's features, computed once each: RGB on, and the aux backbone per set of aux sensors on."""

    def __init__(self, runner: SubsetRunner, x: torch.Tensor, presence: torch.Tensor) -> None:
        self.runner, self.x, self.presence = runner, x, presence
        self.hw: tuple[int, int] = (int(x.shape[2]), int(x.shape[3]))
        self.key = (self.hw, x.dtype, x.device)
        self.on = sensors_on(runner.modalities, x, presence)
        self.rgb_on = runner.split.encode_rgb(x[:, :3])
        self.aux_on = runner.split.encode_aux(x[:, 3:], presence)
        self._aux: dict[Subset, object] = {self.on - {"rgb"}: self.aux_on}

    def aux(self, subset: Subset) -> object:
        """The aux features with only ``subset``'s aux sensors on (the others: zero plane, presence 0)."""
        wanted = subset - {"rgb"}
        if not wanted:
            return self.runner.aux_off(self)
        if wanted not in self._aux:
            keep = torch.tensor([n in wanted for n in self.runner.modalities[1:]], dtype=self.x.dtype,
                                device=self.x.device)
            planes = self.x[:, 3:] * keep[None, :, None, None]
            self._aux[wanted] = self.runner.split.encode_aux(planes, self.presence * keep[None])
        return self._aux[wanted]


def sensors_on(modalities: tuple[str, ...], x: torch.Tensor, presence: torch.Tensor) -> Subset:
    """The sensors of a (1, 3 + A, H, W) input that are on: RGB unless its planes are all zero, an aux
    modality when its presence flag is set (a radar that sees nothing is on)."""
    aux = [n for i, n in enumerate(modalities[1:]) if float(presence[0, i]) > 0]
    return frozenset((["rgb"] if bool(x[:, :3].any()) else []) + aux)


def needed_subsets(on: Subset, alone: bool = False) -> list[Subset]:
    """Besides all of ``on``: each sensor off; with ``alone``, or at most two sensors on (free then), each
    sensor alone; with ``alone``, nothing on. Each subset once."""
    ordered = sorted(on)
    wanted = [on - {n} for n in ordered]
    if alone or len(on) <= 2:
        wanted += [frozenset({n}) for n in ordered]
    if alone:
        wanted.append(frozenset())
    return [s for i, s in enumerate(wanted) if s != on and s not in wanted[:i]]


def box_confidence(boxes: torch.Tensor, probabilities: torch.Tensor, targets: torch.Tensor,
                   labels: torch.Tensor) -> torch.Tensor:
    """Per target box, the best confidence of its class among the anchors whose box overlaps it with
    IoU >= 0.5: what is left of that detection, wherever the net now places it (0 if nothing)."""
    if len(boxes) == 0:
        return targets.new_zeros(len(targets))
    overlap = box_iou(targets, boxes) >= MATCH_IOU  # (K, N)
    scores = probabilities[:, labels].T  # (K, N)
    return torch.where(overlap, scores, torch.zeros_like(scores)).amax(1)


def kept_share(per_target: torch.Tensor, base: torch.Tensor) -> torch.Tensor | None:
    """(K, M) confidences -> (M,) the share of the targets' confidence (``base``, (K,)) they make up, each
    target's clipped to 0..its base: confidence-weighted over targets. None without targets."""
    total = float(base.sum())
    if total <= 0:
        return None
    return torch.minimum(per_target.clamp(min=0.0), base[:, None]).sum(0) / total


def shapley(ablation: Ablation) -> torch.Tensor | None:
    """(K, M) exact Shapley values of the sensors that were on, over the subsets run, from nothing on
    to all on (0 for sensors off); None when a subset is missing (more than 3 sensors on)."""
    on = sorted(ablation.on)
    values = torch.zeros(len(ablation.base), len(ablation.modalities))
    n = len(on)
    for name in on:
        others = [o for o in on if o != name]
        for size in range(n):
            weight = math.factorial(size) * math.factorial(n - size - 1) / math.factorial(n)
            for rest in itertools.combinations(others, size):
                without, with_ = frozenset(rest), frozenset(rest) | {name}
                if without not in ablation.subsets or with_ not in ablation.subsets:
                    return None
                values[:, ablation.modalities.index(name)] += weight * (
                    ablation.subsets[with_] - ablation.subsets[without])
    return values
