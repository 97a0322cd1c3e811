"""The controller task: feeds the pure ``Controller`` from percepts and applies its choice.

Two coroutines run under ``run``: one drains the percept queue into the sliding window
(cheap per-percept features), the other wakes every ``decision_period_s`` on the injected
clock, reads system signals (worker thread), steps the controller, applies the new
configuration to every affected driver concurrently (each with a timeout; a failing driver
is logged and the rest proceed; it is retried at the next decision), and publishes the
decision to the taps. The Q-table is loaded when ``run`` first starts and saved every
``save_every`` updates and on ``close``.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import structlog

from respecd.clock import Clock
from respecd.control.config import ControllerConfig
from respecd.control.controller import Controller
from respecd.control.features import FeatureExtractor, Window
from respecd.control.persist import load_into, save_table, table_path
from respecd.control.probe import SystemProbe, SystemSample
from respecd.control.shipped import load_shipped
from respecd.drivers.base import Driver
from respecd.errors import DriverError
from respecd.messages import Decision, Percept, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.sensors import Capabilities

log = structlog.get_logger(__name__)

STARVED_WARN_AFTER = 5  # empty windows in a row before warning (a slow detector skips some)


class ControllerStage:
    """Owns the controller of one run; the daemon constructs it and runs ``run``."""

    def __init__(
        self,
        config: ControllerConfig,
        profile: Any,
        drivers: dict[str, Driver],
        clock: Clock,
        state_dir: Path,
    ) -> None:
        self.config = config
        self.profile = profile
        self.drivers = drivers
        self.clock = clock
        self.controller = Controller.from_profile(config, profile, _capabilities(drivers))
        self.applied: dict[str, SensorConfig] = {name: d.applied for name, d in drivers.items()}
        self.controller.position = self.controller.space.nearest(self.applied)
        self.table_path = table_path(Path(state_dir), config.table_file, profile.name)
        self.last: Decision | None = None
        self.on_decision: list[Callable[[Decision], None]] = []
        self.perception_hint: Callable[[], None] | None = None
        self._features = FeatureExtractor()
        self._window = Window(config.window_s, config.latency_budget_s)
        self._requested: dict[str, SensorConfig] = {}
        self._probe: SystemProbe | None = None
        self._prepared = False
        self._saved_updates = 0
        self._starved = 0  # consecutive decision windows without a percept

    # public ---------------------------------------------------------------------------
    def describe_action(self, action: int) -> str:
        return self.controller.describe_action(action)

    def describe_state(self, bins: tuple[int, ...]) -> str:
        return self.controller.states.describe(bins)

    async def run(self, percepts: DropOldestQueue[Percept]) -> None:
        """Forever: gather percepts, decide every period. Cancel to stop (then ``close``)."""
        await self._prepare()
        tasks = [
            asyncio.create_task(self._consume(percepts), name="controller-percepts"),
            asyncio.create_task(self._decide_forever(), name="controller-decide"),
        ]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in done:
                task.result()  # re-raise a crash for the supervisor
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def close(self) -> None:
        """Save the Q-table (learn mode) so the next start resumes from it."""
        if self._prepared and self.config.policy == "learn":
            await self._save()

    # internals ------------------------------------------------------------------------
    async def _prepare(self) -> None:
        if self._prepared:
            return  # a supervisor restart keeps the learned table in memory
        table = self.controller.table
        if table is not None:
            layout = self.controller.layout()
            loaded = await asyncio.to_thread(load_into, self.table_path, table, layout)
            if not loaded and self.config.policy == "exploit":  # nothing learned here yet: the shipped table
                loaded = await asyncio.to_thread(load_shipped, table, layout)
            self._saved_updates = table.updates
            if not loaded and self.config.policy == "exploit":
                log.warning("exploit_without_table", path=str(self.table_path))
        if self.config.system_probe:
            rails = self.profile.telemetry.power_rails == "auto"
            self._probe = await asyncio.to_thread(SystemProbe, Path("/"), rails)
            await asyncio.to_thread(self._probe.read)  # prime the CPU counters
        self._prepared = True
        log.info(
            "controller_ready",
            policy=self.config.policy,
            states=self.controller.states.size,
            actions=self.controller.space.n,
            table_columns=self.controller.space.columns,
            table=str(self.table_path),
        )

    async def _consume(self, percepts: DropOldestQueue[Percept]) -> None:
        while True:
            percept = await percepts.get()
            # stamped on arrival: with a slow detector percept.t lags the clock by its latency.
            # Features stay on the loop (~0.3 ms for 720p): a thread hop would let a lockstep
            # replay's decision see or miss this percept depending on thread timing.
            self._window.add(self._features.sample(percept, self.clock.now()))

    async def _decide_forever(self) -> None:
        period = self.config.decision_period_s
        next_t = self.clock.now() + period
        while True:
            await self.clock.sleep_until(next_t)
            await self.decide(self.clock.now())
            next_t += period
            if next_t <= self.clock.now():  # fell behind (slow apply): skip, do not burst
                next_t = self.clock.now() + period

    async def decide(self, now: float) -> Decision | None:
        """One decision at ``now``; None when the window held no percept."""
        system = await asyncio.to_thread(self._probe.read) if self._probe else SystemSample(None, None, None)
        obs = self._window.observe(now, system.cpu, system.gpu, system.power_w)
        self._hint()
        if obs.n_percepts == 0:  # nothing new seen: no state, no reward, no learning
            self._starved += 1
            if self._starved == STARVED_WARN_AFTER:
                log.warning("controller_no_percepts", windows=self._starved, window_s=self.config.window_s)
            return None
        if self._starved >= STARVED_WARN_AFTER:
            log.info("controller_percepts_back", after_windows=self._starved)
        self._starved = 0
        decision = self.controller.step(obs, self.applied)
        applied = await self._apply(decision.configs)
        decision = replace(decision, configs=applied)
        self.last = decision
        self._publish(decision)
        await self._maybe_save()
        return decision

    async def _apply(self, requests: tuple[SensorConfig, ...]) -> tuple[SensorConfig, ...]:
        names = [slot.name for slot in self.controller.space.slots]
        changed = {
            name: req
            for name, req in zip(names, requests, strict=True)
            if name in self.drivers and self._requested.get(name) != req
        }
        results = await asyncio.gather(*(self._apply_one(n, r) for n, r in changed.items()))
        for name, result in zip(changed, results, strict=True):
            if result is not None:
                self.applied[name] = result
                self._requested[name] = changed[name]
        return tuple(self.applied.get(n, r) for n, r in zip(names, requests, strict=True))

    async def _apply_one(self, name: str, request: SensorConfig) -> SensorConfig | None:
        try:
            applied = await asyncio.wait_for(self.drivers[name].apply(request), self.config.apply_timeout_s)
        except (DriverError, asyncio.TimeoutError) as err:
            log.warning("apply_failed", sensor=name, error=repr(err))
            return None
        except Exception:  # one driver's bug must not stop the others being configured
            log.exception("apply_crashed", sensor=name)
            return None
        if applied.notes:
            log.info("apply_clamped", sensor=name, notes=list(applied.notes))
        return applied

    def _publish(self, decision: Decision) -> None:
        log.info(
            "decision",
            state=self.describe_state(decision.state),
            action=self.describe_action(decision.action),
            reward=round(decision.reward, 4),
            epsilon=round(decision.epsilon, 4),
            held=bool(decision.terms.get("held")),
            **{k: round(v, 4) for k, v in decision.terms.items() if k not in ("reward", "held")},
        )
        for tap in self.on_decision:
            try:
                tap(decision)
            except Exception:  # a broken recorder must not stop control
                log.exception("decision_tap_failed")

    def _hint(self) -> None:
        if self.perception_hint is not None:
            try:
                self.perception_hint()
            except Exception:
                log.exception("perception_hint_failed")

    async def _maybe_save(self) -> None:
        table = self.controller.table
        if self.config.policy == "learn" and table is not None:
            if table.updates - self._saved_updates >= self.config.save_every:
                await self._save()

    async def _save(self) -> None:
        table = self.controller.table
        if table is None:
            return
        info = {"profile": self.profile.name, "policy": self.config.policy}
        try:
            await asyncio.to_thread(save_table, self.table_path, table, self.controller.layout(), info)
        except OSError as err:
            log.error("qtable_save_failed", path=str(self.table_path), error=str(err))
            return
        self._saved_updates = table.updates
        log.info("qtable_saved", path=str(self.table_path), updates=table.updates)


def _capabilities(drivers: dict[str, Driver]) -> dict[str, Capabilities]:
    caps = {}
    for name, driver in drivers.items():
        with contextlib.suppress(Exception):  # capabilities may need start(); fall back to the profile
            caps[name] = driver.capabilities
    return caps
