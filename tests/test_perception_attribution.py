"""Attribution: the ablation drops are what a sensor-off forward pass gives, per-target
normalization, zero channels carry nothing, decay toward uniform, and it runs on the real
LLVIP pairs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from respecd.perception.attribution import (
    Attributor,
    SceneScores,
    box_channel_sums,
    grouped,
    scene_score,
)
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector
from respecd.perception.model import FusionNet
from respecd.perception.split import candidate_windows

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


def _random_detector_input(seed: int, responsive: bool = True) -> tuple[FusionNet, torch.Tensor, torch.Tensor]:
    """An untrained net with real BatchNorm statistics; ``responsive``: its class logits vary
    with the input (exact average statistics, random class weights), else only the prior shows."""
    torch.manual_seed(seed)
    model = FusionNet(TINY)
    model.train()
    for module in model.modules():
        if responsive and isinstance(module, torch.nn.BatchNorm2d):
            module.momentum = None  # running statistics = the plain average of the batches below
    with torch.no_grad():  # give BatchNorm real statistics so the untrained net is not flat
        for _ in range(3):
            model(torch.rand(2, 5, 192, 320))
        for branch in model.head.cls if responsive else ():
            branch[-1].weight.normal_(0.0, 0.1)
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model, torch.rand(1, 5, 192, 320), torch.ones(1, 2)


@pytest.mark.parametrize("method", ["ablation", "gradient"])
def test_attribution_rows_sum_to_one_and_zero_channel_gets_nothing(method: str) -> None:
    model, x, presence = _random_detector_input(0)
    x[:, 4] = 0.0  # radar channel switched off
    presence[:, 1] = 0.0
    result = Attributor(model, method)(x, presence, 0.0, 0.5, 20, 5)
    shares, scene = result.shares, result.scene
    assert len(result.detections[1]) > 0 and shares is not None and scene is not None
    assert result.modalities == ("rgb", "thermal", "radar")
    assert shares.shape == (min(5, len(result.detections[1])), 3)
    rows = shares.sum(1)
    assert all(r == pytest.approx(1.0) or r == 0.0 for r in rows.tolist()) and rows.max() > 0
    assert shares[:, 2].abs().max().item() == 0.0 and scene["radar"] == 0.0
    assert sum(scene[m] for m in result.modalities) == pytest.approx(1.0)
    assert ("r" in scene) == (method == "gradient")  # the paper's method also splits R, G, B


def test_ablation_drop_is_what_a_sensor_off_forward_pass_gives() -> None:
    """The cached and partial passes change nothing: each drop equals a full forward with that sensor off,
    where the box's confidence is the best among the anchors whose box overlaps it with IoU >= 0.5."""
    from respecd.perception.boxes import box_iou

    model, x, presence = _random_detector_input(4)
    result = Attributor(model, "ablation")(x, presence, 0.0, 0.5, 20, 5)
    targets, scores, labels, _ = result.detections
    k = len(result.ranking)
    moved = 0
    for column, (channels, flag) in enumerate((((0, 1, 2), None), ((3,), 0), ((4,), 1))):
        x_off, presence_off = x.clone(), presence.clone()
        x_off[:, list(channels)] = 0.0
        if flag is not None:
            presence_off[:, flag] = 0.0
        with torch.no_grad():
            boxes, probabilities = model.decode(model(x_off, presence_off), tuple(x.shape[2:]))
        for i in range(k):
            overlapping = box_iou(targets[i : i + 1], boxes[0])[0] >= 0.5
            best = float(probabilities[0, overlapping, labels[i]].max()) if overlapping.any() else 0.0
            assert float(result.ranking[i, column]) == pytest.approx(float(scores[i]) - best, abs=1e-5)
            moved += int(overlapping.sum()) > 1
        assert moved  # other anchors than the target's own do overlap it: the match is over boxes
    assert result.ranking.abs().max() > 0.01  # the random net does respond to each sensor
    expected = result.ranking.clamp(min=0)
    expected = torch.nan_to_num(expected / expected.sum(1, keepdim=True))
    assert torch.allclose(result.shares, expected, atol=1e-6)


def test_every_matching_box_has_its_anchor_in_the_candidate_windows() -> None:
    """The windows the ablation runs the head on lose nothing. A decoded box contains its anchor,
    so every anchor inside a box that overlaps a target with IoU >= 0.5 must be a window cell:
    checked on random targets, random boxes around them, and boxes at the IoU limit (a target
    widened by 0.99 of its width on one side: IoU 1 / 1.99)."""
    from respecd.perception.boxes import box_iou
    from respecd.perception.model import STRIDES

    height, width = 384, 640
    gen = torch.Generator().manual_seed(5)
    matching = at_the_limit = 0
    for _ in range(60):
        corner = torch.rand(2, generator=gen) * torch.tensor([width - 40.0, height - 40.0])
        size = 4 + torch.rand(2, generator=gen) * torch.tensor([120.0, 200.0])
        target = torch.cat([corner, corner + size])[None]
        windows = candidate_windows(target, (height, width))
        w, h = float(size[0]), float(size[1])
        moves = torch.rand(300, 4, generator=gen) * 1.3 - 0.3  # each side out by -0.3 .. 1 of the target's size
        moves = torch.cat([moves, 0.99 * torch.eye(4)])  # the limit: one side out by 0.99 of it, IoU 1 / 1.99
        boxes = target + moves * torch.tensor([-w, -h, w, h])
        match = box_iou(target, boxes)[0] >= 0.5
        boxes = boxes[match]
        matching += len(boxes)
        at_the_limit += int((moves[match].max(1).values > 0.9).sum())
        for x1, y1, x2, y2 in boxes.tolist():
            for s, (r0, r1, c0, c1) in zip(STRIDES, windows, strict=True):  # cells whose anchor is in the box
                rows = range(max(0, math.ceil(y1 / s - 0.5)), min(height // s, math.floor(y2 / s - 0.5) + 1))
                cols = range(max(0, math.ceil(x1 / s - 0.5)), min(width // s, math.floor(x2 / s - 0.5) + 1))
                assert not rows or (r0 <= rows[0] and rows[-1] < r1)
                assert not cols or (c0 <= cols[0] and cols[-1] < c1)
    assert matching > 1000 and at_the_limit >= 4 * 60


def test_head_on_windows_equals_the_full_head_there() -> None:
    model, x, presence = _random_detector_input(2)
    hw = tuple(x.shape[2:])
    targets = torch.tensor([[140.0, 80.0, 156.0, 100.0], [170.0, 85.0, 180.0, 105.0]])
    windows = candidate_windows(targets, hw)
    assert all(0 < r0 and r1 < hw[0] // s and 0 < c0 and c1 < hw[1] // s  # inside the map: the halo matters
               for s, (r0, r1, c0, c1) in zip((8, 16, 32), windows, strict=True))
    with torch.no_grad():
        rgb, aux = model.encode_rgb(x[:, :3]), model.encode_aux(x[:, 3:], presence)
        boxes, probabilities = model.decode(model.fuse(rgb, aux), hw)
        raw, anchors = model.fuse_window(rgb, aux, windows)
        some_boxes, some_probabilities = model.decode(raw, hw, anchors)
    assert 0 < len(anchors) < boxes.shape[1] // 2
    assert torch.allclose(some_boxes[0], boxes[0, anchors], atol=1e-4)
    assert torch.allclose(some_probabilities[0], probabilities[0, anchors], atol=1e-6)
    with torch.no_grad():  # a window with no cells at any level gives no anchors, not an error
        raw, anchors = model.fuse_window(rgb, aux, [(0, 0, 0, 0)] * 3)
    assert len(anchors) == 0 and raw[0].shape[1] == 0 and raw[1].shape[1] == 0


def test_no_detection_decays_toward_uniform() -> None:
    scores = SceneScores(CHANNELS, decay_s=2.0, per_channel=True)
    assert scores.value["rgb"] == pytest.approx(1 / 3) and scores.value["r"] == pytest.approx(1 / 9)
    assert "r" not in SceneScores(CHANNELS, decay_s=2.0).value  # ablation scores whole modalities
    fresh = grouped(CHANNELS, torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0]))
    assert scores.update(10.0, fresh)["thermal"] == 1.0
    after = scores.update(12.0, None)  # one time constant later
    expected = 1 / 3 + (1.0 - 1 / 3) * math.exp(-1.0)
    assert after["thermal"] == pytest.approx(expected)
    assert sum(after[k] for k in ("rgb", "thermal", "radar")) == pytest.approx(1.0)
    much_later = scores.update(60.0, None)
    assert much_later["thermal"] == pytest.approx(1 / 3, abs=1e-6)


@pytest.mark.slow
def test_attribution_runs_on_real_llvip_pairs(shared_data) -> None:
    from respecd.lab.detector.data import llvip_frames

    root = shared_data / "llvip_pairs"
    model, _, _ = _random_detector_input(3, responsive=False)  # real images would saturate the other one
    detector = FusionDetector(model, PerceptionConfig(model=TINY, score_threshold=0.0, max_detections=5,
                                                      attribution_method="gradient"))
    for pair in ("190003",):  # five people, full 1280x1024
        frames = llvip_frames(root, pair)
        assert frames["rgb"].data.shape == (1024, 1280, 3)
        percept = detector.infer(frames, attribute=True)
        assert percept.contributions is not None
        assert all(np.isfinite(v) for v in percept.contributions.values())
        total = sum(percept.contributions[k] for k in ("rgb", "thermal", "radar"))
        assert total == pytest.approx(1.0)
        assert percept.contributions["radar"] == 0.0  # LLVIP has no radar: zero channel
