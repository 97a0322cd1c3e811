"""The fusion net on pretrained Darknet backbones: a sensor that is off adds nothing, checkpoints round-trip,
the detector runs and attributes with it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from respecd.errors import InputError
from respecd.perception import checkpoint, darknet
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.darknet_fusion import DarknetFusionNet, from_darknet
from respecd.perception.detector import FusionDetector, frames_from_arrays

pytestmark = pytest.mark.usefixtures("one_torch_thread")

NAME = "yolo-fastest-1.1_body"
SPEC = ModelSpec(backbone=f"darknet:{NAME}", aux_modalities=("thermal",))


@pytest.fixture
def weights(shared_data: Path) -> Path:
    return shared_data.parent / "pretrained" / "yolo_fastest" / f"{NAME}.weights"


@pytest.fixture
def pair(shared_data: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """A real registered visible/infrared pair (TarDAL's M3FD sample), 640x480, as 0..1 planes."""
    root = shared_data / "tardal_ir_vis_samples"
    vis = cv2.resize(cv2.imread(str(root / "vi" / "M3FD_00471.png")), (640, 480))
    ir = cv2.resize(cv2.imread(str(root / "ir" / "M3FD_00471.png"), cv2.IMREAD_GRAYSCALE), (640, 480))
    rgb = torch.from_numpy(vis[:, :, ::-1].copy()).permute(2, 0, 1).float()[None] / 255
    return rgb, torch.from_numpy(ir).float()[None, None] / 255


@pytest.mark.slow
def test_a_sensor_that_is_off_adds_nothing(weights: Path, pair) -> None:
    model = from_darknet(SPEC, weights).eval()
    ref = darknet.load(weights.with_suffix(".cfg"), weights)
    rgb, ir = pair
    with torch.inference_mode():
        rgb_only = model(torch.cat([rgb, torch.zeros_like(ir)], 1), torch.zeros(1, 1))
        ir_only = model(torch.cat([torch.zeros_like(rgb), ir], 1), torch.ones(1, 1))
        both = model(torch.cat([rgb, ir], 1), torch.ones(1, 1))
        for ours, pretrained in zip(rgb_only, ref(rgb), strict=True):
            torch.testing.assert_close(ours, pretrained, rtol=0, atol=1e-4)  # thermal off: the pretrained net
        for ours, pretrained in zip(ir_only, ref(ir.expand(1, 3, -1, -1)), strict=True):
            torch.testing.assert_close(ours, pretrained, rtol=0, atol=1e-4)  # RGB off: it on replicated IR
        assert any((a - b).abs().max() > 0.1 for a, b in zip(both, rgb_only, strict=True))  # both on: fused


@pytest.mark.slow
def test_checkpoint_round_trip_and_detector(weights: Path, pair, tmp_path: Path) -> None:
    model = from_darknet(SPEC, weights).eval()
    path = tmp_path / "rgbt.pt"
    checkpoint.save(path, model, {"data": "unit-test"})
    loaded, _ = checkpoint.load(str(path), expected=SPEC)
    assert isinstance(loaded, DarknetFusionNet)
    rgb, ir = pair
    x = torch.cat([rgb, ir], 1)
    with torch.inference_mode():
        for a, b in zip(model(x, torch.ones(1, 1)), loaded(x, torch.ones(1, 1)), strict=True):
            assert torch.equal(a, b)
    config = PerceptionConfig(weights=str(path), model=SPEC)
    detector = FusionDetector.load(config)
    vis = (rgb[0].permute(1, 2, 0).numpy()[:, :, ::-1] * 255).astype(np.uint8)
    thermal = (ir[0, 0].numpy() * 255).astype(np.uint8)
    percept = detector.infer(frames_from_arrays(vis, thermal), attribute=True)
    assert percept.detections and percept.contributions is not None
    assert set(percept.contributions) >= {"rgb", "thermal"}
    assert abs(percept.contributions["rgb"] + percept.contributions["thermal"] - 1) < 1e-5
    assert all(0 <= d.box[0] < d.box[2] <= 640 and 0 <= d.box[1] < d.box[3] <= 480 for d in percept.detections)


def test_unknown_backbone_is_a_clear_error() -> None:
    with pytest.raises(InputError, match=r"no packaged Darknet cfg nope.cfg \(shipped: .*yolo-fastest-1.1_body"):
        checkpoint.build(ModelSpec(backbone="darknet:nope"))


def test_spec_rover_profile_loads_the_shipped_real_checkpoint() -> None:
    from respecd.config import load_profile

    profile = load_profile(Path(__file__).resolve().parents[1] / "configs" / "spec-rover.yaml")
    assert profile.perception.weights == "builtin:rgbt"
    detector = FusionDetector.load(profile.perception.model_copy(update={"device": "cpu"}))
    assert isinstance(detector.model, DarknetFusionNet) and detector.channels == ("r", "g", "b", "thermal")
    spec = detector.model.spec  # the card's, docs/PERCEPTION.md: xl on both backbones, one thermal map per case
    assert (spec.backbone, spec.aux_backbone, spec.rgb_aware_fusion) == ("darknet:yolo-fastest-1.1-xl", None, True)


XL = "yolo-fastest-1.1-xl"
MIXED = ModelSpec(backbone=f"darknet:{NAME}", aux_backbone=f"darknet:{XL}", aux_scale=0.5, aux_modalities=("thermal",))


@pytest.mark.slow
def test_a_thermal_backbone_from_another_model_starts_silent(weights: Path, pair) -> None:
    with pytest.raises(InputError, match="needs its own .weights file"):
        from_darknet(MIXED, weights)
    model = from_darknet(MIXED, weights, weights.with_name(f"{XL}.weights")).eval()
    assert sum(p.numel() for p in model.aux.parameters()) > 2 * sum(p.numel() for p in model.rgb.parameters())
    ref = darknet.load(weights.with_suffix(".cfg"), weights)
    rgb, ir = pair
    with torch.inference_mode():
        both = model(torch.cat([rgb, ir], 1), torch.ones(1, 1))
        for ours, pretrained in zip(both, ref(rgb), strict=True):  # its features are not the head's: W_aux = 0
            torch.testing.assert_close(ours, pretrained, rtol=0, atol=1e-4)
    with torch.no_grad():
        for fuse in model.fuse:
            fuse.aux.weight.normal_(0, 0.01)  # as if trained: thermal now moves the output
        moved = model(torch.cat([rgb, ir], 1), torch.ones(1, 1))
        blank = model(torch.cat([rgb, torch.zeros_like(ir)], 1), torch.zeros(1, 1))
    assert any((a - b).abs().max() > 1e-3 for a, b in zip(moved, both, strict=True))
    for ours, pretrained in zip(blank, ref(rgb), strict=True):  # thermal off still adds exactly nothing
        torch.testing.assert_close(ours, pretrained, rtol=0, atol=1e-4)


@pytest.mark.slow
def test_a_checkpoint_with_one_joint_fusion_kernel_loads(weights: Path, pair) -> None:
    """Checkpoints written before the fusion was split into its RGB and aux halves hold one (c, 2c) kernel."""
    model = from_darknet(SPEC, weights).eval()
    state = model.state_dict()
    for i in range(len(model.fuse)):
        state[f"fuse.{i}.weight"] = torch.cat([state.pop(f"fuse.{i}.rgb.weight"), state.pop(f"fuse.{i}.aux.weight")], 1)
    fresh = DarknetFusionNet(SPEC).eval()
    fresh.load_state_dict(state, strict=True)
    x = torch.cat(pair, 1)
    with torch.inference_mode():
        for a, b in zip(model(x, torch.ones(1, 1)), fresh(x, torch.ones(1, 1)), strict=True):
            assert torch.equal(a, b)


@pytest.mark.slow
def test_rgb_aware_fusion_changes_only_what_both_cameras_see_together(weights: Path, pair, tmp_path: Path) -> None:
    """``rgb_aware_fusion``: W_both starts as W_aux (the import is unchanged) and acts only where RGB is on as
    well; each sensor alone goes through exactly the maps it had, and W_aux no longer acts beside RGB."""
    plain = from_darknet(SPEC, weights).eval()
    aware_spec = SPEC.model_copy(update={"rgb_aware_fusion": True})
    aware = from_darknet(aware_spec, weights).eval()
    rgb, ir = pair
    inputs = {"both": (torch.cat([rgb, ir], 1), torch.ones(1, 1)),
              "rgb": (torch.cat([rgb, torch.zeros_like(ir)], 1), torch.zeros(1, 1)),
              "thermal": (torch.cat([torch.zeros_like(rgb), ir], 1), torch.ones(1, 1))}
    with torch.inference_mode():
        for x, presence in inputs.values():
            for a, b in zip(plain(x, presence), aware(x, presence), strict=True):
                assert torch.equal(a, b)  # W_both = W_aux at import
        for fuse in aware.fuse:
            fuse.both.weight.normal_(0, 0.05)  # as if trained
        for fuse in plain.fuse:
            fuse.aux.weight.mul_(3)  # and W_aux too
        for fuse, mine in zip(aware.fuse, plain.fuse, strict=True):
            fuse.aux.weight.copy_(mine.aux.weight)
        out = {name: aware(x, presence) for name, (x, presence) in inputs.items()}
        for name in ("rgb", "thermal"):
            for a, b in zip(plain(*inputs[name]), out[name], strict=True):
                assert torch.equal(a, b), name
        assert any((a - b).abs().max() > 1e-3 for a, b in zip(plain(*inputs["both"]), out["both"], strict=True))
        two = torch.cat([inputs["both"][0], inputs["thermal"][0]])  # per image in a batch
        batched = aware(two, torch.ones(2, 1))
        for i, name in enumerate(("both", "thermal")):
            for a, b in zip(batched, out[name], strict=True):
                torch.testing.assert_close(a[i:i + 1], b, rtol=0, atol=1e-5)
        for fuse in aware.fuse:
            fuse.aux.weight.zero_()  # thermal alone's map does not act beside RGB
        for a, b in zip(aware(*inputs["both"]), out["both"], strict=True):
            assert torch.equal(a, b)
    path = tmp_path / "aware.pt"
    checkpoint.save(path, aware, {"data": "unit-test"})
    loaded, _ = checkpoint.load(str(path))
    assert loaded.spec.rgb_aware_fusion and all(torch.equal(a.both.weight, b.both.weight)
                                                for a, b in zip(aware.fuse, loaded.fuse, strict=True))
