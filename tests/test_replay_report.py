"""Replay report arithmetic: matching against ground truth at the native resolution, energy
from the power model, the latency model fitted from a log, and report merging."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from respecd.clock import ManualClock
from respecd.messages import Bundle, Detection, Frame, Health, Percept, SensorConfig, SyncStats
from respecd.record.config import RecordingConfig
from respecd.record.reader import open_log
from respecd.record.recorder import Recorder
from respecd.replay import report_out
from respecd.replay.latency import LatencyModel
from respecd.replay.report import Collector, Reference, energy, match, summarize
from respecd.sensors import SensorPower

SYNC = SyncStats(30.0, 0.0, 0.0, Health.GOOD)


def _percept(t: float, size: tuple[int, int], gt: list, boxes: list, conf: float = 0.9) -> Percept:
    rgb = Frame("rgb", t, 0, np.zeros((size[1], size[0], 3), np.uint8), {"gt": gt})
    detections = tuple(Detection(tuple(b), conf) for b in boxes)
    return Percept(t, detections, conf if boxes else 0.0, None, 0.01, Bundle(t, {"rgb": rgb}, SYNC))


def test_match_counts_each_reference_once() -> None:
    reference = np.array([[0, 0, 10, 10], [20, 20, 30, 30]], float)
    detected = np.array([[0, 0, 10, 10], [1, 1, 10, 10], [50, 50, 60, 60]], float)
    assert match(detected, reference) == (1, 2, 1)
    assert match(np.zeros((0, 4)), reference) == (0, 0, 2)
    hidden = np.array([[50, 50, 60, 60]], float)  # mostly occluded: finding it is not a false positive
    assert match(detected, reference, hidden) == (1, 1, 1)


def test_collector_scores_in_native_pixels_whatever_the_replayed_resolution() -> None:
    collector = Collector(Reference("ground_truth"), native_rgb=(1280, 720))
    person = {"box": [100.0, 100.0, 200.0, 300.0], "visible": 1.0}
    collector.on_percept(_percept(0.0, (1280, 720), [person], [[100, 100, 200, 300]]))
    half = {"box": [50.0, 50.0, 100.0, 150.0]}  # the same person in a 640x360 counterfactual frame
    collector.on_percept(_percept(0.1, (640, 360), [half], [[50, 50, 100, 150], [300, 10, 320, 40]]))
    collector.on_percept(_percept(0.2, (640, 360), [half], []))
    occluded = {"box": [300.0, 10.0, 320.0, 40.0], "visible": 0.1}
    collector.on_percept(_percept(0.3, (640, 360), [occluded], [[300, 10, 320, 40]]))  # neither TP nor FP
    collector.on_percept(_percept(0.4, (640, 360), [occluded], []))  # nor FN
    assert (collector.tp, collector.fp, collector.fn) == (2, 1, 1)
    entry = summarize(collector, 0.0, 1.0, {})
    assert entry["quality"]["precision"] == pytest.approx(2 / 3, abs=1e-4)
    assert entry["quality"]["recall"] == pytest.approx(2 / 3, abs=1e-4)


def test_energy_integrates_the_applied_configuration() -> None:
    power = {"cam": SensorPower(static_w=1.0, per_hz_w={"640x360": 0.01})}
    configs = [
        (float("-inf"), "cam", SensorConfig("rgb", True, 30.0, (640, 360))),  # 1.3 W from the start
        (4.0, "cam", SensorConfig("rgb", True, 10.0, (640, 360))),  # 1.1 W
        (8.0, "cam", SensorConfig("rgb", False, 10.0, (640, 360))),  # off
    ]
    result = energy(configs, power, 0.0, 10.0)
    assert result["sensor_j"]["cam"] == pytest.approx(4 * 1.3 + 4 * 1.1)
    assert result["mean_w"] == pytest.approx((4 * 1.3 + 4 * 1.1) / 10)


async def test_latency_model_is_fitted_from_the_logged_percepts(tmp_path: Path) -> None:
    clock = ManualClock()
    recorder = Recorder(RecordingConfig(path=str(tmp_path / "p.mcap")), {"name": "rig", "sensors": []}, clock)
    recorder.start()
    for i in range(10):
        p = _percept(i / 10, (640, 360), [], [])
        latency = 0.046 if i % 5 else 0.138  # every 5th percept carried an attribution
        recorder.on_percept(Percept(p.t, (), 0.0, {"rgb": 1.0} if i % 5 == 0 else None, latency, p.bundle))
    await recorder.close()
    model = LatencyModel.from_log(open_log(recorder.paths[0]))
    assert model.source == "log"
    replayed = _percept(0.0, (1280, 720), [], [])  # a counterfactual at 4x the pixels
    assert model.latency(replayed) == pytest.approx(4 * 0.046)
    attributed = Percept(0.0, (), 0.0, {"rgb": 1.0}, 0.0, replayed.bundle)
    assert model.latency(attributed) == pytest.approx(4 * 0.138)


def test_reports_merge_per_policy_only_for_the_same_log(tmp_path: Path) -> None:
    path = tmp_path / "r.json"
    log_a, log_b = {"path": "/a.mcap", "bytes": 1, "start_ns": 5}, {"path": "/b.mcap", "bytes": 1, "start_ns": 5}
    path.write_text(json.dumps(report_out.merge(path, log_a, "static", {"x": 1})))
    merged = report_out.merge(path, log_a, "heuristic", {"x": 2})
    assert list(merged["policies"]) == ["static", "heuristic"]
    path.write_text(json.dumps(merged))
    assert list(report_out.merge(path, log_b, "learn", {"x": 3})["policies"]) == ["learn"]


def _long_learning_report() -> dict:
    """Three policies over 60 s, the learner trying a new action at nearly every decision."""
    rng = np.random.default_rng(7)
    choices = {"rgb": ["1280x720", "960x540", "640x360"], "thermal": ["160x120", "320x240"],
               "radar": ["range", "velocity"], "depth": ["640x480", "424x240"]}
    policies = {}
    for policy, moves in (("static", 0), ("heuristic", 6), ("learn", 60)):
        configs, decisions = [], []
        for k in range(max(moves, 1)):
            t = k * 60 / max(moves, 1)
            pick = {s: (str(rng.choice(v)), float(rng.choice([1, 5, 9.4, 15, 30]))) for s, v in choices.items()}
            configs += [{"t": t, "sensor": s, "enabled": True, "rate_hz": r, "setting": v}
                        for s, (v, r) in pick.items()]
            name = " ".join(f"{s} {v}@{r:g}Hz" for s, (v, r) in pick.items())
            decisions.append({"t": t, "state": [0], "action": k, "action_name": name, "reward": 0.0})
        timeline = [{"t": t, "conf_agg": 0.5, "latency_ms": 90.0, "contributions": {"rgb": 0.6, "thermal": 0.4}}
                    for t in np.arange(0, 60, 0.5)]
        policies[policy] = {"decisions": decisions, "configs": configs, "timeline": timeline, "replayed_s": 60.0}
    return {"log": {"path": "/x/rover.mcap"}, "policies": policies}


@pytest.mark.slow
def test_the_figures_action_panel_has_no_overlapping_labels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """What a person reads in the action panel (its y labels and the labels in it) never overlaps."""
    plt = pytest.importorskip("matplotlib.pyplot")
    drawn = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: drawn.append(fig))
    report_out.write(tmp_path / "r.json", _long_learning_report())
    fig, = drawn
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    panel = fig.axes[0]
    labels = [t for t in (*panel.get_yticklabels(), *panel.texts) if t.get_visible() and t.get_text()]
    boxes = [t.get_window_extent(renderer) for t in labels]
    overlaps = [(labels[i].get_text(), labels[j].get_text()) for i in range(len(boxes))
                for j in range(i + 1, len(boxes)) if boxes[i].overlaps(boxes[j])]
    close(fig)
    assert len(labels) > 15 and not overlaps, overlaps[:3]
    assert (tmp_path / "r.png").stat().st_size > 20_000
