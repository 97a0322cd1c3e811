"""The shipped checkpoint: loads from package data, matches its card, detects on simulated scenes
(by day even with every non-RGB sensor off, at night through thermal), and the inference bench."""

from __future__ import annotations

import argparse
import json
from importlib import resources

import numpy as np
import pytest

from respecd.lab.detector.metrics import iou_matrix
from respecd.messages import Frame
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def detector() -> FusionDetector:
    return FusionDetector.load(PerceptionConfig())


def _scene(scenario: str, seed: int, with_aux: bool) -> tuple[dict[str, Frame], np.ndarray]:
    from respecd.sim.render import ground_truth, render_radar, render_rgb, render_thermal
    from respecd.sim.world import SimulationConfig, World

    state = World(SimulationConfig(scenarios=[scenario]), seed).state_at(12.0)
    rng = np.random.default_rng(seed)
    data = {"rgb": render_rgb(state, (640, 360), 1 / 30, rng)}
    if with_aux:
        data["thermal"] = render_thermal(state, (160, 120), rng)
        data["radar"] = render_radar(state, "range", 10.0, rng)
    frames = {k: Frame(k, state.t, 0, v) for k, v in data.items()}  # type: ignore[arg-type]
    boxes = np.array([g["box"] for g in ground_truth(state, (640, 360)) if g["visible"] > 0.5], np.float32)
    return frames, boxes.reshape(-1, 4)


def _found(percept, boxes: np.ndarray) -> int:
    pred = np.array([d.box for d in percept.detections], np.float32).reshape(-1, 4)
    return int((iou_matrix(boxes, pred) >= 0.5).any(1).sum()) if len(pred) else 0


def test_card_describes_the_shipped_checkpoint(detector: FusionDetector) -> None:
    card = json.loads((resources.files("respecd.perception") / "weights" / "sim-rover.json").read_text())
    assert card["channels"] == list(detector.channels) == ["r", "g", "b", "thermal", "radar"]
    assert card["parameters"] == detector.parameters  # as trained, before batch norms are folded
    assert ModelSpec.model_validate(card["spec"]) == PerceptionConfig().model  # fields added later: defaults


def test_detects_by_day_with_every_non_rgb_sensor_off(detector: FusionDetector) -> None:
    frames, boxes = _scene("good-light-static", 21, with_aux=False)
    percept = detector.infer(frames, attribute=True)
    assert len(boxes) and _found(percept, boxes) == len(boxes)
    assert percept.contributions["thermal"] == 0.0 and percept.contributions["radar"] == 0.0
    # RGB alone: all of it is lost with RGB off, and RGB alone keeps all of it (the one sensor on)
    assert percept.dependence["rgb"] == pytest.approx(1.0, abs=0.02) and percept.sufficiency["rgb"] == 1.0
    assert percept.dependence["thermal"] == percept.sufficiency["thermal"] == 0.0


def test_detects_at_night_and_thermal_carries_it(detector: FusionDetector) -> None:
    frames, boxes = _scene("poor-light-static", 22, with_aux=True)
    percept = detector.infer(frames, attribute=True)
    assert len(boxes) and _found(percept, boxes) == len(boxes)
    assert percept.contributions["thermal"] > percept.contributions["rgb"]
    assert percept.dependence["thermal"] > 10 * percept.dependence["rgb"]  # in the dark it leans on thermal
    assert percept.sufficiency is None  # three sensors on: each alone is a pass more, left out by default


@pytest.mark.slow
def test_inference_bench_reports_every_resolution(monkeypatch) -> None:
    from respecd.lab.bench import inference

    monkeypatch.setattr(inference, "RESOLUTIONS", ((640, 360),))  # one size keeps the test short
    args = argparse.Namespace(weights="builtin:sim-rover", repeats=1, threads=1, seed=1, runtime="torch")
    figures = inference.run(args)
    row = figures["resolutions"][0]
    assert row["rgb"] == "640x360" and row["forward_ms"] > 0 and row["attribution_ms"] > 0
    assert figures["model_params"] == 1_506_291
    torch_row = figures["runtimes"]["torch"]["640x360"]
    assert 0 < torch_row["forward_ms"] < torch_row["attributed_ms"]
    assert torch_row["to_limit"] == pytest.approx(torch_row["forward_ms"] / figures["limit_ms"]["640x360"], rel=0.02)
    assert figures["gflop"]["640x360"] == pytest.approx(3.06, abs=0.01)  # builtin:sim-rover's convolutions at 640x384
    assert figures["limit_ms"]["640x360"] == pytest.approx(3.06 / figures["peak_gflops"] * 1000, rel=0.01)
    # the cost of the attribution as a share of a forward, per variant; the default's is the row's own
    assert row["ratio"] == row["methods"]["ablation"]["ratio"] and row["cpu_ratio"] > 0
    assert set(row["methods"]) == {"ablation", "ablation+sufficiency", "gradient"}
    # three sensors on (RGB, thermal, radar): each off; with every sufficiency also each alone
    assert row["methods"]["ablation"]["fusion_passes"] == 3
    assert row["methods"]["ablation+sufficiency"]["fusion_passes"] == 6
