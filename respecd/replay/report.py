"""What a replay measured, per policy: detection quality against a reference, compute spent,
estimated sensor energy, and the actions over time — as JSON, a PNG timeline and a table.

Reference detections are the log's ground truth when its RGB frames carry ``meta["gt"]``
(the simulated rover's do), otherwise the detections the log recorded at full fidelity; a log
with neither (a foreign bag) has no quality figures (None, "no ground truth"), never a 0.
Quality is matched per percept at IoU >= 0.5 (greedy by confidence), in the pixel frame of
the logged (native) RGB resolution.
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from respecd.messages import Bundle, Decision, Frame, Percept, SensorConfig

IOU_MATCH = 0.5
MIN_VISIBLE = 0.3  # as respecd.lab.detector.data: a person less visible than this is "ignore" truth
REFERENCE_MAX_AGE_S = 0.2  # a reference older than this at a percept's time is not used


def boxes_of(value: Any) -> np.ndarray:
    """(N, 4) x1, y1, x2, y2 from ground truth or detections in any of the usual shapes."""
    if value is None:
        return np.zeros((0, 4))
    if isinstance(value, dict):
        value = value.get("boxes", value.get("box", []))
    rows = []
    for item in value:
        if isinstance(item, dict):
            item = item.get("box", item.get("bbox"))
        if item is not None and len(item) >= 4:
            rows.append([float(x) for x in list(item)[:4]])
    return np.asarray(rows, dtype=np.float64).reshape(-1, 4)


def split_truth(value: Any) -> tuple[np.ndarray, np.ndarray]:
    """(boxes to find, boxes to ignore): the simulator's mostly hidden people are neither
    required nor false positives when found (the detector's own evaluation rule)."""
    if not isinstance(value, (list, tuple)):
        return boxes_of(value), np.zeros((0, 4))
    hidden = [g for g in value if isinstance(g, dict) and float(g.get("visible", 1.0)) < MIN_VISIBLE]
    shown = [g for g in value if not (isinstance(g, dict) and float(g.get("visible", 1.0)) < MIN_VISIBLE)]
    return boxes_of(shown), boxes_of(hidden)


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of (N, 4) and (M, 4) boxes -> (N, M)."""
    x1 = np.maximum(a[:, None, 0], b[None, :, 0])
    y1 = np.maximum(a[:, None, 1], b[None, :, 1])
    x2 = np.minimum(a[:, None, 2], b[None, :, 2])
    y2 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def match(detected: np.ndarray, reference: np.ndarray, ignore: np.ndarray | None = None) -> tuple[int, int, int]:
    """(true positives, false positives, false negatives); ``detected`` sorted best first.

    Detections of an ``ignore`` box (IoU >= 0.5) that match nothing else do not count.
    """
    if ignore is not None and len(ignore) and len(detected):
        if len(reference):
            best = iou(detected, reference).max(axis=1)
            keep = (best >= IOU_MATCH) | (iou(detected, ignore).max(axis=1) < IOU_MATCH)
        else:
            keep = iou(detected, ignore).max(axis=1) < IOU_MATCH
        detected = detected[keep]
    if len(detected) == 0 or len(reference) == 0:
        return 0, len(detected), len(reference)
    overlaps = iou(detected, reference)
    taken = np.zeros(len(reference), dtype=bool)
    tp = 0
    for row in overlaps:
        row = np.where(taken, -1.0, row)
        j = int(np.argmax(row))
        if row[j] >= IOU_MATCH:
            taken[j] = True
            tp += 1
    return tp, len(detected) - tp, len(reference) - tp


@dataclass
class Reference:
    """Reference boxes over time, at the log's native RGB resolution."""

    kind: str  # "ground_truth" | "log_detections" | "none"
    times: list[float] = field(default_factory=list)
    boxes: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (to find, to ignore)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        i = bisect.bisect_right(self.times, t + 1e-9) - 1
        if i < 0 or t - self.times[i] > REFERENCE_MAX_AGE_S:
            return None
        return self.boxes[i]


def build_reference(truth: list[tuple[float, Any]], percepts: list[dict[str, Any]]) -> Reference:
    """Ground truth from the RGB frames' meta when the log has it, else the logged detections."""
    if truth:
        return Reference("ground_truth", [t for t, _ in truth], [split_truth(gt) for _, gt in truth])
    if percepts:
        return Reference(
            "log_detections",
            [float(p["t"]) for p in percepts],
            [(boxes_of(p.get("detections")), np.zeros((0, 4))) for p in percepts],
        )
    return Reference("none")


def image_pixels(frames: Iterable[Frame]) -> int:
    return int(sum(f.shape[0] * f.shape[1] for f in frames if len(f.shape) >= 2))


class Collector:
    """A session observer gathering what the report needs (O(1) per call, on the loop)."""

    def __init__(self, reference: Reference, native_rgb: tuple[int, int] | None) -> None:
        self.reference = reference
        self.native_rgb = native_rgb
        self.tp = self.fp = self.fn = 0
        self.percepts = 0
        self.attributions = 0
        self.latency_s = 0.0  # measured inference (+ attribution) time
        self.pixels = 0
        self.frames: Counter[str] = Counter()
        self.configs: list[tuple[float, str, SensorConfig]] = []
        self.decisions: list[Decision] = []
        self.timeline: list[dict[str, Any]] = []
        self.first_t: float | None = None
        self.last_t: float | None = None
        self._ticked = False
        self._current: dict[str, SensorConfig] = {}
        self._changed: dict[str, SensorConfig] = {}  # config messages since the last tick

    def start(self) -> None:
        """Nothing to open: everything is gathered in memory."""

    def close(self) -> None:
        """Nothing to close: the report is built from what was gathered."""

    def on_frame(self, sensor_name: str, frame: Frame) -> None:
        self.frames[sensor_name] += 1
        self.first_t = frame.t if self.first_t is None else min(self.first_t, frame.t)
        self.last_t = frame.t if self.last_t is None else max(self.last_t, frame.t)

    def on_bundle(self, bundle: Bundle) -> None:
        """Configuration changes count from the tick that first runs under them."""
        self._ticked = True
        for name, applied in self._changed.items():
            if self._current.get(name) != applied:
                self._current[name] = applied
                self.configs.append((bundle.t, name, applied))
        self._changed.clear()

    def on_config(self, sensor_name: str, applied: SensorConfig) -> None:
        if not self._ticked:  # the start configuration
            self._current[sensor_name] = applied
            self.configs.append((float("-inf"), sensor_name, applied))
        else:
            self._changed[sensor_name] = applied

    def on_decision(self, decision: Decision) -> None:
        self.decisions.append(decision)

    def measured(self, percept: Percept) -> None:
        """The percept as perception produced it (real latency), before any latency model."""
        self.latency_s += percept.latency
        self.percepts += 1
        self.attributions += percept.contributions is not None
        if percept.bundle is not None:
            self.pixels += image_pixels(percept.bundle.frames.values())

    def on_percept(self, percept: Percept) -> None:
        self._score(percept)
        self.timeline.append({
            "t": round(percept.t, 4),
            "conf_agg": round(percept.conf_agg, 4),
            "latency_ms": round(percept.latency * 1000, 2),
            "contributions": {k: round(v, 4) for k, v in (percept.contributions or {}).items()},
        })

    def _score(self, percept: Percept) -> None:
        frames = percept.bundle.frames if percept.bundle is not None else {}
        rgb = frames.get("rgb")
        scale = self._scale(rgb)
        detected = boxes_of([d.box for d in sorted(percept.detections, key=lambda d: -d.confidence)]) * scale
        if rgb is not None and "gt" in rgb.meta and self.reference.kind == "ground_truth":
            find, hidden = split_truth(rgb.meta["gt"])  # the frame's own truth, resized with it
            reference: tuple[np.ndarray, np.ndarray] | None = (find * scale, hidden * scale)
        else:
            reference = self.reference.at(percept.t)
        if reference is None:
            return
        tp, fp, fn = match(detected, *reference)
        self.tp, self.fp, self.fn = self.tp + tp, self.fp + fp, self.fn + fn

    def _scale(self, rgb: Frame | None) -> np.ndarray:
        """Factor from the bundle's RGB pixels to the native (logged) RGB pixels."""
        if rgb is None or self.native_rgb is None or len(rgb.shape) < 2:
            return np.ones(4)
        sx = self.native_rgb[0] / rgb.shape[1]
        sy = self.native_rgb[1] / rgb.shape[0]
        return np.array([sx, sy, sx, sy])


def energy(configs: Sequence[tuple[float, str, SensorConfig]], power: dict[str, Any], t0: float, t1: float) -> dict:
    """Joules per sensor from the power model, integrating the applied config over time."""
    joules: dict[str, float] = {}
    by_sensor: dict[str, list[tuple[float, SensorConfig]]] = {}
    for t, name, cfg in configs:
        by_sensor.setdefault(name, []).append((max(t, t0), cfg))
    for name, changes in by_sensor.items():
        model = power.get(name)
        if model is None:
            continue
        total = 0.0
        for i, (t, cfg) in enumerate(changes):
            end = changes[i + 1][0] if i + 1 < len(changes) else t1
            total += model.watts(cfg) * max(0.0, min(end, t1) - t)
        joules[name] = round(total, 3)
    span = max(t1 - t0, 1e-9)
    total = sum(joules.values())
    return {"sensor_j": joules, "total_j": round(total, 3), "mean_w": round(total / span, 3)}


def matched(c: Collector) -> dict[str, Any]:
    """Precision, recall and F1 against the reference; None where the log has none to score
    against (a foreign bag without ground truth): a 0.000 there would read as a result."""
    if c.reference.kind == "none":
        return {"precision": None, "recall": None, "f1": None, "tp": None, "fp": None, "fn": None,
                "note": "no ground truth"}
    precision = c.tp / (c.tp + c.fp) if c.tp + c.fp else 0.0
    recall = c.tp / (c.tp + c.fn) if c.tp + c.fn else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": round(precision, 4), "recall": round(recall, 4), "f1": round(f1, 4),
            "tp": c.tp, "fp": c.fp, "fn": c.fn}


def summarize(c: Collector, t0: float, t1: float, power: dict[str, Any], describe: Any = None) -> dict[str, Any]:
    """One policy's entry of the report (plain JSON types)."""
    span = max(t1 - t0, 1e-9)
    actions = Counter(d.action for d in c.decisions)
    switches = sum(1 for a, b in zip(c.decisions, c.decisions[1:], strict=False) if a.action != b.action)
    conf = [p["conf_agg"] for p in c.timeline]
    return {
        "replayed_s": round(span, 3),
        "reference": c.reference.kind,
        "quality": {**matched(c), "mean_conf_agg": round(float(np.mean(conf)), 4) if conf else 0.0},
        "compute": {
            "percepts": c.percepts,
            "attributions": c.attributions,
            "inference_ms_per_s": round(1000 * c.latency_s / span, 2),
            "mean_latency_ms": round(1000 * c.latency_s / c.percepts, 2) if c.percepts else 0.0,
            "pixels_per_s": round(c.pixels / span),
            "frames": dict(c.frames),
        },
        "energy": energy(c.configs, power, t0, t1),
        "actions": {
            "counts": {str(describe(a) if describe else a): n for a, n in sorted(actions.items())},
            "switches": switches,
        },
        "decisions": [
            {"t": round(d.t, 4), "state": list(d.state), "action": d.action,
             "action_name": str(describe(d.action)) if describe else None, "reward": round(d.reward, 6)}
            for d in c.decisions
        ],
        "configs": [
            {"t": round(max(t, t0), 4), "sensor": n, "enabled": cfg.enabled, "rate_hz": cfg.rate_hz,
             "setting": f"{cfg.resolution[0]}x{cfg.resolution[1]}" if cfg.resolution else cfg.mode}
            for t, n, cfg in c.configs
        ],
        "timeline": c.timeline,
    }
