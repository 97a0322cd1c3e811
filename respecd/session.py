"""The session: one run of the pipeline built from a profile, and its whole lifecycle.

drivers → synchronizer → perception → controller, on one event loop; every stage is a
named task restarted by ``supervise`` when it crashes, and stages share nothing but bounded
drop-oldest queues. Components start in order and stop in reverse (aiohttp's cleanup
contexts): the detector and the Q-table load first, in worker threads and abandoned at once
when ``stop`` is set (a bad checkpoint fails before any file is opened or device touched),
then the observers (the recorder), then the stage tasks. ``stop`` cancels every stage,
closes each component in reverse order within ``SHUTDOWN_TIMEOUT_S`` and collects what
failed in ``errors``: one component failing to close never keeps the others open.

Observers attach through ``hooks`` (or ``attach`` for an object with ``on_*`` methods),
never by replacing a running component's queues or callbacks. The daemon, a replay and the
benchmarks all build their pipeline here.
"""

from __future__ import annotations

import asyncio
import gc
import sys
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import structlog

from respecd import heap
from respecd.applied import AppliedConfigs
from respecd.clock import Clock
from respecd.drivers import driver_class
from respecd.drivers.base import Driver, DriverContext
from respecd.liveness import Liveness, status_text
from respecd.messages import Bundle, Decision, Frame, Percept, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.sdnotify import Notifier
from respecd.status import format_line, snapshot
from respecd.supervisor import driver_backoff, driver_runner, supervise
from respecd.sync import HealthThresholds, Synchronizer
from respecd.timeouts import within

log = structlog.get_logger(__name__)

T = TypeVar("T")
SHUTDOWN_TIMEOUT_S = 1.5  # SIGTERM to exit must stay within ~2 s
CANCEL_GRACE_S = 0.3  # stages normally end at once when cancelled
# Worker threads (renders, decoding, torch glue) hold the GIL for up to the switch interval
# before the loop thread may run; CPython's 5 ms default alone would break the 30 Hz tick's
# jitter budget, so the session asks for 1 ms. 0.5 ms measured no better (docs/PERFORMANCE.md,
# "GIL switch interval").
GIL_SWITCH_INTERVAL_S = 0.001
HEAP_TRIM_PERIOD_S = 30.0  # session-clock seconds between malloc_trim calls (_heap_trim_loop)

StatusSink = Callable[[dict[str, Any], str], None]


@dataclass
class Hooks:
    """The declared observation points of a running session; every callable must return at once."""

    frame: list[Callable[[str, Frame], None]] = field(default_factory=list)  # (sensor name, frame)
    bundle: list[Callable[[Bundle], None]] = field(default_factory=list)
    inference: list[Callable[[Percept], None]] = field(default_factory=list)  # as the detector produced it
    percept: list[Callable[[Percept], None]] = field(default_factory=list)  # as the controller gets it
    decision: list[Callable[[Decision], None]] = field(default_factory=list)
    config: list[Callable[[str, SensorConfig], None]] = field(default_factory=list)  # start config, then changes
    tick: list[Callable[[float, float], None]] = field(default_factory=list)  # synchronizer (scheduled, actual)
    up: list[Callable[[], None]] = field(default_factory=list)  # every component started: the pipeline runs


class StartAbandoned(Exception):
    """``stop`` was set while the session was still starting."""


class Session:
    """Builds one pipeline from ``profile``; ``run`` starts it, waits, and stops it."""

    def __init__(
        self,
        profile: Any,
        clock: Clock,
        context: DriverContext | None = None,
        *,
        policy: str | None = None,
        state_dir: Path | None = None,
        tables: Any = None,
        observers: list[Any] | None = None,
        status_sink: StatusSink | None = None,
        notifier: Notifier | None = None,
        latency_model: Any = None,
    ) -> None:
        """No I/O here: drivers are constructed (their constructors do none), nothing runs."""
        self.profile = profile
        self.clock = clock
        self.context = context or DriverContext()
        self.policy = policy
        self.state_dir = state_dir
        self.tables = tables  # control.stage.TableFiles; default: the state directory's table
        self.status_sink = status_sink
        self.notifier = notifier or Notifier(address="")
        self.latency_model = latency_model
        self.hooks = Hooks()
        self.drivers: dict[str, Driver] = {
            s.name: driver_class(s.driver)(s, clock, self.context) for s in profile.sensors
        }
        self.applied = AppliedConfigs({name: d.applied for name, d in self.drivers.items()})
        sync_cfg = profile.sync
        self.frame_queues = {n: DropOldestQueue[Frame](sync_cfg.frame_queue, n) for n in self.drivers}
        self.bundles = DropOldestQueue[Bundle](sync_cfg.bundle_queue, "bundles")
        self.percepts = DropOldestQueue[Percept](4, "percepts")
        self.synchronizer = Synchronizer(
            self.drivers, self.frame_queues, self.bundles, clock,
            min_rate_hz=sync_cfg.min_rate_hz, max_rate_hz=sync_cfg.max_rate_hz, window_s=sync_cfg.window_s,
            phase=sync_cfg.tick_phase, on_tick=self._tick, applied=self.applied,
            thresholds=HealthThresholds(
                sync_cfg.jitter_ms_fair, sync_cfg.jitter_ms_poor, sync_cfg.stale_fair, sync_cfg.stale_poor
            ),
        )
        self.perception: Any = None
        self.controller: Any = None
        self.observers: list[Any] = []
        self.last_flow_t: float | None = None
        self.errors: list[str] = []  # what failed while stopping (logged with its traceback)
        self.lingering: list[str] = []  # stage tasks still running after shutdown's budget
        self._closers: list[tuple[str, Callable[[], Any]]] = []  # in start order
        self._tasks: dict[str, asyncio.Task[None]] = {}  # in start order
        self._running = False
        self._withheld: list[str] = []  # why the watchdog is not fed, as last logged
        controller = profile.controller
        self.liveness = Liveness(clock, profile.telemetry.watchdog_stall_s,
                                 controller.decision_period_s + controller.apply_timeout_s)
        for kind in ("frame", "bundle", "inference", "percept", "decision", "tick"):
            getattr(self.hooks, kind).append(getattr(self.liveness, f"on_{kind}"))
        for observer in observers or []:
            self.attach(observer)

    # -- observers ----------------------------------------------------------------------
    def attach(self, observer: Any) -> None:
        """Attach an object's ``on_frame/on_bundle/on_percept/on_decision/on_config`` (those
        it has) to the hooks; its ``start``/``close``, if any, become part of the lifecycle."""
        for kind in ("frame", "bundle", "percept", "decision", "config"):
            method = getattr(observer, f"on_{kind}", None)
            if method is not None:
                getattr(self.hooks, kind).append(method)
        self.observers.append(observer)

    # -- lifecycle ----------------------------------------------------------------------
    async def run(self, duration: float | None = None, stop: asyncio.Event | None = None) -> None:
        """Start, then run until ``duration`` seconds have passed on the clock or ``stop`` is
        set, then stop. A stop during start-up ends it as soon as the loop sees the signal."""
        stop = stop or asyncio.Event()
        try:
            await self.start(stop)
            await self._wait(duration, stop)
        except StartAbandoned:
            log.info("start_abandoned")
        finally:
            await self.stop()

    async def start(self, stop: asyncio.Event | None = None) -> None:
        """Start every component in order; on a failure, stop what started and re-raise."""
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        try:
            await self._start_stages(stop)
            for observer in self.observers:
                await self._start_observer(observer)
            self._start_tasks()
        except BaseException:
            await self.stop()
            raise
        self._running = True
        # what start-up made (modules, the detector, the profile) lives as long as the run: out of
        # the collector's sight, so a full collection scans only what the run allocates since
        # (with torch loaded one took tens of ms, all of it on the loop or a stage's thread)
        gc.collect()
        gc.freeze()
        log.info("pipeline_up", sensors=list(self.drivers), profile=self.profile.name)
        self.notifier.ready(status="pipeline up")
        for hook in self.hooks.up:
            hook()

    async def _start_stages(self, stop: asyncio.Event | None) -> None:
        """Detector and controller first: a bad checkpoint or an empty action space is a
        start-up error (exit 2) before anything else runs."""
        if self.profile.perception.enabled:
            from respecd.perception.stage import PerceptionStage

            self.perception = PerceptionStage(self.profile.perception, self.profile, self.clock,
                                              latency_model=self.latency_model)
            self.perception.on_inference.extend(self.hooks.inference)
            await self._unless_stopped(self.perception.load(), stop)
        if self.profile.controller.enabled:
            self.controller = self._controller_stage()
            self._closers.append(("controller", self.controller.close))
            await self._unless_stopped(self.controller.prepare(), stop)

    def _controller_stage(self) -> Any:
        from respecd.control.stage import ControllerStage

        config = self.profile.controller
        if self.policy is not None:
            config = config.model_copy(update={"policy": self.policy})
        stage = ControllerStage(config, self.profile, self.drivers, self.clock, self.state_dir or Path("."),
                                self.applied, self.tables)
        stage.on_decision.extend(self.hooks.decision)
        if self.perception is not None:
            self.perception.attribute_on_request()  # once per decision window, never more
            stage.loop.on_window.append(self.perception.request_attribution)
        return stage

    async def _start_observer(self, observer: Any) -> None:
        start = getattr(observer, "start", None)
        if start is not None:
            result = start()
            if asyncio.iscoroutine(result):
                await result
        close = getattr(observer, "close", None)
        if close is not None:
            self._closers.append((type(observer).__name__, close))

    def _start_tasks(self) -> None:
        self.bundles.taps.append(self._note_flow)
        self.bundles.taps.extend(self.hooks.bundle)
        self.percepts.taps.extend(self.hooks.percept)
        self.applied.subscribe(self.synchronizer.on_config, current=False)
        for listener in self.hooks.config:
            self.applied.subscribe(listener)  # the start configuration, then every change
        loop = asyncio.get_running_loop()
        for name, driver in self.drivers.items():
            driver.announce_changes(partial(self._notice, loop, name))
            self._driver_changed(name)  # anything a driver learned between construction and now
            runner = driver_runner(driver, self._sink(name))
            self._spawn(f"driver:{name}", supervise(f"driver:{name}", runner, backoff=driver_backoff(driver)))
        self._spawn("sync", supervise("sync", self.synchronizer.run))
        if self.perception is not None:
            perception = self.perception
            self._spawn("perception", supervise("perception", lambda: perception.run(self.bundles, self.percepts)))
        else:
            self._spawn("perception", supervise("passthrough", self._passthrough))
        if self.controller is not None:
            controller = self.controller
            self._spawn("controller", supervise("controller", lambda: controller.run(self.percepts)))
        self._spawn("status", self._status_loop())
        if heap.available():
            self._spawn("heap-trim", self._heap_trim_loop())
        if self.notifier.enabled:
            self._spawn("watchdog", self._watchdog_loop())

    async def stop(self) -> None:
        """Cancel every stage, then close components in reverse start order — within ~2 s.

        What must not be lost (Q-table, MCAP log) is closed right after the stages are
        cancelled, before waiting on slow stragglers such as an inference still running in
        its worker thread; ``lingering`` lists what had not finished when the budget ran out.
        Safe to call twice, and after a failed start.
        """
        if self._running:
            self.notifier.stopping()
            log.info("stopping")
        tasks = list(self._tasks.values())[::-1]
        self._tasks.clear()
        for task in tasks:
            task.cancel()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SHUTDOWN_TIMEOUT_S
        if tasks:
            await asyncio.wait(tasks, timeout=CANCEL_GRACE_S)
        closers, self._closers = self._closers[::-1], []
        for name, close in closers:
            await self._close(name, close, max(deadline - loop.time(), CANCEL_GRACE_S))
        pending = [t for t in tasks if not t.done()]
        if pending:
            await asyncio.wait(pending, timeout=max(deadline - loop.time(), 0.01))
        for driver in self.drivers.values():
            driver.announce_changes(None)
        self.lingering = [t.get_name() for t in tasks if not t.done()]
        if self.lingering:
            log.warning("stages_still_stopping", tasks=self.lingering)
        if self._running:
            self.notifier.close()
            log.info("stopped")
        self._running = False

    async def _close(self, name: str, close: Callable[[], Any], timeout: float) -> None:
        try:
            result = close()
            if asyncio.iscoroutine(result):
                await within(result, timeout)
        except Exception as err:  # one component failing to close must not keep the others open
            self.errors.append(f"{name}: {err!r}")
            log.exception("close_failed", component=name)

    async def _unless_stopped(self, work: Awaitable[T], stop: asyncio.Event | None) -> T:
        """``work``, unless ``stop`` is set first (then StartAbandoned; a worker thread still
        loading is left to finish on its own, nobody waits for it)."""
        job = asyncio.ensure_future(work)
        if stop is None:
            return await job
        waiter = asyncio.ensure_future(stop.wait())
        try:
            await asyncio.wait({job, waiter}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
        if not job.done():
            job.cancel()
            raise StartAbandoned
        return job.result()

    async def _wait(self, duration: float | None, stop: asyncio.Event) -> None:
        waiters: list[asyncio.Future[Any]] = [asyncio.ensure_future(stop.wait())]
        if duration is not None:
            waiters.append(asyncio.ensure_future(self.clock.sleep_until(self.clock.now() + duration)))
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()
            await asyncio.gather(*waiters, return_exceptions=True)

    # -- the stages ---------------------------------------------------------------------
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

    def _spawn(self, name: str, coro: Any) -> None:
        self._tasks[name] = asyncio.create_task(coro, name=name)

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

    def _note_flow(self, bundle: Bundle) -> None:
        if bundle.frames:
            self.last_flow_t = bundle.t

    async def _passthrough(self) -> None:
        """Without a detector, the controller still gets every bundle (scene signals only)."""
        while True:
            bundle = await self.bundles.get()
            percept = Percept(t=bundle.t, detections=(), conf_agg=0.0, contributions=None, latency=0.0, bundle=bundle)
            for hook in self.hooks.inference:
                hook(percept)
            self.percepts.put(percept)

    async def _status_loop(self) -> None:
        period = self.profile.telemetry.status_period_s
        next_t = self.clock.now() + period
        while True:
            await self.clock.sleep_until(next_t)
            next_t += period
            fields = self.status_fields()
            fields["degraded"] = self.liveness.degraded(self.drivers, self.applied, fields.get("recording"))
            fields["stalled"] = self.stalls()
            line = format_line(fields, {n: d.modality for n, d in self.drivers.items()})
            line = status_text(line, fields["degraded"], fields["stalled"])
            if self.status_sink is not None:
                self.status_sink(fields, line)
            self.notifier.status(line)

    async def _heap_trim_loop(self) -> None:
        """Hand freed C-heap pages back to the kernel every HEAP_TRIM_PERIOD_S (respecd.heap).

        Torch's and the recorder's buffers come and go at sizes that change with the sensors' settings,
        and glibc keeps the pages they free: untrimmed, RSS grows in steps while the bytes in use stay
        flat. The trim runs in a worker thread; what it saves and costs: docs/PERFORMANCE.md "soak".
        """
        next_t = self.clock.now() + HEAP_TRIM_PERIOD_S
        while True:
            await self.clock.sleep_until(next_t)
            next_t += HEAP_TRIM_PERIOD_S
            await asyncio.to_thread(heap.trim)

    def stalls(self) -> list[str]:
        """Why the watchdog must not be fed (respecd.liveness); empty while alive and supervising."""
        stages = ("perception", "controller") if self.controller is not None else ("perception",)
        return self.liveness.stalls(self._tasks, stages)

    async def _watchdog_loop(self) -> None:
        """WATCHDOG=1 at least every second (at half of WatchdogSec at most) while the loop is
        alive and supervising; sensors being absent does not matter (STATUS= says so)."""
        period = min(self.notifier.watchdog_interval_s() or 1.0, 1.0)
        while True:
            stalls = self.stalls()
            if not stalls:
                self.notifier.watchdog()
            if stalls != self._withheld:  # log once per change, not once per second
                if stalls:
                    log.error("watchdog_withheld", reasons=stalls)
                else:
                    log.info("watchdog_fed_again", after=self._withheld)
                self._withheld = stalls
            await asyncio.sleep(period)  # wall time: what systemd's WatchdogSec counts

    def status_fields(self) -> dict[str, Any]:
        drops = {name: q.dropped for name, q in self.frame_queues.items() if q.dropped}
        drops["bundles"] = self.bundles.dropped
        recorder_drops = sum(getattr(o, "dropped", 0) for o in self.observers)
        if recorder_drops:
            drops["recorder"] = recorder_drops
        percept = getattr(self.perception, "last", None)
        decision = getattr(self.controller, "last", None)
        action_name = None
        if decision is not None and hasattr(self.controller, "describe_action"):
            action_name = self.controller.describe_action(decision.action)
        fields = snapshot(self.clock.now(), self.drivers, self.synchronizer.last_stats, drops, percept, decision,
                          action_name, self.applied)
        for observer in self.observers:
            if hasattr(observer, "recording_status"):
                fields["recording"] = observer.recording_status()
        return fields
