"""The fusion network: shapes at the three RGB resolutions, DFL decoding, NMS, the detector API."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from respecd.messages import conf_agg
from respecd.perception import fold
from respecd.perception.boxes import box_iou, nms, pad_to_stride
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector, frames_from_arrays
from respecd.perception.model import FusionNet, anchor_grid, decode_boxes

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def net() -> FusionNet:
    torch.manual_seed(0)
    return FusionNet(ModelSpec()).eval()


@pytest.mark.parametrize("w,h", [(1280, 720), (960, 540), (640, 360)])
def test_output_shapes_follow_rgb_resolution(net: FusionNet, w: int, h: int) -> None:
    hp, wp = pad_to_stride(h, w)
    assert hp % 32 == 0 and wp % 32 == 0 and hp - h < 32 and wp - w < 32
    x = torch.rand(1, 5, hp, wp)
    with torch.inference_mode():
        box, cls = net(x, torch.ones(1, 2))
    n = sum((hp // s) * (wp // s) for s in (8, 16, 32))
    assert box.shape == (1, n, 4 * net.spec.reg_max)
    assert cls.shape == (1, n, 1)
    points, strides = anchor_grid(hp, wp)
    assert points.shape == (n, 2) and strides.shape == (n, 1)


def test_cost_scales_with_pixels() -> None:
    """Fully convolutional: 640x360 has about a third of the anchors of 1280x720 (not a resize)."""
    small = sum((384 // s) * (640 // s) for s in (8, 16, 32))
    large = sum((736 // s) * (1280 // s) for s in (8, 16, 32))
    assert 0.25 < small / large < 0.3


def test_dfl_decode_uniform_logits_gives_centred_box() -> None:
    reg_max = 16
    points = torch.tensor([[100.0, 50.0]])
    strides = torch.tensor([[8.0]])
    box = decode_boxes(torch.zeros(1, 1, 4 * reg_max), points, strides, reg_max)
    # uniform over bins 0..15 -> expected distance 7.5 stride units = 60 px each side
    assert torch.allclose(box[0, 0], torch.tensor([40.0, -10.0, 160.0, 110.0]))


def test_nms_keeps_best_of_overlapping_boxes() -> None:
    boxes = torch.tensor([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60]], dtype=torch.float32)
    scores = torch.tensor([0.5, 0.9, 0.8])
    keep = nms(boxes, scores, 0.5)
    assert keep.tolist() == [1, 2]
    assert box_iou(boxes[:1], boxes[1:2]).item() == pytest.approx(81 / 119)


def test_presence_planes_change_the_output() -> None:
    torch.manual_seed(2)
    model = FusionNet(TINY).train()  # batch statistics: an untrained net's running stats flatten everything
    x = torch.rand(2, 5, 192, 320)
    with torch.no_grad():
        on = model(x, torch.tensor([[1.0, 1.0], [1.0, 1.0]]))[1]
        off = model(x, torch.tensor([[1.0, 1.0], [0.0, 0.0]]))[1]
    assert not torch.allclose(on[1], off[1])


def test_detector_runs_with_missing_modalities() -> None:
    torch.manual_seed(1)
    config = PerceptionConfig(score_threshold=0.0, model=TINY, max_detections=10)
    model = FusionNet(TINY).train()
    for module in model.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.momentum = None  # running statistics = the average of the batches below
    with torch.no_grad():
        for _ in range(2):
            model(torch.rand(2, 5, 192, 320))
        for branch in model.head.cls:  # class logits that respond to the input, not only the prior
            branch[-1].weight.normal_(0.0, 0.5)
    detector = FusionDetector(model, config)
    rgb = np.random.default_rng(0).integers(0, 255, (360, 640, 3), dtype=np.uint8)
    percept = detector.infer(frames_from_arrays(rgb), attribute=False)
    assert percept.contributions is None and percept.latency > 0
    assert 0 < len(percept.detections) <= 10
    for det in percept.detections:
        x1, y1, x2, y2 = det.box
        assert 0 <= x1 <= x2 <= 640 and 0 <= y1 <= y2 <= 360  # clipped to the RGB frame, not the padding
    thermal_only = detector.infer(frames_from_arrays(None, thermal=np.full((120, 160), 30000, np.uint16)), True)
    assert thermal_only.contributions is not None
    assert thermal_only.contributions["rgb"] == pytest.approx(0.0)  # zero RGB planes carry nothing


def test_conf_agg_is_mean_of_top_three() -> None:
    assert conf_agg([]) == 0.0
    assert conf_agg([0.5]) == 0.5
    assert conf_agg([0.9, 0.1, 0.8, 0.7]) == pytest.approx(0.8)


def test_inference_rewrite_keeps_the_outputs() -> None:
    """Folded batch norms and channels-last memory (what the detector runs) change no output:
    on a net whose batch norms hold non-trivial statistics, box and class logits agree to 1e-4."""
    torch.manual_seed(3)
    model = FusionNet(TINY).train()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.3, 0.3)
        for _ in range(3):  # running statistics away from (0, 1)
            model(torch.rand(2, 5, 64, 96) * 2, torch.ones(2, 2))
    x, presence = torch.rand(1, 5, 64, 96), torch.tensor([[1.0, 0.0]])
    with torch.no_grad():
        want = model.eval()(x, presence)
        fast = fold.for_inference(model, torch.device("cpu"))
        got = fast(fold.channels_last(x), presence)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    for w, g in zip(want, got, strict=True):
        torch.testing.assert_close(g, w, atol=1e-4, rtol=1e-4)
