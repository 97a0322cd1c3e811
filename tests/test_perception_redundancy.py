"""Dependence and sufficiency tell redundancy from dependence, checked by what they are for.

A small constructed net sees a person in each sensor's plane (the mean of the plane inside the
box) and combines the sensors by a known rule: "or" (either sensor alone detects) or "and" (it
needs both). Two sensors that each suffice are redundant: high sufficiency and low dependence
each; where only thermal sees, thermal's dependence is high; and the dependence the attribution
reports is what turning the sensor off then costs, through the daemon's detector. The
normalized contributions and the Shapley value cannot tell "or" from "and": that is why the
detector reports dependence and sufficiency beside them.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from respecd.perception.ablation import needed_subsets
from respecd.perception.attribution import Attributor
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector, frames_from_arrays
from respecd.perception.split import as_split

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PERSON = (16, 16, 48, 48)  # x1, y1, x2, y2 in a 64 x 64 frame
ELSEWHERE = ((0, 0, 16, 16), (48, 48, 64, 64), (0, 48, 16, 64))  # boxes with nothing in them


class SeeingNet(nn.Module):
    """Per candidate box, each sensor's evidence is its plane's mean inside the box (RGB: over R, G, B);
    the confidence combines the sensors' evidence by ``rule``. It is its own ``SplitNet``: the
    "backbones" measure the evidence, ``detect`` combines it."""

    def __init__(self, rule: str, aux: tuple[str, ...] = ("thermal",)) -> None:
        super().__init__()
        self.rule, self.spec = rule, ModelSpec(aux_modalities=aux)  # type: ignore[arg-type]
        self.register_buffer("boxes", torch.tensor([PERSON, *ELSEWHERE], dtype=torch.float32))

    def _evidence(self, planes: torch.Tensor) -> torch.Tensor:  # (1, C, H, W) -> (N boxes, C)
        return torch.stack([planes[0, :, y1:y2, x1:x2].mean((1, 2)) for x1, y1, x2, y2 in self.boxes.int().tolist()])

    def encode_rgb(self, rgb: torch.Tensor) -> torch.Tensor:
        return self._evidence(rgb).mean(1, keepdim=True)

    def encode_aux(self, aux: torch.Tensor, presence: torch.Tensor) -> torch.Tensor:
        return self._evidence(aux) * presence  # a sensor that is off has no evidence

    def detect(self, rgb, aux, input_hw, near=None):
        seen = torch.cat([rgb, aux], 1).clamp(0, 1)  # (N, M)
        confidence = (1 - (1 - seen).prod(1)) if self.rule == "or" else seen.prod(1)
        return self.boxes[None], confidence[None, :, None]

    def forward(self, x: torch.Tensor, presence: torch.Tensor):
        return self.encode_rgb(x[:, :3]), self.encode_aux(x[:, 3:], presence)

    def decode(self, raw, input_hw):
        return self.detect(*raw, input_hw)


class WholeNet(nn.Module):
    """The same net offering only forward and decode: attribution runs it whole per subset."""

    def __init__(self, net: SeeingNet) -> None:
        super().__init__()
        self.net, self.spec = net, net.spec

    def forward(self, x, presence):
        return self.net(x, presence)

    def decode(self, raw, input_hw):
        return self.net.decode(raw, input_hw)


def _scene(rgb_sees: bool, thermal_sees: bool, radar_sees: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """A 64 x 64 input: every sensor on; a sensor that sees has the person bright in its plane."""
    planes = [(0.9 if rgb_sees else 0.02, 0.02)] * 3 + [(0.9 if thermal_sees else 0.02, 0.02)]
    if radar_sees is not None:
        planes.append((0.9 if radar_sees else 0.0, 0.0))
    x = torch.zeros(1, len(planes), 64, 64)
    for c, (inside, outside) in enumerate(planes):
        x[0, c] = outside
        x[0, c, PERSON[1]:PERSON[3], PERSON[0]:PERSON[2]] = inside
    return x, torch.ones(1, len(planes) - 3)


def _attribute(net, x, presence, sufficiency="auto"):
    result = Attributor(net, "ablation", sufficiency)(x, presence, 0.25, 0.5, 10, 5)  # the daemon's threshold
    assert len(result.detections[1]) == 1 and result.detections[0][0].tolist() == list(map(float, PERSON))
    return result


def test_two_sensors_that_each_suffice_are_redundant() -> None:
    result = _attribute(SeeingNet("or"), *_scene(rgb_sees=True, thermal_sees=True))
    assert result.sufficiency["rgb"] > 0.9 and result.sufficiency["thermal"] > 0.9  # each alone keeps it
    assert result.dependence["rgb"] < 0.1 and result.dependence["thermal"] < 0.1  # losing either costs little


def test_where_only_thermal_sees_thermal_is_depended_on() -> None:
    result = _attribute(SeeingNet("or"), *_scene(rgb_sees=False, thermal_sees=True))
    assert result.dependence["thermal"] > 0.9 and result.dependence["rgb"] < 0.05
    assert result.sufficiency["thermal"] > 0.95 and result.sufficiency["rgb"] < 0.05
    assert result.scene["thermal"] > 0.95  # the controller's contribution agrees


def test_contributions_and_shapley_cannot_tell_redundant_from_joint_but_these_can() -> None:
    from respecd.lab.detector.evaluate import shapley_share

    either = _attribute(SeeingNet("or"), *_scene(True, True), "always")  # nothing on too: the Shapley value
    both = _attribute(SeeingNet("and"), *_scene(True, True), "always")
    for result in (either, both):  # each sensor half, whichever the rule
        assert result.scene["rgb"] == pytest.approx(0.5) and result.scene["thermal"] == pytest.approx(0.5)
        shares = shapley_share(result.ablation)
        assert shares is not None and shares["rgb"] == pytest.approx(shares["thermal"])
    assert both.dependence["rgb"] == pytest.approx(1.0) and both.sufficiency["rgb"] == pytest.approx(0.0)
    assert either.dependence["rgb"] < 0.1 and either.sufficiency["rgb"] > 0.9


def test_dependence_is_what_turning_the_sensor_off_costs_in_the_daemon() -> None:
    """Through the daemon's detector: without the thermal frame (the daemon's "off"), or with a black RGB frame,
    the detection loses the share of its confidence the attribution on the full frame called that sensor's
    dependence."""
    spec = ModelSpec(aux_modalities=("thermal",))
    detector = FusionDetector(SeeingNet("or"), PerceptionConfig(model=spec))
    everything = FusionDetector(SeeingNet("or"), PerceptionConfig(model=spec, score_threshold=0.0))  # no threshold
    for rgb_sees, thermal_sees in ((True, True), (False, True), (True, False)):
        x, _ = _scene(rgb_sees, thermal_sees)
        rgb = (x[0, :3].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        thermal = (x[0, 3].numpy() * 255).round().astype(np.uint8)
        full = detector.infer(frames_from_arrays(rgb, thermal), attribute=True)
        assert [d.box for d in full.detections] == [PERSON]
        for name, frames in (("rgb", frames_from_arrays(np.zeros_like(rgb), thermal)),
                             ("thermal", frames_from_arrays(rgb))):
            kept = [d.confidence for d in everything.infer(frames, attribute=False).detections if d.box == PERSON]
            cost = full.detections[0].confidence - kept[0]
            assert cost / full.detections[0].confidence == pytest.approx(full.dependence[name], abs=1e-6)


def test_a_whole_net_gives_the_split_nets_numbers() -> None:
    """Any net with forward and decode gets the same numbers (whole forward passes), as another runtime's
    ``SplitNet`` would through the interface."""
    net = SeeingNet("or")
    assert as_split(net) is net
    x, presence = _scene(True, False)
    split, whole = _attribute(net, x, presence), _attribute(WholeNet(net), x, presence)
    assert split.dependence == whole.dependence and split.sufficiency == whole.sufficiency
    assert torch.equal(split.ranking, whole.ranking)


def test_three_sensors_sufficiency_when_asked_and_shapley_is_exact() -> None:
    """With three sensors on, each alone is a pass more: left out unless asked; then every subset is run and
    the Shapley values add up to what all three find over what none finds."""
    from respecd.perception.ablation import shapley

    net = SeeingNet("or", aux=("thermal", "radar"))
    x, presence = _scene(rgb_sees=False, thermal_sees=True, radar_sees=True)
    auto = _attribute(net, x, presence)
    assert auto.sufficiency is None and auto.dependence is not None
    asked = _attribute(net, x, presence, "always")
    assert asked.sufficiency["thermal"] > 0.9 and asked.sufficiency["radar"] > 0.9 and asked.sufficiency["rgb"] < 0.05
    assert asked.dependence["thermal"] < 0.1 and asked.dependence["radar"] < 0.1  # redundant with each other
    assert len(asked.ablation.subsets) == 8
    values = shapley(asked.ablation)
    nothing = asked.ablation.subsets[frozenset()]
    assert float(values.sum()) == pytest.approx(float(asked.ablation.base[0] - nothing[0]), abs=1e-6)


def test_needed_subsets() -> None:
    two, three = frozenset({"rgb", "thermal"}), frozenset({"rgb", "thermal", "radar"})
    assert set(needed_subsets(two)) == {frozenset({"rgb"}), frozenset({"thermal"})}  # alone = the other off
    assert len(needed_subsets(three)) == 3 and len(needed_subsets(three, alone=True)) == 7  # + alone, + none
    assert needed_subsets(frozenset({"rgb"})) == [frozenset()]  # the only sensor off: nothing on
