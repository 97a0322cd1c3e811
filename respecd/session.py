"""The session: one run of the pipeline built from a profile, and its lifecycle.

Components start in order and stop in reverse (aiohttp's cleanup contexts): the detector and
the Q-table load first, in worker threads and abandoned at once when ``stop`` is set (a bad
checkpoint fails before any file is opened or device touched), then the observers (the
recorder), then the stage tasks (respecd.pipeline). ``stop`` cancels every stage, closes
each component in reverse order within ``SHUTDOWN_TIMEOUT_S`` and collects what failed in
``errors``: one component failing to close never keeps the others open.

A session touches no process-global state, so a replay, a benchmark or a test builds and
runs one as it likes; the live daemon's process chores (GIL switch interval, gc freeze, heap
trim, watchdog, status line) are ``respecd.daemon.Daemon``'s.
"""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import Awaitable, Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import structlog

from respecd.clock import Clock
from respecd.config import Profile
from respecd.drivers.base import DriverContext
from respecd.observe import Hooks, Observer
from respecd.pipeline import Pipeline
from respecd.timeouts import within

log = structlog.get_logger(__name__)

T = TypeVar("T")
SHUTDOWN_TIMEOUT_S = 1.5  # SIGTERM to exit must stay within ~2 s
CANCEL_GRACE_S = 0.3  # stages normally end at once when cancelled


class StartAbandoned(Exception):
    """``stop`` was set while the session was still starting."""


class Session:
    """Builds one pipeline from ``profile``; ``run`` starts it, waits, and stops it."""

    def __init__(
        self,
        profile: Profile,
        clock: Clock,
        context: DriverContext | None = None,
        *,
        policy: str | None = None,
        state_dir: Path | None = None,
        tables: Any = None,
        observers: Iterable[Observer] = (),
        latency_model: Any = None,
        exports: Path | None = None,
    ) -> None:
        """No I/O here: the pipeline is built (drivers' constructors do none), nothing runs.
        ``tables``: control.stage.TableFiles; default: the state directory's table."""
        self.profile = profile
        self.clock = clock
        self.policy = policy
        self.state_dir = state_dir
        self.tables = tables
        self.exports = exports or (state_dir / "exported" if state_dir else None)  # PerceptionStage's exports
        self.hooks = Hooks()
        self.pipeline = Pipeline(profile, clock, context or DriverContext(), self.hooks, latency_model)
        self.observers: list[Observer] = []
        self.errors: list[str] = []  # what failed while stopping (logged with its traceback)
        self.lingering: list[str] = []  # stage tasks still running after shutdown's budget
        self._closers: list[tuple[str, Callable[[], object]]] = []  # in start order
        self._tasks: dict[str, asyncio.Task[None]] = {}  # in start order
        self._running = False
        for observer in observers:
            self.attach(observer)

    @property
    def tasks(self) -> Mapping[str, asyncio.Task[None]]:
        """The running stage tasks by name (empty before start and after stop)."""
        return self._tasks

    def attach(self, observer: Observer) -> None:
        """Tap ``observer`` into every hook it declares; its ``start``/``close`` join the lifecycle."""
        self.hooks.frame.append(observer.on_frame)
        self.hooks.bundle.append(observer.on_bundle)
        self.hooks.percept.append(observer.on_percept)
        self.hooks.decision.append(observer.on_decision)
        self.hooks.config.append(observer.on_config)
        self.observers.append(observer)

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
        try:
            await self._start_stages(stop)
            for observer in self.observers:
                await self._start_observer(observer)
            for name, coro in self.pipeline.tasks().items():
                self._tasks[name] = asyncio.create_task(coro, name=name)
        except BaseException:
            await self.stop()
            raise
        self._running = True
        log.info("pipeline_up", sensors=list(self.pipeline.drivers), profile=self.profile.name)
        for hook in self.hooks.up:
            hook()

    async def _start_stages(self, stop: asyncio.Event | None) -> None:
        """Detector and controller first: a bad checkpoint or an empty action space is a
        start-up error (exit 2) before anything else runs."""
        if self.profile.perception.enabled:
            await self._unless_stopped(self.pipeline.make_perception(self.exports).load(), stop)
        if self.profile.controller.enabled:
            controller = self.pipeline.make_controller(self.policy, self.state_dir, self.tables)
            self._closers.append(("controller", controller.close))
            await self._unless_stopped(controller.prepare(), stop)

    async def _start_observer(self, observer: Observer) -> None:
        result = observer.start()
        if inspect.isawaitable(result):
            await result
        self._closers.append((type(observer).__name__, observer.close))

    async def stop(self) -> None:
        """Cancel every stage, then close components in reverse start order — within ~2 s.

        What must not be lost (Q-table, MCAP log) is closed right after the stages are
        cancelled, before waiting on slow stragglers such as an inference still running in
        its worker thread; ``lingering`` lists what had not finished when the budget ran out.
        Safe to call twice, and after a failed start.
        """
        if self._running:
            log.info("stopping")
            for hook in self.hooks.stopping:
                hook()
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
        self.pipeline.detach()
        self.lingering = [t.get_name() for t in tasks if not t.done()]
        if self.lingering:
            log.warning("stages_still_stopping", tasks=self.lingering)
        if self._running:
            log.info("stopped")
        self._running = False

    async def _close(self, name: str, close: Callable[[], object], timeout: float) -> None:
        try:
            result = close()
            if inspect.isawaitable(result):
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
