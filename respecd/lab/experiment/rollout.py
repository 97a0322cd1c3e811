"""A controller driven through scenario segments by the daemon's own control loop.

The rollout runs ``respecd.control.loop.ControlLoop`` — the loop the daemon and a replay
run — on a lockstep clock it controls, so a decision window costs no wall time. What differs
from the daemon is only what feeds the loop: samples come from the detector's cached
outcomes at a few scene instants per window instead of every percept, the system signal is
the modelled detector load (``ModelledLoad``), and decisions go to ``SimulatedSensors``,
which answer what the simulated drivers' ``apply`` would (they clamp). Per decision window
(``decision_period_s``):

1. ``samples_per_s`` scene instants at seeded random offsets inside the window (the same
   instants for every policy, so the comparison is paired); at each, the detector's
   outcome on the frames the current configuration delivers (cached, see ``outcomes.py``);
   the first instant after a decision is attributed, as the daemon's perception attributes
   the first bundle after the loop asks (once per decision);
2. at the window's end the loop decides and applies; the observation's detector busy share
   is the window's modelled compute (step 3), since the window holds only the scored
   instants, not every inference;
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

import asyncio
import zlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from respecd.applied import AppliedConfigs
from respecd.clock import Clock
from respecd.control.actions import Position
from respecd.control.bandwidth import sensing_bandwidth
from respecd.control.controller import Controller
from respecd.control.features import Sample
from respecd.control.loop import ControlLoop
from respecd.control.probe import SystemSample
from respecd.lab.detector.metrics import ImageResult
from respecd.lab.experiment.latency import Latency
from respecd.lab.experiment.outcomes import Evaluator
from respecd.messages import Decision, SensorConfig
from respecd.perception.attribution import SceneScores
from respecd.replay.lockstep import LockstepClock, LockstepLoop
from respecd.sensors import Capabilities, clamp_request
from respecd.sim.world import World

if TYPE_CHECKING:
    from respecd.config import Profile


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

    def __init__(self, piece: Piece, world: Any, offset: float, static: bool, loop: ControlLoop,
                 scores: SceneScores) -> None:
        self.world, self.offset, self.static = world, offset, static
        self.loop, self.scores = loop, scores
        # the same instants for every policy: seeded by the piece, not by the run
        self.rng = np.random.default_rng([piece.seed, zlib.crc32(piece.scenario.encode()), 5])


class SimulatedSensors:
    """The loop's ``Sensors`` for a trainer: what the simulated drivers' ``apply`` answers
    (a request clamped into their capabilities), without running them."""

    def __init__(self, capabilities: Mapping[str, Capabilities]) -> None:
        self.capabilities = capabilities

    async def apply(self, requests: Mapping[str, SensorConfig]) -> dict[str, SensorConfig | None]:
        return {name: clamp_request(self.capabilities[name], request) if name in self.capabilities else request
                for name, request in requests.items()}


class ModelledLoad:
    """The loop's ``LoadProbe`` for a trainer: the detector's busy share of a window at the
    running configuration, from its measured latency (what the Jetson's GPU probe reads,
    capped at one accelerator); the host's own CPU is not probed."""

    def __init__(self, rollout: Rollout, applied: Mapping[str, SensorConfig]) -> None:
        self.rollout = rollout
        self.applied = applied

    async def read(self) -> SystemSample:
        busy = self.rollout.compute_s(dict(self.applied)) / self.rollout.period
        return SystemSample(None, min(busy, 1.0), None, busy)


def controller_for(profile: Profile, policy: str) -> Controller:
    """The controller the daemon would build for ``profile`` over simulated sensors."""
    from respecd.drivers.sim import CAPABILITIES

    caps = {s.name: CAPABILITIES[s.modality] for s in profile.sensors if s.driver == "sim"}
    config = profile.controller.model_copy(update={"policy": policy, "system_probe": False})
    return Controller.from_profile(config, profile, caps)


class Rollout:
    """Runs a controller over pieces on cached detector outcomes."""

    def __init__(self, profile: Profile, evaluator: Evaluator, latency: dict[tuple[int, int], Latency],
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

    def starting(self, controller: Controller) -> dict[str, SensorConfig]:
        """The simulated sensors start at the action space's position nearest the profile's
        settings (a daemon gets there at its first decision): the latency table knows only
        the resolutions the controller can choose."""
        applied = self.initial()
        requests = controller.space.requests(controller.space.nearest(applied))
        for slot, request in zip(controller.space.slots, requests, strict=True):
            result = clamp_request(self.caps[slot.name], request) if slot.name in self.caps else request
            if result != applied.get(slot.name):
                applied[slot.name] = result
        return applied

    def run(self, controller: Controller, pieces: Iterable[Piece],
            on_window: Callable[[WindowRecord], None] | None = None,
            attach: Callable[[ControlLoop], None] | None = None) -> list[WindowRecord]:
        """Every piece in sequence under ``controller``; one record per decision window.
        ``attach`` sees the control loop before it runs (to observe its hooks)."""
        with asyncio.Runner(loop_factory=LockstepLoop) as runner:
            return runner.run(self._run(controller, list(pieces), on_window, attach))

    async def _run(self, controller: Controller, pieces: list[Piece], on_window: Callable[[WindowRecord], None] | None,
                   attach: Callable[[ControlLoop], None] | None) -> list[WindowRecord]:
        clock = LockstepClock(0.0)
        applied = AppliedConfigs(self.starting(controller))
        loop = ControlLoop(controller, clock, SimulatedSensors(self.caps), applied, ModelledLoad(self, applied))
        if attach is not None:
            attach(loop)
        feeder = _Feeder(self, loop, on_window)
        tasks = [asyncio.create_task(loop.run(), name="control-loop"),
                 asyncio.create_task(feeder.run(pieces), name="rollout-samples")]
        try:
            await clock.run(feeder.total_s(pieces))
            for task in tasks:
                if task.done():
                    task.result()  # a crash in either is the rollout's error
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        return feeder.records

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
        run.loop.add(Sample(offset + t, out.conf_agg, self.mean_latency_s(configs),
                            out.luminance, out.motion, float(np.linalg.norm(imu[3:6])), out.radar_points, 0,
                            contributions))
        assert res is not None, "the RGB camera always has a resolution"
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
        bandwidth = sensing_bandwidth(applied.values(), points)
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
        resolution = by_modality["rgb"].resolution
        assert resolution is not None, "the RGB camera always has a resolution"
        lat = self.latency[resolution]
        inferences = max(self.detector_rate(by_modality) * self.period, 1.0)
        return lat.forward_s * inferences + (lat.attribution_s - lat.forward_s), inferences


class _Feeder:
    """The rollout's percept source on the loop's clock: a window's samples at their
    instants, and its record once the loop has decided at the window's end."""

    def __init__(self, rollout: Rollout, loop: ControlLoop, on_window: Callable[[WindowRecord], None] | None) -> None:
        self.rollout = rollout
        self.loop = loop
        self.on_window = on_window
        self.records: list[WindowRecord] = []
        det = rollout.evaluator.detector
        self.scores = det.scene_scores()
        self._attribute = True  # the first window's first instant, as perception's first bundle
        self._window: tuple[str, Position, dict[str, SensorConfig], list[ImageResult], float] | None = None
        loop.on_window.append(self._attribute_next)
        loop.on_decision.append(self._decided)

    def total_s(self, pieces: list[Piece]) -> float:
        return sum(self.steps(p) for p in pieces) * self.rollout.period

    def steps(self, piece: Piece) -> int:
        return max(1, int(round(piece.duration_s / self.rollout.period)))

    async def run(self, pieces: list[Piece]) -> None:
        rollout, clock, period = self.rollout, self.loop.clock, self.rollout.period
        offset = 0.0
        for piece in pieces:
            run = _PieceRun(piece, rollout.world(piece), offset, rollout.evaluator.static(piece), self.loop,
                            self.scores)
            for k in range(self.steps(piece)):
                await clock.sleep_until(offset + k * period)  # after the loop's decision at this instant
                applied = dict(self.loop.applied)  # what runs during this window
                position = self.loop.controller.position
                images, points = await self._observe(run, k, applied, clock)
                self._window = (piece.scenario, position, applied, images, points)
            offset += self.steps(piece) * period

    async def _observe(self, run: _PieceRun, k: int, applied: dict[str, SensorConfig],
                       clock: Clock) -> tuple[list[ImageResult], float]:
        """The samples of window ``k`` at their instants; its images and mean radar points."""
        rollout = self.rollout
        samples, period = rollout.samples, rollout.period
        configs = rollout._by_modality(applied)
        offsets = (np.arange(samples) + run.rng.uniform(0.02, 0.98, samples)) / samples
        images, points = [], []
        for j, u in enumerate(offsets):
            t = (k + u) * period
            await clock.sleep_until(run.offset + t)
            slot = k * samples + j if run.static else None
            attribute, self._attribute = self._attribute, False
            image, n_points = rollout._sample(run, configs, t, attribute, slot)
            images.append(image)
            points.append(n_points or 0.0)
        return images, float(np.mean(points))

    def _attribute_next(self) -> None:
        self._attribute = True

    def _decided(self, decision: Decision) -> None:
        assert self._window is not None, "a decision before any sample"
        scenario, position, applied, images, points = self._window
        record = self.rollout._record(scenario, decision.t, position, decision, applied, images, points)
        self.records.append(record)
        if self.on_window is not None:
            self.on_window(record)
