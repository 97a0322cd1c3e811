"""One accelerator in the experiment, as in the daemon: a single server behind a drop-oldest queue."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest
import yaml

from respecd.config import load_profile
from respecd.lab.experiment.accelerator import Accelerator
from respecd.lab.experiment.latency import Latency
from respecd.lab.experiment.rollout import Piece, Rollout, controller_for
from respecd.lab.experiment.setup import load_detector, make_evaluator
from respecd.messages import SensorConfig

RES = (640, 360)
TINY_MODEL = {"rgb_widths": [4, 8, 8, 16, 16], "aux_widths": [4, 8, 8, 16, 16], "neck_widths": [8, 16, 16],
              "reg_max": 4}


def _accelerator(forward_s: float, attribution_s: float | None = None, queue: int = 2) -> Accelerator:
    return Accelerator({RES: Latency(forward_s, attribution_s or forward_s)}, ("rgb", "radar"), queue)


def _configs(rgb_hz: float, radar_hz: float = 1.0) -> dict[str, SensorConfig]:
    return {"rgb": SensorConfig("rgb", rate_hz=rgb_hz, resolution=RES),
            "radar": SensorConfig("radar", rate_hz=radar_hz, mode="range"),
            "depth": SensorConfig("depth", rate_hz=30.0, resolution=(640, 480))}


def test_an_overloaded_accelerator_drops_bundles_and_saturates_at_one() -> None:
    acc = _accelerator(0.1)  # 10 inferences a second at most, 30 new RGB frames a second
    acc.configure(0.0, "piece", 0.0, _configs(30.0), [30.0, 1.0, 30.0])
    loads = [acc.close_window(t, 1.0) for t in (1.0, 2.0, 3.0)]
    assert all(w.busy == pytest.approx(1.0) for w in loads[1:])  # busy all the time, never above one
    assert all(w.dropped >= 18 for w in loads[1:])  # the queue (2) overflows: what cannot run is dropped
    assert all(w.inferences in (9, 10, 11) for w in loads[1:])


def test_a_light_configuration_keeps_the_accelerator_partly_idle() -> None:
    acc = _accelerator(0.01, 0.03)
    acc.configure(0.0, "piece", 0.0, _configs(5.0), [5.0, 1.0, 30.0])
    first = acc.close_window(1.0, 1.0)
    # 5 new RGB frames (ticks at 30 Hz carry the IMU/depth's, not the detector's): 5 inferences, one attributed
    assert first.inferences == 5 and first.dropped == 0
    assert first.busy == pytest.approx(4 * 0.01 + 0.03)
    acc.request_attribution()
    second = acc.close_window(2.0, 1.0)
    assert second.busy == pytest.approx(4 * 0.01 + 0.03) and acc.skipped > 0  # repeated inputs skipped


def test_the_radar_alone_sets_the_detector_rate_when_it_is_the_fastest_input() -> None:
    acc = _accelerator(0.01)
    acc.configure(0.0, "piece", 0.0, _configs(1.0, 15.0), [1.0, 15.0, 30.0])
    assert acc.close_window(1.0, 1.0).inferences == 15


def test_the_delivered_percept_is_the_last_finished_one_and_stale() -> None:
    acc = _accelerator(0.25)  # four inferences a second on a 30 Hz camera
    acc.configure(0.0, "piece", 0.0, _configs(30.0), [30.0, 1.0, 30.0])
    acc.advance(0.2)
    assert acc.delivered is None  # the first inference is still running: nothing to hand on yet
    acc.advance(1.6)
    done = acc.delivered
    assert done is not None and done.end <= 1.6 < done.end + 0.25
    assert 1.6 - done.bundle.t > 0.25  # what the daemon shows at 1.6 s was sensed more than a latency ago
    assert [i.attributed for i in acc.take_attributed()] == [True] and acc.take_attributed() == []


def test_a_rollout_on_an_overloaded_accelerator_reports_drops_and_full_load(tmp_path: Path) -> None:
    doc = yaml.safe_load((resources.files("respecd.profiles") / "sim-rover.yaml").read_text())
    doc["perception"] = {"model": TINY_MODEL, "torch_threads": 1}
    doc["controller"] = {"min_dwell_s": 0, "actions": {"rgb_resolutions": [list(RES)], "rate_levels_hz": [1, 10, 30]}}
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(doc))
    profile = load_profile(tmp_path / "p.yaml")
    evaluator = make_evaluator(load_detector(profile, random_init=True), profile, use_cache=False)
    pieces = [Piece("good-light-moving", 0, 3.0)]
    slow = Rollout(profile, evaluator, {RES: Latency(0.08, 0.2)}).run(controller_for(profile, "static"), pieces)
    fast = Rollout(profile, evaluator, {RES: Latency(0.005, 0.01)}).run(controller_for(profile, "static"), pieces)
    for record in slow[1:]:
        assert record.load.busy == pytest.approx(1.0) and record.load.dropped > 0
        assert record.compute_ms > 1000  # what static asks for: more than one accelerator has
        assert record.decision.terms["power_w"] == pytest.approx(
            record.energy_j - record.accelerator_j + profile.controller.reward.compute_w * 1.0, rel=1e-6)
    for record in fast[1:]:
        assert 0.1 < record.load.busy < 0.3 and record.load.dropped == 0
    assert slow[-1].decision.state != fast[-1].decision.state  # the load factor sees the difference
