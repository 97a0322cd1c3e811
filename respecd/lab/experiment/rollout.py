"""A controller driven through scenario segments by the daemon's own control loop.

The rollout runs ``respecd.control.loop.ControlLoop`` — the loop the daemon and a replay
run — on a lockstep clock it controls, so a decision window costs no wall time. What differs
from the daemon is only what feeds the loop: the detector is the daemon's single server
(``accelerator.py``: the synchronizer's ticks, the drop-oldest bundle queue, one inference
at a time for as long as the latency table says), its outcomes come from the cache at a few
scored instants per window instead of every percept, the system signal is the accelerator's
busy share (``ModelledLoad``), and decisions go to ``SimulatedSensors``, which answer what the
simulated drivers' ``apply`` would (they clamp). Per decision window (``decision_period_s``):

1. ``samples_per_s`` scene instants at seeded random offsets inside the window (the same
   instants for every policy, so the comparison is paired); at each, the percept the daemon
   would hand on then — the last inference that has ended, on the frames of the bundle it
   took (cached, see ``outcomes.py``), stale as it is — is scored against ground truth at
   the instant, and its features go to the loop. The first bundle taken after the loop asks
   is attributed, once per decision, as the daemon's perception does, and charged as such;
   once it has ended, the next scored instant brings contributions to the loop, from an
   attributed pass over the frames delivered then (at most a window from the attributed
   bundle's; an attributed pass detects exactly what a plain one does, so the scoring is the
   same): one detector outcome per scored instant, not two;
2. at the window's end the loop decides and applies; the observation's load is the
   accelerator's busy share over the window (at most 1) and its latency the mean inference
   time;
3. the window's figures under the configuration that was active during it: the scored
   instants, the accelerator's busy share (the paper's GPU load), the bundles it dropped,
   the detector time the configuration asks for (``compute_ms``: forward time x the rate of
   new detector inputs + attribution once; above 1000 ms/s one accelerator cannot keep up),
   energy (the profile's sensor power model plus the accelerator's power x its busy share),
   and sensing bandwidth, of every sensor and of those the detector reads.

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
from respecd.control.config import HeuristicRules
from respecd.control.controller import Controller
from respecd.control.features import Sample
from respecd.control.loop import ControlLoop
from respecd.control.probe import SystemSample
from respecd.lab.detector.metrics import ImageResult, detection_f1
from respecd.lab.experiment.accelerator import Accelerator, Inference, WindowLoad
from respecd.lab.experiment.latency import Latency
from respecd.lab.experiment.outcomes import Evaluator, Outcome
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
    compute_ms: float  # detector time the configuration asks for, per second (uncapped)
    energy_j: float  # sensors and accelerator
    bandwidth_bps: float
    images: list[ImageResult] = field(default_factory=list)
    load: WindowLoad = WindowLoad(0.0, 0, 0)  # the accelerator over the window
    accelerator_j: float = 0.0  # the accelerator's share of energy_j
    bandwidth_read_bps: float = 0.0  # of the sensors the detector reads


class _PieceRun:
    """One piece inside a rollout: its world, time offset, sample instants and shared state."""

    def __init__(self, piece: Piece, world: Any, offset: float, static: bool, loop: ControlLoop,
                 scores: SceneScores) -> None:
        self.piece = piece
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
    """The loop's ``LoadProbe`` for a trainer: the accelerator's busy share over the window
    that just closed (what the Jetson's GPU probe reads; at most 1, one accelerator); the
    host's own CPU is not probed."""

    def __init__(self, accelerator: Accelerator, clock: Clock, period: float) -> None:
        self.accelerator, self.clock, self.period = accelerator, clock, period
        self.last = WindowLoad(0.0, 0, 0)

    async def read(self) -> SystemSample:
        self.last = self.accelerator.close_window(self.clock.now(), self.period)
        return SystemSample(None, self.last.busy, None, self.last.busy)


def controller_for(profile: Profile, policy: str, rules: HeuristicRules | None = None) -> Controller:
    """The controller the daemon would build for ``profile`` over simulated sensors
    (``rules``: the heuristic's, in place of the profile's)."""
    from respecd.drivers.sim import CAPABILITIES

    caps = {s.name: CAPABILITIES[s.modality] for s in profile.sensors if s.driver == "sim"}
    update: dict[str, Any] = {"policy": policy, "system_probe": False}
    if rules is not None:
        update["heuristic"] = rules
    config = profile.controller.model_copy(update=update)
    return Controller.from_profile(config, profile, caps)


class Rollout:
    """Runs a controller over pieces on cached detector outcomes.

    ``latency``: the detector's time per RGB resolution (the platform's table);
    ``accelerator_w``: what the accelerator draws while busy (energy; default the reward's
    ``compute_w``)."""

    def __init__(self, profile: Profile, evaluator: Evaluator, latency: dict[tuple[int, int], Latency],
                 samples_per_s: float = 1.0, accelerator_w: float | None = None) -> None:
        from respecd.drivers.sim import CAPABILITIES

        self.profile = profile
        self.evaluator = evaluator
        self.latency = latency
        self.accelerator_w = profile.controller.reward.compute_w if accelerator_w is None else accelerator_w
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

    def accelerator(self) -> Accelerator:
        """The daemon's perception as one server, sized by the profile's ``sync`` section."""
        sync = self.profile.sync
        return Accelerator(self.latency, self.evaluator.inputs, sync.bundle_queue, sync.tick_phase,
                           sync.min_rate_hz, sync.max_rate_hz)

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
        accelerator = self.accelerator()
        probe = ModelledLoad(accelerator, clock, self.period)
        loop = ControlLoop(controller, clock, SimulatedSensors(self.caps), applied, probe)
        if attach is not None:
            attach(loop)
        feeder = _Feeder(self, loop, accelerator, probe, on_window)
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

    def _by_modality(self, applied: Mapping[str, SensorConfig]) -> dict[str, SensorConfig]:
        out: dict[str, SensorConfig] = {}
        for s in self.sensors:
            out.setdefault(s.modality, applied[s.name])
        return out

    def outcome(self, inference: Inference, attribute: bool) -> Outcome:
        """The detector's outcome on the bundle ``inference`` took (cached); ``attribute``: with
        the attribution's contributions."""
        bundle = inference.bundle
        run: _PieceRun = bundle.source
        slot = int(bundle.local_t * self.samples / self.period) if run.static else None
        return self.evaluator.outcome(run.world, bundle.configs, bundle.local_t, attribute, slot)

    def detector_rate(self, configs: dict[str, SensorConfig]) -> float:
        rates = [c.rate_hz for m, c in configs.items() if m in self.evaluator.inputs and c.enabled]
        sync = self.profile.sync
        return min(max(max(rates, default=sync.min_rate_hz), sync.min_rate_hz), sync.max_rate_hz)

    def _record(self, scenario: str, now: float, position: Position, decision: Decision,
                applied: dict[str, SensorConfig], images: list[ImageResult], points: float,
                load: WindowLoad) -> WindowRecord:
        compute_s = self.compute_s(applied)
        accelerator_j = load.busy * self.accelerator_w * self.period
        energy = sum(self.powers[n].watts(c) for n, c in applied.items()) * self.period + accelerator_j
        bandwidth = sensing_bandwidth(applied.values(), points)
        read = sensing_bandwidth([c for c in applied.values() if c.modality in self.evaluator.inputs], points)
        return WindowRecord(scenario, now, position, decision, 1000.0 * compute_s / self.period, energy, bandwidth,
                            images, load, accelerator_j, read)

    def compute_s(self, applied: dict[str, SensorConfig]) -> float:
        """Detector seconds one decision window under ``applied`` asks for: a forward pass per
        new input frame, and one of them attributed (its extra time added once); uncapped."""
        by_modality = self._by_modality(applied)
        resolution = by_modality["rgb"].resolution
        assert resolution is not None, "the RGB camera always has a resolution"
        lat = self.latency[resolution]
        inferences = max(self.detector_rate(by_modality) * self.period, 1.0)
        return lat.forward_s * inferences + (lat.attribution_s - lat.forward_s)


class _Feeder:
    """The rollout's percept source on the loop's clock: the accelerator fed with what runs,
    a window's scored instants, and its record once the loop has decided at the window's end."""

    def __init__(self, rollout: Rollout, loop: ControlLoop, accelerator: Accelerator, probe: ModelledLoad,
                 on_window: Callable[[WindowRecord], None] | None) -> None:
        self.rollout = rollout
        self.loop = loop
        self.accelerator = accelerator
        self.probe = probe
        self.on_window = on_window
        self.records: list[WindowRecord] = []
        self.scores = rollout.evaluator.detector.scene_scores()
        self._reads_truth = loop.controller.config.reward.quality == "truth"  # else no F1 is worth computing
        self._window: tuple[str, Position, dict[str, SensorConfig], list[ImageResult], float] | None = None
        loop.on_window.append(accelerator.request_attribution)
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
                start = offset + k * period
                await clock.sleep_until(start)  # after the loop's decision at this instant
                applied = dict(self.loop.applied)  # what runs during this window
                rates = [c.rate_hz for c in applied.values() if c.enabled]
                self.accelerator.configure(start, run, offset, rollout._by_modality(applied), rates)
                position = self.loop.controller.position
                images, points = await self._observe(run, k, clock, rollout._by_modality(applied))
                self._window = (piece.scenario, position, applied, images, points)
            offset += self.steps(piece) * period

    async def _observe(self, run: _PieceRun, k: int, clock: Clock,
                       configs: dict[str, SensorConfig]) -> tuple[list[ImageResult], float]:
        """The scored instants of window ``k``; its images and mean radar points."""
        samples, period = self.rollout.samples, self.rollout.period
        offsets = (np.arange(samples) + run.rng.uniform(0.02, 0.98, samples)) / samples
        images, points = [], []
        for u in offsets:
            t = (k + u) * period
            await clock.sleep_until(run.offset + t)
            self.accelerator.advance(run.offset + t)
            resolution = configs["rgb"].resolution
            assert resolution is not None, "the RGB camera always has a resolution"
            image, n_points = self._score(run, t, (int(resolution[0]), int(resolution[1])))
            images.append(image)
            points.append(n_points or 0.0)
        return images, float(np.mean(points))

    def _score(self, run: _PieceRun, t: float, resolution: tuple[int, int]) -> tuple[ImageResult, float | None]:
        """The percept the daemon would hand on at ``t`` (piece time): scored against the truth
        at ``t``, its features (and, after an attributed inference, contributions) to the loop.
        ``resolution``: the RGB camera's now (the truth's pixel grid while nothing has been
        delivered)."""
        attributed = bool(self.accelerator.take_attributed())
        delivered = self.accelerator.delivered
        if delivered is None:  # nothing delivered yet: no detections, nothing for the loop
            boxes, ignore = self.rollout.evaluator.truth(run.world, t, resolution)
            return ImageResult(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), boxes, ignore), None
        out = self.rollout.outcome(delivered, attributed)
        contributions = run.scores.update(delivered.bundle.t, out.contributions) if attributed else None
        imu = self.rollout.evaluator.imu(run.world, t)
        latency = self.accelerator.mean_latency_s() or delivered.service_s
        boxes, ignore = self.rollout.evaluator.truth(run.world, t, delivered.bundle.resolution)
        image = ImageResult(out.boxes, out.scores, boxes, ignore)
        run.loop.add(Sample(run.offset + t, out.conf_agg, latency, out.luminance, out.motion,
                            float(np.linalg.norm(imu[3:6])), out.radar_points, 0, contributions,
                            detection_f1(image) if self._reads_truth else None))
        return image, out.radar_points

    def _decided(self, decision: Decision) -> None:
        assert self._window is not None, "a decision before any sample"
        scenario, position, applied, images, points = self._window
        record = self.rollout._record(scenario, decision.t, position, decision, applied, images, points,
                                      self.probe.last)
        self.records.append(record)
        if self.on_window is not None:
            self.on_window(record)
