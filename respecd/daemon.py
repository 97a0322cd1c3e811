"""The daemon: drivers → synchronizer → perception → controller, on one event loop.

Every stage is a named task owned here and restarted by ``supervise`` when it crashes;
stages share nothing but bounded drop-oldest queues. ``run`` returns after ``duration``
seconds on the injected clock or when ``stop`` is set (SIGTERM), and then shuts down in
order: stages cancelled, drivers stopped, the Q-table saved, the log finished.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import structlog

from respecd.clock import Clock
from respecd.drivers import driver_class
from respecd.drivers.base import Driver, DriverContext
from respecd.messages import Bundle, Decision, Frame, Percept, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.sdnotify import Notifier
from respecd.status import format_line, snapshot
from respecd.supervisor import driver_runner, supervise
from respecd.sync import HealthThresholds, Synchronizer

log = structlog.get_logger(__name__)

SHUTDOWN_TIMEOUT_S = 1.5  # SIGTERM to exit must stay within ~2 s
CANCEL_GRACE_S = 0.3  # stages normally end at once when cancelled
# Worker threads (renders, decoding, torch glue) hold the GIL for up to the switch interval
# before the loop thread may run; CPython's 5 ms default alone would break the 30 Hz tick's
# jitter budget, so the daemon asks for 1 ms.
GIL_SWITCH_INTERVAL_S = 0.001


class Tap(Protocol):
    """An observer of the pipeline (the MCAP recorder); every method must return at once."""

    def on_frame(self, sensor_name: str, frame: Frame) -> None: ...
    def on_bundle(self, bundle: Bundle) -> None: ...
    def on_percept(self, percept: Percept) -> None: ...
    def on_decision(self, decision: Decision) -> None: ...
    def on_config(self, sensor_name: str, applied: SensorConfig) -> None: ...


StatusSink = Callable[[dict[str, Any], str], None]


class Daemon:
    """Owns the drivers, queues and stage tasks of one run."""

    def __init__(
        self,
        profile: Any,
        clock: Clock,
        context: DriverContext | None = None,
        *,
        policy: str | None = None,
        state_dir: Path | None = None,
        taps: list[Tap] | None = None,
        status_sink: StatusSink | None = None,
        notifier: Notifier | None = None,
    ) -> None:
        self.profile = profile
        self.clock = clock
        self.context = context or DriverContext()
        self.policy = policy
        self.state_dir = state_dir
        self.taps = taps or []
        self.status_sink = status_sink
        self.notifier = notifier or Notifier(address="")
        self.drivers: dict[str, Driver] = {
            s.name: driver_class(s.driver)(s, clock, self.context) for s in profile.sensors
        }
        sync_cfg = profile.sync
        self.frame_queues = {n: DropOldestQueue[Frame](sync_cfg.frame_queue, n) for n in self.drivers}
        self.bundles = DropOldestQueue[Bundle](sync_cfg.bundle_queue, "bundles")
        self.percepts = DropOldestQueue[Percept](4, "percepts")
        self.synchronizer = Synchronizer(
            self.drivers,
            self.frame_queues,
            self.bundles,
            clock,
            min_rate_hz=sync_cfg.min_rate_hz,
            max_rate_hz=sync_cfg.max_rate_hz,
            window_s=sync_cfg.window_s,
            phase=sync_cfg.tick_phase,
            thresholds=HealthThresholds(
                sync_cfg.jitter_ms_fair, sync_cfg.jitter_ms_poor, sync_cfg.stale_fair, sync_cfg.stale_poor
            ),
        )
        self.perception: Any = None
        self.controller: Any = None
        self.last_flow_t: float | None = None
        self.lingering: list[str] = []  # stage tasks still running after shutdown's budget
        self._tasks: set[asyncio.Task[None]] = set()
        self._wire_taps()

    # -- construction -------------------------------------------------------------------
    def _wire_taps(self) -> None:
        self.bundles.taps.append(self._note_flow)
        for tap in self.taps:
            self.bundles.taps.append(tap.on_bundle)
            self.percepts.taps.append(tap.on_percept)

    def _note_flow(self, bundle: Bundle) -> None:
        if bundle.frames:
            self.last_flow_t = bundle.t

    def _build_stages(self) -> None:
        if self.profile.perception.enabled:
            from respecd.perception.stage import PerceptionStage

            self.perception = PerceptionStage(self.profile.perception, self.profile, self.clock)
        if self.profile.controller.enabled:
            from respecd.control.stage import ControllerStage

            controller_cfg = self.profile.controller
            if self.policy is not None:
                controller_cfg = controller_cfg.model_copy(update={"policy": self.policy})
            self.controller = ControllerStage(
                controller_cfg, self.profile, self.drivers, self.clock, self.state_dir or Path(".")
            )
            for tap in self.taps:
                self.controller.on_decision.append(tap.on_decision)
            if self.perception is not None:
                self.controller.perception_hint = self.perception.request_attribution

    def _sink(self, name: str) -> Callable[[Frame], None]:
        queue = self.frame_queues[name]
        taps = [tap.on_frame for tap in self.taps]

        def sink(frame: Frame) -> None:
            queue.put(frame)
            for tap in taps:
                tap(name, frame)

        return sink

    def _spawn(self, name: str, coro: Any) -> None:
        task = asyncio.create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # -- running ------------------------------------------------------------------------
    async def run(self, duration: float | None = None, stop: asyncio.Event | None = None) -> None:
        """Run until ``duration`` seconds have passed on the clock or ``stop`` is set."""
        stop = stop or asyncio.Event()
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        self._build_stages()
        for name, driver in self.drivers.items():
            self._spawn(f"driver:{name}", supervise(f"driver:{name}", driver_runner(driver, self._sink(name))))
            for tap in self.taps:
                tap.on_config(name, driver.applied)
        self._spawn("sync", supervise("sync", self.synchronizer.run))
        if self.perception is not None:
            self._spawn("perception", supervise("perception", lambda: self.perception.run(self.bundles, self.percepts)))
        else:
            self._spawn("perception", supervise("passthrough", self._passthrough))
        if self.controller is not None:
            self._spawn("controller", supervise("controller", lambda: self.controller.run(self.percepts)))
        self._spawn("status", self._status_loop())
        log.info("pipeline_up", sensors=list(self.drivers), profile=self.profile.name)
        self.notifier.ready(status="pipeline up")
        waiters = [asyncio.ensure_future(stop.wait())]
        if duration is not None:
            waiters.append(asyncio.ensure_future(self.clock.sleep_until(self.clock.now() + duration)))
        try:
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()
            await asyncio.gather(*waiters, return_exceptions=True)
            await self.shutdown()

    async def _passthrough(self) -> None:
        """Without a detector, the controller still gets every bundle (scene signals only)."""
        while True:
            bundle = await self.bundles.get()
            self.percepts.put(
                Percept(t=bundle.t, detections=(), conf_agg=0.0, contributions=None, latency=0.0, bundle=bundle)
            )

    async def shutdown(self) -> None:
        """Cancel every stage, save the Q-table, finish logs, stop drivers — within ~2 s.

        What must not be lost (Q-table, MCAP log) is closed right after the stages are
        cancelled, before waiting on slow stragglers such as an inference still running in
        its worker thread; ``lingering`` lists what had not finished when the budget ran out.
        """
        self.notifier.stopping()
        log.info("stopping")
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SHUTDOWN_TIMEOUT_S
        if tasks:
            await asyncio.wait(tasks, timeout=CANCEL_GRACE_S)
        for closer in (self.controller, *self.taps):
            await self._close(closer, max(deadline - loop.time(), CANCEL_GRACE_S))
        pending = [t for t in tasks if not t.done()]
        if pending:
            await asyncio.wait(pending, timeout=max(deadline - loop.time(), 0.01))
        self.lingering = [t.get_name() for t in tasks if not t.done()]
        if self.lingering:
            log.warning("stages_still_stopping", tasks=self.lingering)
        self.notifier.close()
        log.info("stopped")

    @staticmethod
    async def _close(component: Any, timeout: float) -> None:
        close = getattr(component, "close", None)
        if close is None:
            return
        try:
            result = close()
            if asyncio.iscoroutine(result):
                await asyncio.wait_for(result, timeout=timeout)
        except Exception:  # one component failing to close must not keep the others open
            log.exception("close_failed", component=type(component).__name__)

    async def _status_loop(self) -> None:
        period = self.profile.telemetry.status_period_s
        stall_s = self.profile.telemetry.watchdog_stall_s
        next_t = self.clock.now() + period
        while True:
            await self.clock.sleep_until(next_t)
            next_t += period
            fields = self.status_fields()
            line = format_line(fields, {n: d.modality for n, d in self.drivers.items()})
            if self.status_sink is not None:
                self.status_sink(fields, line)
            self.notifier.status(line)
            if self.last_flow_t is not None and self.clock.now() - self.last_flow_t < stall_s:
                self.notifier.watchdog()

    def status_fields(self) -> dict[str, Any]:
        drops = {name: q.dropped for name, q in self.frame_queues.items() if q.dropped}
        drops["bundles"] = self.bundles.dropped
        recorder_drops = sum(getattr(tap, "dropped", 0) for tap in self.taps)
        if recorder_drops:
            drops["recorder"] = recorder_drops
        percept = getattr(self.perception, "last", None)
        decision = getattr(self.controller, "last", None)
        action_name = None
        if decision is not None and hasattr(self.controller, "describe_action"):
            action_name = self.controller.describe_action(decision.action)
        return snapshot(
            self.clock.now(), self.drivers, self.synchronizer.last_stats, drops, percept, decision, action_name
        )
