"""Attribution: per-target normalization, zero channels carry nothing, decay toward uniform,
and it runs on the real LLVIP pairs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from respecd.perception.attribution import SceneScores, attribute, box_channel_sums, grouped, scene_score
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector
from respecd.perception.model import FusionNet

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")
CHANNELS = ("r", "g", "b", "thermal", "radar")


def test_box_sums_are_normalized_per_target() -> None:
    saliency = torch.zeros(5, 40, 60)
    saliency[0, 5:10, 5:10] = 1.0  # red inside box 0
    saliency[3, 5:10, 5:10] = 3.0  # thermal inside box 0, three times as strong
    saliency[4, 20:30, 40:50] = 2.0  # radar inside box 1 only
    boxes = torch.tensor([[5.0, 5.0, 10.0, 10.0], [40.0, 20.0, 50.0, 30.0], [0, 30, 4, 39.0]])
    rows = box_channel_sums(saliency, boxes)
    assert rows[0].tolist() == pytest.approx([0.25, 0, 0, 0.75, 0])
    assert rows[1].tolist() == pytest.approx([0, 0, 0, 0, 1.0])
    assert rows[2].tolist() == [0.0] * 5  # nothing attributed there: a zero row, not NaN


def test_scene_score_is_confidence_weighted_and_grouped() -> None:
    rows = torch.tensor([[1.0, 0, 0, 0, 0], [0, 0, 0, 1.0, 0], [0, 0, 0, 0, 0]])
    scene = scene_score(rows, torch.tensor([0.9, 0.3, 0.99]))  # the empty row carries no weight
    assert scene.tolist() == pytest.approx([0.75, 0, 0, 0.25, 0])
    values = grouped(CHANNELS, scene)
    assert values["rgb"] == pytest.approx(values["r"] + values["g"] + values["b"])
    assert sum(values[k] for k in ("rgb", "thermal", "radar")) == pytest.approx(1.0)
    assert scene_score(torch.zeros(2, 5), torch.tensor([0.5, 0.5])) is None


def _random_detector_input(seed: int) -> tuple[FusionNet, torch.Tensor, torch.Tensor]:
    torch.manual_seed(seed)
    model = FusionNet(TINY)
    model.train()
    with torch.no_grad():  # give BatchNorm real statistics so the untrained net is not flat
        for _ in range(3):
            model(torch.rand(2, 5, 192, 320))
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model, torch.rand(1, 5, 192, 320), torch.ones(1, 2)


def test_attribution_rows_sum_to_one_and_zero_channel_gets_nothing() -> None:
    model, x, presence = _random_detector_input(0)
    x[:, 4] = 0.0  # radar channel switched off
    presence[:, 1] = 0.0
    dets, per_target, scene = attribute(model, x, presence, 0.0, 0.5, 20, 5)
    assert len(dets[1]) > 0 and per_target is not None and scene is not None
    assert per_target.shape == (min(5, len(dets[1])), 5)
    assert per_target.sum(1).tolist() == pytest.approx([1.0] * len(per_target))
    assert per_target[:, 4].abs().max().item() == 0.0
    assert scene[4].item() == 0.0 and scene.sum().item() == pytest.approx(1.0)


def test_no_detection_decays_toward_uniform() -> None:
    scores = SceneScores(CHANNELS, decay_s=2.0)
    assert scores.value["rgb"] == pytest.approx(1 / 3) and scores.value["r"] == pytest.approx(1 / 9)
    fresh = grouped(CHANNELS, torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0]))
    assert scores.update(10.0, fresh)["thermal"] == 1.0
    after = scores.update(12.0, None)  # one time constant later
    expected = 1 / 3 + (1.0 - 1 / 3) * math.exp(-1.0)
    assert after["thermal"] == pytest.approx(expected)
    assert sum(after[k] for k in ("rgb", "thermal", "radar")) == pytest.approx(1.0)
    much_later = scores.update(60.0, None)
    assert much_later["thermal"] == pytest.approx(1 / 3, abs=1e-6)


def test_attribution_runs_on_real_llvip_pairs(shared_data) -> None:
    from respecd.lab.detector.data import llvip_frames

    root = shared_data / "llvip_pairs"
    model, _, _ = _random_detector_input(3)
    detector = FusionDetector(model, PerceptionConfig(model=TINY, score_threshold=0.0, max_detections=5))
    for pair in ("190003",):  # five people, full 1280x1024
        frames = llvip_frames(root, pair)
        assert frames["rgb"].data.shape == (1024, 1280, 3)
        percept = detector.infer(frames, attribute=True)
        assert percept.contributions is not None
        assert all(np.isfinite(v) for v in percept.contributions.values())
        total = sum(percept.contributions[k] for k in ("rgb", "thermal", "radar"))
        assert total == pytest.approx(1.0)
        assert percept.contributions["radar"] == 0.0  # LLVIP has no radar: zero channel
