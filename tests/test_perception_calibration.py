"""Confidence calibration per RGB size: the fit, the map a checkpoint carries, and `respecd calibrate`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from respecd.cli import main as cli_main
from respecd.errors import ConfigError
from respecd.lab.detector.finetune import initial_model
from respecd.perception import checkpoint
from respecd.perception.calibration import ScoreCalibration, fit_platt, platt, raw_confidence_for
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector, frames_from_arrays
from respecd.perception.model import FusionNet

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))
SIZES = {"640x360": (1.5, 1.9), "960x540": (1.7, 1.5), "1280x720": (1.6, 0.6)}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_fit_recovers_the_map_that_made_the_labels() -> None:
    rng = np.random.default_rng(0)
    logits = rng.normal(-1.0, 2.0, 20000)
    scores = 1 / (1 + np.exp(-logits))
    matched = rng.random(len(scores)) < 1 / (1 + np.exp(-(2.0 * logits + 1.0)))
    a, b = fit_platt(scores, matched)
    assert a == pytest.approx(2.0, abs=0.1) and b == pytest.approx(1.0, abs=0.1)


def test_raw_confidence_for_inverts_the_map() -> None:
    raw = raw_confidence_for(0.25, 1.5, 1.9)
    assert float(platt(torch.tensor([raw]), 1.5, 1.9)) == pytest.approx(0.25, abs=1e-6)
    assert raw < 0.25  # a positive offset lifts low raw confidences over the threshold


def test_each_input_uses_the_size_of_nearest_padded_height() -> None:
    calibration = ScoreCalibration(SIZES)
    assert calibration.params((384, 640)) == SIZES["640x360"]
    assert calibration.params((544, 960)) == SIZES["960x540"]
    assert calibration.params((736, 1280)) == SIZES["1280x720"]
    assert calibration.params((480, 640)) == SIZES["960x540"]  # 640x480: 544 is nearer than 384


@pytest.mark.parametrize(("table", "message"), [
    ([1, 2], "expected a mapping of 'WxH' to [a, b]"),
    ({"640by360": [1.0, 0.0]}, "score_calibration.640by360: expected 'WxH': [a, b]"),
    ({"640x360": [1.0]}, "score_calibration.640x360: expected 'WxH': [a, b]"),
    ({"640x360": [-0.5, 0.0]}, "slope a must be > 0"),
])
def test_a_bad_calibration_in_a_checkpoint_is_a_config_error(table, message: str) -> None:
    with pytest.raises(ConfigError, match="net.pt: ") as err:
        ScoreCalibration.from_payload(table, "net.pt")
    assert message in str(err.value)


def _tiny_checkpoint(path: Path, calibration: dict | None) -> None:
    torch.manual_seed(0)
    extra = {"data": "sim"} | ({"score_calibration": calibration} if calibration else {})
    checkpoint.save(path, FusionNet(TINY), extra)


@pytest.mark.slow
def test_the_detector_reports_calibrated_confidences_in_the_same_order(tmp_path: Path) -> None:
    raw_path, calibrated_path = tmp_path / "raw.pt", tmp_path / "cal.pt"
    _tiny_checkpoint(raw_path, None)
    _tiny_checkpoint(calibrated_path, {size: list(ab) for size, ab in SIZES.items()})
    rgb = np.random.default_rng(1).integers(0, 255, (360, 640, 3), dtype=np.uint8)
    confidences = []
    for path in (raw_path, calibrated_path):
        detector = FusionDetector.load(PerceptionConfig(weights=str(path), model=TINY, score_threshold=0.0))
        percept = detector.infer(frames_from_arrays(rgb), attribute=False)
        confidences.append(np.array([d.confidence for d in percept.detections]))
    raw, calibrated = confidences
    assert len(raw) == len(calibrated) > 0
    expected = platt(torch.from_numpy(raw), *SIZES["640x360"]).numpy()
    np.testing.assert_allclose(calibrated, expected, rtol=1e-4, atol=1e-6)
    assert np.all(np.diff(calibrated) <= 1e-7)  # still sorted as NMS sorted the raw ones


def test_training_from_a_calibrated_checkpoint_starts_from_raw_confidences(tmp_path: Path) -> None:
    path = tmp_path / "cal.pt"
    _tiny_checkpoint(path, {size: list(ab) for size, ab in SIZES.items()})
    assert initial_model(str(path), TINY).score_calibration is None  # new weights need a new fit


@pytest.mark.slow
def test_calibrate_command_writes_the_map_beside_unchanged_weights(tmp_path: Path, capsys) -> None:
    out = tmp_path / "sim-rover.pt"
    assert cli_main(["calibrate", "--weights", "builtin:sim-rover", "--out", str(out), "--frames", "6", "--seed", "7",
                     "--json", str(tmp_path / "cal.json"), "--no-progress"]) == 0
    source, _ = checkpoint.load("builtin:sim-rover")
    calibrated, payload = checkpoint.load(str(out))
    for name, tensor in source.state_dict().items():
        assert torch.equal(tensor, calibrated.state_dict()[name])
    assert set(payload["score_calibration"]) == {"640x360", "960x540", "1280x720"}
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["score_calibration"]["table"] == payload["score_calibration"]
    assert card["score_calibration"]["fit"]["seed"] == 7 and card["checkpoint_bytes"] == out.stat().st_size
    report = json.loads((tmp_path / "cal.json").read_text())
    for size, row in report["fit"]["sizes"].items():
        assert row["a"] > 0 and 0 <= row["ece_calibrated"] <= 1 and row["boxes"] >= row["matched"] > 0, size
    assert "| fit 7 | 640x360 |" in capsys.readouterr().out
    detector = FusionDetector.load(PerceptionConfig(weights=str(out)))
    assert detector.model.score_calibration is not None


@pytest.mark.slow
def test_calibrate_command_refuses_a_net_that_finds_too_few_people(tmp_path: Path, capsys) -> None:
    weights = tmp_path / "tiny.pt"
    _tiny_checkpoint(weights, None)
    assert cli_main(["calibrate", "--weights", str(weights), "--out", str(tmp_path / "out.pt"), "--frames", "2",
                     "--no-progress"]) == 2
    assert "need at least 20 of each (more --frames)" in capsys.readouterr().err
    assert not (tmp_path / "out.pt").exists()


def test_calibrate_command_refuses_bad_arguments(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as stopped:  # argparse refuses it before the checkpoint loads
        cli_main(["calibrate", "--weights", "builtin:sim-rover", "--out", str(tmp_path / "o.pt"), "--seed", "-3"])
    assert stopped.value.code == 2
    assert "argument --seed: expected an integer >= 0, got '-3'" in capsys.readouterr().err
    weights = tmp_path / "folder.pt"
    checkpoint.save(weights, FusionNet(TINY), {"data": "/data/llvip"})
    assert cli_main(["calibrate", "--weights", str(weights), "--out", str(tmp_path / "o.pt")]) == 2
    assert "needs a checkpoint trained with --data sim" in capsys.readouterr().err
