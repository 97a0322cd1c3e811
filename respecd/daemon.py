"""The live daemon's process chores around one ``Session`` (as aiohttp's ``run_app`` around its runner).

A session is the pipeline's lifecycle and leaves the process alone. ``respecd`` (live) runs it
through ``Daemon``, which adds what the process on a robot needs, and undoes what it set when
the run ends:

- the GIL switch interval at ``GIL_SWITCH_INTERVAL_S`` while the session runs;
- the loop's thread in real-time scheduling where permitted (``sync.realtime_priority``,
  respecd.priority), so a busy neighbour process does not delay the synchronizer's ticks;
- start-up's objects frozen out of the collector's sight once the pipeline is up (respecd.gcfreeze);
- the C heap's freed pages handed back every ``HEAP_TRIM_PERIOD_S`` (respecd.heap);
- sd_notify: READY=1, STATUS= with the status line every ``telemetry.status_period_s``,
  WATCHDOG=1 while the loop is alive and supervising (respecd.liveness), STOPPING=1;
- OpenCV's own stderr lines relayed into the log (respecd.native).

SIGTERM/SIGINT/SIGHUP are noted from the command's first moment (respecd.signals) and reach
``run`` as its ``stop`` event.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable, Coroutine
from typing import Any

import structlog

from respecd import heap, priority
from respecd.gcfreeze import StartupFreeze
from respecd.liveness import Liveness, status_text
from respecd.sdnotify import Notifier
from respecd.session import Session
from respecd.status import format_line, pipeline_fields

log = structlog.get_logger(__name__)

# Worker threads (renders, decoding, torch glue) hold the GIL for up to the switch interval
# before the loop thread may run; CPython's 5 ms default alone would break the 30 Hz tick's
# jitter budget, so the daemon asks for 1 ms; 0.5 ms measured no better (docs/PERFORMANCE.md).
GIL_SWITCH_INTERVAL_S = 0.001
HEAP_TRIM_PERIOD_S = 30.0  # session-clock seconds between malloc_trim calls

StatusSink = Callable[[dict[str, Any], str], None]


class Daemon:
    """Runs ``session`` with the live daemon's chores; ``recorder``: its fields join the status line."""

    def __init__(self, session: Session, *, notifier: Notifier | None = None, status_sink: StatusSink | None = None,
                 recorder: Any = None, relay_stderr: bool = False, trim_period_s: float = HEAP_TRIM_PERIOD_S) -> None:
        self.session = session
        self.notifier = notifier or Notifier(address="")
        self.status_sink = status_sink
        self.recorder = recorder
        self.relay_stderr = relay_stderr
        self.trim_period_s = trim_period_s
        controller = session.profile.controller
        self.liveness = Liveness(session.clock, session.profile.telemetry.watchdog_stall_s,
                                 controller.decision_period_s + controller.apply_timeout_s)
        hooks, live = session.hooks, self.liveness
        hooks.frame.append(live.on_frame)
        hooks.bundle.append(live.on_bundle)
        hooks.inference.append(live.on_inference)
        hooks.percept.append(live.on_percept)
        hooks.decision.append(live.on_decision)
        hooks.tick.append(live.on_tick)
        hooks.up.append(self._up)
        hooks.stopping.append(self._stopping)
        self._chores: dict[str, asyncio.Task[None]] = {}
        self._withheld: list[str] = []  # why the watchdog is not fed, as last logged
        self._freeze = StartupFreeze()
        self.loop_scheduling = "normal: not running"  # what the loop's thread runs as (priority.realtime_loop)

    async def run(self, duration: float | None = None, stop: asyncio.Event | None = None) -> None:
        """``Session.run`` with the chores; the switch interval and the frozen objects restored after."""
        from respecd.native import StderrRelay

        relay = StderrRelay() if self.relay_stderr else None
        previous = sys.getswitchinterval()
        sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
        self.loop_scheduling, restore_scheduling = priority.realtime_loop(self.session.profile.sync.realtime_priority)
        log.info("loop_scheduling", runs_as=self.loop_scheduling)
        if relay is not None:
            relay.start()
        try:
            await self.session.run(duration, stop)
        finally:
            self._cancel_chores()
            await asyncio.gather(*self._chores.values(), return_exceptions=True)
            self.notifier.close()
            self._freeze.release()
            restore_scheduling()
            sys.setswitchinterval(previous)
            if relay is not None:
                relay.stop()

    def _up(self) -> None:
        self._freeze.up()
        self.notifier.ready(status="pipeline up")
        self._spawn("status", self._status_loop())
        if heap.available():
            self._spawn("heap-trim", self._heap_trim_loop())
        if self.notifier.enabled:
            self._spawn("watchdog", self._watchdog_loop())

    def _stopping(self) -> None:
        self.notifier.stopping()
        self._cancel_chores()

    def _cancel_chores(self) -> None:
        for task in self._chores.values():
            task.cancel()

    def _spawn(self, name: str, coro: Coroutine[Any, Any, None]) -> None:
        self._chores[name] = asyncio.create_task(coro, name=name)

    def stalls(self) -> list[str]:
        """Why the watchdog must not be fed (respecd.liveness); empty while alive and supervising."""
        stages = ("perception", "controller") if self.session.pipeline.controller is not None else ("perception",)
        tasks = {**self.session.tasks, **{n: t for n, t in self._chores.items() if n != "watchdog"}}
        return self.liveness.stalls(tasks, stages)

    def status_fields(self) -> dict[str, Any]:
        """The status line's fields, with what is degraded and what stalls."""
        pipeline = self.session.pipeline
        recording = self.recorder.recording_status() if self.recorder is not None else None
        fields = pipeline_fields(pipeline, getattr(self.recorder, "dropped", 0), recording)
        fields["degraded"] = self.liveness.degraded(pipeline.drivers, pipeline.applied, recording, fields.get("qtable"))
        fields["stalled"] = self.stalls()
        return fields

    async def _status_loop(self) -> None:
        clock = self.session.clock
        period = self.session.profile.telemetry.status_period_s
        next_t = clock.now() + period
        while True:
            await clock.sleep_until(next_t)
            next_t += period
            fields = self.status_fields()
            line = format_line(fields, {n: d.modality for n, d in self.session.pipeline.drivers.items()})
            line = status_text(line, fields["degraded"], fields["stalled"])
            if self.status_sink is not None:
                self.status_sink(fields, line)
            self.notifier.status(line)

    async def _heap_trim_loop(self) -> None:
        """Hand freed C-heap pages back to the kernel every ``trim_period_s`` (respecd.heap).

        Torch's and the recorder's buffers come and go at sizes that change with the sensors' settings,
        and glibc keeps the pages they free: untrimmed, RSS grows in steps while the bytes in use stay
        flat. The trim runs in a worker thread; what it saves and costs: docs/PERFORMANCE.md "soak".
        """
        clock = self.session.clock
        next_t = clock.now() + self.trim_period_s
        while True:
            await clock.sleep_until(next_t)
            next_t += self.trim_period_s
            await asyncio.to_thread(heap.trim)

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
