"""The pipeline of one run: drivers → synchronizer → perception → controller, built from a profile.

Stages share nothing but bounded drop-oldest queues, and every stage runs as a named task
restarted by ``supervise`` when it crashes. Building does no I/O (drivers' constructors do
none); ``Session`` says when each part loads, runs and stops.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from respecd.applied import AppliedConfigs
from respecd.clock import Clock
from respecd.drivers import driver_class
from respecd.drivers.base import Driver, DriverContext
from respecd.messages import Bundle, Frame, Percept
from respecd.observe import Hooks
from respecd.queues import DropOldestQueue
from respecd.supervisor import driver_backoff, driver_runner, supervise
from respecd.sync import HealthThresholds, Synchronizer

if TYPE_CHECKING:
    from respecd.config import Profile
    from respecd.control.stage import ControllerStage
    from respecd.perception.stage import PerceptionStage


class Pipeline:
    """The stages of one run and the queues between them; ``hooks`` observe every hand-over."""

    def __init__(self, profile: Profile, clock: Clock, context: DriverContext, hooks: Hooks,
                 latency_model: Any = None) -> None:
        self.profile = profile
        self.clock = clock
        self.hooks = hooks
        self.latency_model = latency_model
        self.drivers: dict[str, Driver] = {
            s.name: driver_class(s.driver)(s, clock, context) for s in profile.sensors
        }
        self.applied = AppliedConfigs({name: d.applied for name, d in self.drivers.items()})
        sync = profile.sync
        self.frame_queues = {n: DropOldestQueue[Frame](sync.frame_queue, n) for n in self.drivers}
        self.bundles = DropOldestQueue[Bundle](sync.bundle_queue, "bundles")
        self.percepts = DropOldestQueue[Percept](4, "percepts")
        self.synchronizer = Synchronizer(
            self.drivers, self.frame_queues, self.bundles, clock,
            min_rate_hz=sync.min_rate_hz, max_rate_hz=sync.max_rate_hz, window_s=sync.window_s,
            phase=sync.tick_phase, on_tick=self._tick, applied=self.applied,
            thresholds=HealthThresholds(sync.jitter_ms_fair, sync.jitter_ms_poor, sync.stale_fair, sync.stale_poor),
        )
        self.perception: PerceptionStage | None = None
        self.controller: ControllerStage | None = None

    def make_perception(self, exports: Path | None = None) -> PerceptionStage:
        """``exports``: where another runtime's exported graphs are cached (``FusionDetector.load``)."""
        from respecd.perception.stage import PerceptionStage, calibration_from_profile

        self.perception = PerceptionStage(self.profile.perception, calibration_from_profile(self.profile),
                                          self.clock, latency_model=self.latency_model, exports=exports)
        self.perception.on_inference.extend(self.hooks.inference)
        return self.perception

    def make_controller(self, policy: str | None, state_dir: Path | None, tables: Any) -> ControllerStage:
        """``tables``: control.stage.TableFiles; default: the state directory's table."""
        from respecd.control.stage import ControllerStage

        config = self.profile.controller
        if policy is not None:
            config = config.model_copy(update={"policy": policy})
        stage = ControllerStage(config, self.profile, self.drivers, self.clock, state_dir or Path("."),
                                self.applied, tables)
        stage.on_decision.extend(self.hooks.decision)
        if self.perception is not None:
            self.perception.attribute_on_request()  # once per decision window, never more
            stage.loop.on_window.append(self.perception.request_attribution)
        self.controller = stage
        return stage

    def tasks(self) -> dict[str, Coroutine[Any, Any, None]]:
        """Connect the taps and the drivers' change notices; the supervised stage coroutines by task name."""
        self.bundles.taps.extend(self.hooks.bundle)
        self.percepts.taps.extend(self.hooks.percept)
        self.applied.subscribe(self.synchronizer.on_config, current=False)
        for listener in self.hooks.config:
            self.applied.subscribe(listener)  # the start configuration, then every change
        loop = asyncio.get_running_loop()
        tasks: dict[str, Coroutine[Any, Any, None]] = {}
        for name, driver in self.drivers.items():
            driver.announce_changes(partial(self._notice, loop, name))
            self._driver_changed(name)  # anything a driver learned between construction and now
            runner = driver_runner(driver, self._sink(name))
            tasks[f"driver:{name}"] = supervise(f"driver:{name}", runner, backoff=driver_backoff(driver))
        tasks["sync"] = supervise("sync", self.synchronizer.run)
        perception, controller = self.perception, self.controller
        if perception is not None:
            tasks["perception"] = supervise("perception", lambda: perception.run(self.bundles, self.percepts))
        else:
            tasks["perception"] = supervise("passthrough", self._passthrough)
        if controller is not None:
            tasks["controller"] = supervise("controller", lambda: controller.run(self.percepts))
        return tasks

    def detach(self) -> None:
        """The drivers stop announcing changes: nobody follows configurations any more."""
        for driver in self.drivers.values():
            driver.announce_changes(None)

    def _notice(self, loop: asyncio.AbstractEventLoop, name: str) -> None:
        """Any thread: a driver's ``applied`` changed; publish it from the loop."""
        try:
            loop.call_soon_threadsafe(self._driver_changed, name)
        except RuntimeError:  # the loop has closed: the session is over and nobody follows configs
            pass

    def _driver_changed(self, name: str) -> None:
        """On the loop: publish what a driver runs if it changed outside an apply answer.

        The value is read now, not carried by the notice, so a notice that arrives after a
        newer apply answer has been published finds nothing new and publishes nothing stale.
        """
        applied = self.drivers[name].applied
        if self.applied.get(name) != applied:
            self.applied.publish(name, applied)

    def _sink(self, name: str) -> Callable[[Frame], None]:
        queue = self.frame_queues[name]
        hooks = self.hooks.frame

        def sink(frame: Frame) -> None:
            queue.put(frame)
            for hook in hooks:
                hook(name, frame)

        return sink

    def _tick(self, scheduled: float, actual: float) -> None:
        for hook in self.hooks.tick:
            hook(scheduled, actual)

    async def _passthrough(self) -> None:
        """Without a detector, the controller still gets every bundle (scene signals only)."""
        while True:
            bundle = await self.bundles.get()
            percept = Percept(t=bundle.t, detections=(), conf_agg=0.0, contributions=None, latency=0.0, bundle=bundle)
            for hook in self.hooks.inference:
                hook(percept)
            self.percepts.put(percept)
