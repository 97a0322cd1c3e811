"""A controller driven through scenario segments, one decision window at a time.

This is the daemon's control loop without asyncio or wall-clock waits, built from the same
pieces: the profile's ``Controller`` (state bins, reward, Q-table, baselines, dwell time),
the daemon's ``Window`` of per-percept samples, the detector's decaying scene score, and
the simulated sensors' clamping. Per decision window (``decision_period_s``):

1. ``samples_per_s`` scene instants at seeded random offsets inside the window (the same
   instants for every policy, so the comparison is paired); at each, the detector's
   outcome on the frames the current configuration delivers (cached, see ``outcomes.py``);
   the first instant of the window is attributed, as the daemon attributes once per decision;
2. the window's observation -> ``Controller.step`` -> the new configuration is applied; the
   observation's detector busy share is the window's modelled compute (step 3), since the
   window holds only the scored instants, not every inference;
3. the window's figures under the configuration that was active during it: detections vs
   ground truth at the instant (a stale frame scores worse on a moving target), compute
   (measured forward time x inference rate + attribution once per window), energy from the
   profile's power model, and sensing bandwidth.

The detector runs once per new detector input, so its rate is the fastest detector-input
sensor (RGB, thermal, radar; depth when the network reads it), capped by ``sync.max_rate_hz``.
Load is the larger of the detector's busy share (what the Jetson's GPU probe reads; capped at
1) and latency / ``latency_budget_s``, with the latency the daemon's window would average:
the window's detector time over its inferences, most plain forward passes, one attributed.
The host's CPU is not probed (``system_probe`` off, as for deterministic replay).
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from respecd.control.actions import Position
from respecd.control.controller import Controller
from respecd.control.features import Sample, Window
from respecd.lab.detector.metrics import ImageResult
from respecd.lab.experiment.frames import frame_bytes
from respecd.lab.experiment.latency import Latency
from respecd.lab.experiment.outcomes import Evaluator
from respecd.messages import Decision, SensorConfig
from respecd.perception.attribution import SceneScores
from respecd.sensors import clamp_request
from respecd.sim.world import World


@dataclass(frozen=True)
class Piece:
    """One run of one scenario: which, with which world seed, for how long (and, on a
    recorded log, from which second of the log)."""

    scenario: str
    seed: int
    duration_s: float
    start_s: float = 0.0


@dataclass
class WindowRecord:
    """One decision window: what ran, what it cost, what it saw."""

    scenario: str
    t: float  # end of the window, seconds since the rollout began
    position: Position  # the configuration active during the window
    decision: Decision  # the step taken at the end of the window
    compute_ms: float  # inference wall time spent per second in this window
    energy_j: float
    bandwidth_bps: float
    images: list[ImageResult] = field(default_factory=list)


class _PieceRun:
    """One piece inside a rollout: its world, time offset, sample instants and shared state."""

    def __init__(self, piece: Piece, world: Any, offset: float, static: bool, window: Window,
                 scores: SceneScores) -> None:
        self.world, self.offset, self.static = world, offset, static
        self.window, self.scores = window, scores
        # the same instants for every policy: seeded by the piece, not by the run
        self.rng = np.random.default_rng([piece.seed, zlib.crc32(piece.scenario.encode()), 5])


def controller_for(profile: Any, policy: str) -> Controller:
    """The controller the daemon would build for ``profile`` over simulated sensors."""
    from respecd.drivers.sim import CAPABILITIES

    caps = {s.name: CAPABILITIES[s.modality] for s in profile.sensors if s.driver == "sim"}
    config = profile.controller.model_copy(update={"policy": policy, "system_probe": False})
    return Controller.from_profile(config, profile, caps)


class Rollout:
    """Runs a controller over pieces on cached detector outcomes."""

    def __init__(self, profile: Any, evaluator: Evaluator, latency: dict[tuple[int, int], Latency],
                 samples_per_s: float = 1.0) -> None:
        from respecd.drivers.sim import CAPABILITIES

        self.profile = profile
        self.evaluator = evaluator
        self.latency = latency
        self.period = profile.controller.decision_period_s
        self.samples = max(1, int(round(samples_per_s * self.period)))
        self.sensors = [s for s in profile.sensors if s.enabled]
        self.caps = {s.name: CAPABILITIES[s.modality] for s in self.sensors if s.driver == "sim"}
        self.powers = {s.name: s.power for s in self.sensors}

    def world(self, piece: Piece) -> World:
        return self.evaluator.world(piece, self.profile.simulation)

    def initial(self) -> dict[str, SensorConfig]:
        return {s.name: clamp_request(self.caps[s.name], s.initial_request()) if s.name in self.caps
                else s.initial_request() for s in self.sensors}

    def run(self, controller: Controller, pieces: Iterable[Piece],
            on_window: Callable[[WindowRecord], None] | None = None) -> list[WindowRecord]:
        cfg = controller.config
        window = Window(cfg.window_s, cfg.latency_budget_s)
        det = self.evaluator.detector
        scores = SceneScores(det.channels, det.config.attribution_decay_s)
        applied = self.initial()
        controller.position = controller.space.nearest(applied)
        # the sensors start at that position (the daemon gets there at its first decision)
        applied = self._configure(applied, controller, controller.space.requests(controller.position))
        records: list[WindowRecord] = []
        offset = 0.0
        for piece in pieces:
            run = _PieceRun(piece, self.world(piece), offset, self.evaluator.static(piece), window, scores)
            steps = max(1, int(round(piece.duration_s / self.period)))
            for k in range(steps):
                images, points = self._observe(run, k, self._by_modality(applied))
                now = offset + (k + 1) * self.period
                position = controller.position
                # the window holds only the scored instants: the detector's busy share comes from its
                # real rate, and is the load a GPU probe would read (capped at one accelerator)
                busy = self.compute_s(applied) / self.period
                obs = replace(window.observe(now, gpu=min(busy, 1.0)), busy=busy)
                decision = controller.step(obs, applied)
                records.append(self._record(piece.scenario, now, position, decision, applied, images, points))
                applied = self._configure(applied, controller, decision.configs)
                if on_window is not None:
                    on_window(records[-1])
            offset += steps * self.period
        return records

    def _observe(self, run: _PieceRun, k: int, configs: dict[str, SensorConfig]) -> tuple[list[ImageResult], float]:
        """The samples of window ``k`` into the controller's window; images and mean radar points."""
        offsets = (np.arange(self.samples) + run.rng.uniform(0.02, 0.98, self.samples)) / self.samples
        images, points = [], []
        for j, u in enumerate(offsets):
            slot = k * self.samples + j if run.static else None
            image, n_points = self._sample(run, configs, (k + u) * self.period, j == 0, slot)
            images.append(image)
            points.append(n_points or 0.0)
        return images, float(np.mean(points))

    def _by_modality(self, applied: dict[str, SensorConfig]) -> dict[str, SensorConfig]:
        out: dict[str, SensorConfig] = {}
        for s in self.sensors:
            out.setdefault(s.modality, applied[s.name])
        return out

    def _sample(self, run: _PieceRun, configs: dict[str, SensorConfig], t: float, attribute: bool,
                slot: int | None) -> tuple[ImageResult, float | None]:
        world, offset = run.world, run.offset
        out = self.evaluator.outcome(world, configs, t, attribute, slot)
        contributions = run.scores.update(offset + t, out.contributions) if attribute else None
        res = configs["rgb"].resolution
        imu = self.evaluator.imu(world, t)
        run.window.add(Sample(offset + t, out.conf_agg, self.mean_latency_s(configs),
                          out.luminance, out.motion, float(np.linalg.norm(imu[3:6])), out.radar_points, 0,
                          contributions))
        boxes, ignore = self.evaluator.truth(world, t, res)
        return ImageResult(out.boxes, out.scores, boxes, ignore), out.radar_points

    def detector_rate(self, configs: dict[str, SensorConfig]) -> float:
        rates = [c.rate_hz for m, c in configs.items() if m in self.evaluator.inputs and c.enabled]
        sync = self.profile.sync
        return min(max(max(rates, default=sync.min_rate_hz), sync.min_rate_hz), sync.max_rate_hz)

    def _record(self, scenario: str, now: float, position: Position, decision: Decision,
                applied: dict[str, SensorConfig], images: list[ImageResult], points: float) -> WindowRecord:
        compute_s = self.compute_s(applied)
        energy = sum(self.powers[n].watts(c) for n, c in applied.items()) * self.period
        bandwidth = sum(frame_bytes(c, points) * c.rate_hz for c in applied.values() if c.enabled)
        return WindowRecord(scenario, now, position, decision, 1000.0 * compute_s / self.period, energy, bandwidth,
                            images)

    def compute_s(self, applied: dict[str, SensorConfig]) -> float:
        """Detector seconds in one decision window under ``applied``: a forward pass per new
        input frame, and one of them attributed (its extra time added once)."""
        return self._window_compute(self._by_modality(applied))[0]

    def mean_latency_s(self, by_modality: dict[str, SensorConfig]) -> float:
        """The mean perception latency the daemon's window would hold: the window's detector
        time over its inferences (most plain, one attributed)."""
        compute_s, inferences = self._window_compute(by_modality)
        return compute_s / inferences

    def _window_compute(self, by_modality: dict[str, SensorConfig]) -> tuple[float, float]:
        lat = self.latency[by_modality["rgb"].resolution]
        inferences = max(self.detector_rate(by_modality) * self.period, 1.0)
        return lat.forward_s * inferences + (lat.attribution_s - lat.forward_s), inferences

    def _configure(self, applied: dict[str, SensorConfig], controller: Controller,
                   requests: tuple[SensorConfig, ...]) -> dict[str, SensorConfig]:
        """What the simulated drivers answer to the requests (they clamp, like their apply())."""
        out = dict(applied)
        for slot, request in zip(controller.space.slots, requests, strict=True):
            result = clamp_request(self.caps[slot.name], request) if slot.name in self.caps else request
            if result != applied.get(slot.name):
                out[slot.name] = result
        return out
