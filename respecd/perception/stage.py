"""The perception stage: Bundles in, Percepts out, the detector in one worker thread.

Torch work never runs on the event loop: one dedicated single-thread executor does every
``infer`` (so the detector's state, e.g. the decaying scene score, is only ever touched by
that thread), and the checkpoint is loaded in a worker thread by ``load`` (the loop keeps
answering signals meanwhile). Attribution (a few forward passes) runs only where its result
is used: with a controller, on the first bundle and then once per decision window, at the
next bundle after the controller's ``request_attribution()`` and never more often; without
one (the scene score is then for the status line and the log), at the profile's cadence.

A lockstep replay gives the stage a ``LatencyModel``: the detector takes the modelled
latency on the log's clock, as on the robot. The percept is delivered that much later, and
the stage takes its next bundle only then (a slow detector skips bundles as it did on the
robot); the percept carries the modelled latency downstream. Meanwhile the log's clock goes
on (sensors, synchronizer, controller run beside the detector, on the other core); only if
the detector is not done when its modelled latency is up does the clock wait for it. Which
bundle is taken and when a percept arrives depend on the log alone. ``on_inference``
observers see each percept as the detector produced it (measured latency).

While the clock waits for the detector, the bundle it will take next is already queued: its
input is prepared then, beside the detector (``perception.ahead``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import threading
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import structlog

from respecd.clock import Clock
from respecd.errors import UndecodableImageError
from respecd.messages import Bundle, Percept
from respecd.perception.ahead import InputPreparer, core_beside
from respecd.perception.config import PerceptionConfig
from respecd.priority import lower_thread_priority
from respecd.queues import DropOldestQueue
from respecd.sensors import Calibration

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)

SHUTDOWN_TIMEOUT_S = 5.0  # longer than one forward+attribution at 1280x720 on a 2-core CPU

# Loaded detectors by (perception config, calibration), while ``share_detectors`` holds: a process
# that evaluates many logs one after another (a fleet's worker) loads each checkpoint once. Each
# session still starts from a fresh scene score; the detector's other caches depend on input
# sizes alone, so a shared detector answers as a fresh one does.
_shared: dict[str, _Shared] | None = None


@dataclasses.dataclass
class _Shared:
    """A shared detector, and the threads a stopped session left running an inference on it
    (a fleet's machine under load can take longer than the stop's grace to finish one)."""

    detector: Any
    stragglers: list[threading.Thread] = dataclasses.field(default_factory=list)


@contextlib.contextmanager
def share_detectors() -> Iterator[None]:
    """Within: sessions of this process share loaded detectors (one session at a time: the next
    waits for the last one's inference still running, which would change its scene score)."""
    global _shared
    before = _shared
    _shared = {} if before is None else before
    try:
        yield
    finally:
        _shared = before


class LatencyModel(Protocol):
    """Perception latency as the robot's detector would have had it (``replay.latency``)."""

    def predict(self, bundle: Bundle, attributed: bool) -> float: ...


def calibration_from_profile(profile: Profile) -> dict[str, Calibration | None]:
    """Per modality, the calibration of the first sensor that has one (else None)."""
    calibration: dict[str, Calibration | None] = {}
    for sensor in profile.sensors:
        if calibration.get(sensor.modality) is None:
            calibration[sensor.modality] = sensor.calibration
    return calibration


def _on_grid(frames: Mapping[Any, Any], grid: tuple[int, int] | None) -> dict[str, tuple[int, int]]:
    """``infer``'s grid argument for frames without an RGB frame (none with one, or without a grid)."""
    return {} if grid is None or "rgb" in frames else {"rgb_size": grid}


class PerceptionStage:
    """Runs the fusion detector on each bundle.

    The checkpoint is loaded by ``load`` before the session starts the pipeline, so a bad or
    mismatched one fails the start (exit 2) rather than a supervised task; the session races
    it against a stop signal. ``last`` is the newest Percept for the status line,
    with the most recent attribution's scene numbers (contributions, dependence, sufficiency)
    carried over between attributions (the Percepts on the queue keep ``contributions=None``
    when not attributed).
    """

    def __init__(self, config: PerceptionConfig, calibration: Mapping[str, Calibration | None] | None,
                 clock: Clock, detector: Any = None, latency_model: LatencyModel | None = None,
                 exports: Path | None = None) -> None:
        """``calibration``: per modality (``calibration_from_profile``); None when a detector is given."""
        self.config = config
        self.calibration = dict(calibration or {})
        # with perception.runtime other than torch: where the exported graphs are cached (the session's state
        # directory's exported/; None: the default state directory's), see FusionDetector.load
        self.exports = exports
        self.clock = clock
        self.last: Percept | None = None
        self.processed = 0
        self.latency_model = latency_model
        self.on_inference: list[Callable[[Percept], None]] = []  # as produced, before any latency model
        self._detector = detector
        self._shared_entry: _Shared | None = None  # the detector's, while share_detectors holds
        self._busy_until = float("-inf")
        self._attributed: Percept | None = None  # the newest percept with contributions
        self._executor: ThreadPoolExecutor | None = None
        self._attribution_requested = False
        self._on_request_only = False
        self._last_attribution_t: float | None = None
        self._inputs = frozenset({"rgb", *config.model.aux_modalities})
        self._last_inputs: dict[str, tuple[int, float]] = {}
        self.skipped = 0  # bundles whose detector inputs were all seen already
        self.undecodable: dict[str, int] = {}  # per sensor: logged images left out, their bytes damaged
        self._pending: asyncio.Future[None] | None = None  # done once the bundle taken has its percept out
        self._finishing = False
        self._preparer: InputPreparer | None = None  # prepares the next bundle's input (lockstep)
        self._rgb_grid: tuple[int, int] | None = None  # with a preparer: the newest RGB size, in bundle order

    def finish(self) -> asyncio.Future[None] | None:
        """Take no new bundle; the future is done when the one being worked on has its percept
        out (None when idle). A replay calls it at the log's end: the robot's detector would
        have finished that bundle, and none after it is part of the log."""
        self._finishing = True
        return self._pending if self._pending is not None and not self._pending.done() else None

    def request_attribution(self) -> None:
        """Attribute the next bundle, whatever the cadence says."""
        self._attribution_requested = True

    def attribute_on_request(self) -> None:
        """A controller will ask for attributions (once per window): attribute only then, and
        the first bundle, so the first decision has contributions; the cadence no longer applies."""
        self._on_request_only = True

    async def load(self) -> None:
        """Load the checkpoint in a worker thread of its own (ConfigError when it is bad); once.

        Not the loop's default executor: when a stop signal abandons the start, nobody waits
        for a load still running there (``asyncio.run`` would join the default executor)."""
        if self._detector is not None:
            return
        log.info("detector_loading", weights=self.config.weights)
        executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="perception-load")
        try:
            self._detector = await asyncio.get_running_loop().run_in_executor(executor, self._load)
        finally:
            executor.shutdown(wait=False)

    async def run(self, bundles: DropOldestQueue[Bundle], percepts: DropOldestQueue[Percept]) -> None:
        """Forever: bundle -> detector (worker thread) -> Percept(bundle=...) on ``percepts``."""
        await self.load()
        loop = asyncio.get_running_loop()
        # live, the detector only has to keep up and yields to the loop; in a lockstep replay (the
        # latency model's) the log's clock waits for it, so it is the critical path: normal priority
        yields = lower_thread_priority if self.latency_model is None else None
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="perception", initializer=yields)
        prepare = getattr(self._detector, "prepare", None)
        if self.latency_model is not None and prepare is not None and core_beside(self.config.torch_threads):
            self._preparer = InputPreparer(prepare, self._inputs)
            self._rgb_grid = self._detector.first_rgb_size()
        try:
            while True:
                if self.latency_model is not None:
                    await self.clock.sleep_until(self._busy_until)  # still busy on the modelled clock
                bundle = await bundles.get()
                taken = self.clock.now()
                if self._finishing:
                    continue
                if not self._has_new_input(bundle):
                    self.skipped += 1
                    continue
                attribute = self._attribution_due(bundle.t)
                frames = dict(bundle.frames)
                self._pending = loop.create_future()
                if self.latency_model is None:
                    percept = await loop.run_in_executor(self._executor, self._infer_intact, frames, attribute)
                    modelled = None
                else:
                    modelled = self.latency_model.predict(bundle, attribute)
                    percept = await self._infer_beside_the_clock(frames, attribute, taken + modelled, bundles)
                percept = dataclasses.replace(percept, t=bundle.t, bundle=bundle)
                self.last = self._with_last_attribution(percept)
                self.processed += 1
                for hook in self.on_inference:
                    hook(percept)
                if modelled is not None:
                    percept = dataclasses.replace(percept, latency=modelled)
                    self._busy_until = taken + modelled
                percepts.put(percept)
                self._pending.set_result(None)
        finally:
            if self._pending is not None and not self._pending.done():
                self._pending.cancel()
            await self._shutdown()

    async def _infer_beside_the_clock(self, frames: dict[Any, Any], attribute: bool, due: float,
                                      bundles: DropOldestQueue[Bundle]) -> Percept:
        """The detector in its thread while the log's clock runs on to ``due`` (when the
        robot's detector would have delivered); then its result, the clock standing still
        until it is there (meanwhile the next bundle's input is prepared). The job is handed
        to the executor directly, so a ``LockstepLoop`` does not count it (which would hold
        the clock); waiting for its result is counted."""
        assert self._executor is not None
        prepared = self._preparer.take(frames) if self._preparer is not None else None
        grid = self._rgb_grid = self._grid_for(frames)
        job = self._executor.submit(self._infer, frames, attribute, prepared, grid)
        try:
            await self.clock.sleep_until(due)
            if job.done():
                return job.result()
            self._prepare_next(bundles)
            return await asyncio.get_running_loop().run_in_executor(None, job.result)
        finally:
            job.cancel()  # a stop while it runs: it finishes in its thread, nobody waits for it

    def _infer_intact(self, frames: dict[Any, Any], attribute: bool, grid: tuple[int, int] | None = None) -> Percept:
        """The detector on ``frames``; a logged image that does not decode is left out, as a frame
        that never came (the detector runs on the other sensors), and said: the first time per
        sensor, then every 100th. Before, it took the whole perception stage down for its restart.
        ``grid``: the RGB size to detect on if no RGB frame is left (``_grid_for``)."""
        try:
            return self._detector.infer(frames, attribute, **_on_grid(frames, grid))
        except UndecodableImageError:
            intact: dict[Any, Any] = {}
            for name, frame in frames.items():
                try:
                    frame.data  # noqa: B018  # decodes it (cached) or raises again
                except UndecodableImageError as err:
                    count = self.undecodable[name] = self.undecodable.get(name, 0) + 1
                    if count == 1 or count % 100 == 0:
                        log.warning("frame_undecodable", sensor=name, error=str(err), count=count,
                                    action="inferred without it")
                    continue
                intact[name] = frame
            return self._detector.infer(intact, attribute, **_on_grid(intact, grid))

    def _prepare_next(self, bundles: DropOldestQueue[Bundle]) -> None:
        """Prepare, in the preparer's thread, the input of the bundle ``run`` takes next. Called
        with the clock at the running job's due time: the queue holds what it will hold when
        the job is done. A frame that cannot be decoded fails again where the detector reads it."""
        if self._preparer is None or self._finishing:
            return
        bundle = next((b for b in bundles.pending() if self._inputs_of(b) != self._last_inputs), None)
        if bundle is not None:
            self._preparer.start(dict(bundle.frames), self._grid_for(bundle.frames))

    def _grid_for(self, frames: Mapping[Any, Any]) -> tuple[int, int] | None:
        """The grid of the bundle taken next: its RGB frame's size, else the newest one taken before it
        (at first the detector's calibrated size). Kept here in bundle order, not by the aligner, which
        the preparer's thread and the detector's both run: which of them aligned a later RGB frame first
        must not decide where a bundle without one is detected. None without a preparer."""
        rgb = frames.get("rgb")
        if self._preparer is None or rgb is None:
            return self._rgb_grid
        height, width = rgb.shape[:2]
        return (width, height)

    def _infer(self, frames: dict[Any, Any], attribute: bool, prepared: Future[Any] | None,
               grid: tuple[int, int] | None) -> Percept:
        """The detector on ``frames`` (its thread), with the input prepared ahead when it is there:
        waited for if the preparer is on it, prepared here if it has not started or failed."""
        aligned = None if prepared is None or prepared.cancel() else prepared.result()
        if aligned is None:
            return self._infer_intact(frames, attribute, grid)
        return self._detector.infer(frames, attribute, aligned, **_on_grid(frames, grid))

    async def _shutdown(self) -> None:
        """Drop a pending infer, let a running one finish in its thread without blocking the loop."""
        preparer, self._preparer = self._preparer, None
        if preparer is not None:
            preparer.shutdown()
        executor, self._executor = self._executor, None
        if executor is None:
            return
        executor.shutdown(wait=False, cancel_futures=True)
        threads = list(getattr(executor, "_threads", ()))
        if self._shared_entry is not None:  # the next session on this detector waits for them
            self._shared_entry.stragglers = threads
        deadline = asyncio.get_running_loop().time() + SHUTDOWN_TIMEOUT_S
        while any(t.is_alive() for t in threads) and asyncio.get_running_loop().time() < deadline:
            await asyncio.sleep(0.01)

    def _with_last_attribution(self, percept: Percept) -> Percept:
        """``percept``, carrying the newest attribution's scene numbers when it has none of its own."""
        if percept.contributions:
            self._attributed = percept
        if percept.contributions is not None or self._attributed is None:
            return percept
        held = self._attributed
        return dataclasses.replace(percept, contributions=held.contributions, dependence=held.dependence,
                                   sufficiency=held.sufficiency)

    def _load(self) -> Any:
        """Set torch's (process-wide) intra-op thread count and load the checkpoint (into its runtime)."""
        import torch

        from respecd.perception.detector import FusionDetector

        torch.set_num_threads(self.config.torch_threads)
        if _shared is None:
            return FusionDetector.load(self.config, self.calibration, self.exports)
        calibration = {m: c.model_dump(mode="json") if c is not None else None for m, c in self.calibration.items()}
        key = json.dumps([self.config.model_dump(mode="json"), calibration, str(self.exports)], sort_keys=True)
        entry = _shared.get(key)
        if entry is None:
            entry = _shared[key] = _Shared(FusionDetector.load(self.config, self.calibration, self.exports))
        for thread in entry.stragglers:  # the last session's inference ends before this one starts
            thread.join()
        entry.stragglers = []
        entry.detector.start_session()
        self._shared_entry = entry
        return entry.detector

    def _has_new_input(self, bundle: Bundle) -> bool:
        """True when a detector input (RGB or an aux modality) brings a frame not yet seen.

        The synchronizer ticks at the fastest sensor (an IMU keeps it at 30 Hz); running
        the detector again on the same RGB/thermal/radar frames would cost a full inference
        for an identical answer, so lowering those sensors' rates really lowers compute.
        """
        seen = self._inputs_of(bundle)
        if seen == self._last_inputs:
            return False
        self._last_inputs = seen
        return True

    def _inputs_of(self, bundle: Bundle) -> dict[str, tuple[int, float]]:
        """Which frame (seq, time) each detector input of ``bundle`` is."""
        return {m: (f.seq, f.t) for m, f in bundle.frames.items() if m in self._inputs}

    def _attribution_due(self, t: float) -> bool:
        cadence = not self._on_request_only and (
            self._last_attribution_t is not None and t - self._last_attribution_t >= self.config.attribution_every_s
        )
        due = self._attribution_requested or self._last_attribution_t is None or cadence
        if due:
            self._attribution_requested = False
            self._last_attribution_t = t
        return due
