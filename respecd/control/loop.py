"""The one control loop: window -> observation -> decision -> sensors, every decision period.

The daemon, a replay, policy training and the scenario benchmark all run this class. They
differ only in the clock (monotonic, a log's lockstep clock, or one a trainer steps), in
where samples come from (percepts through the feature extractor, or cached detector
outcomes), in the system signals (``LoadProbe``: /proc and sysfs, or a modelled load) and in
the ``Sensors`` decisions go to (drivers, or the simulated sensors' clamping).

What each sensor runs is the session's ``AppliedConfigs``: the loop publishes every answer
a sensor gives to ``apply`` there, and follows the table as messages arrive.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from dataclasses import replace
from typing import Protocol

import structlog

from respecd.applied import AppliedConfigs
from respecd.clock import Clock
from respecd.control.controller import Controller
from respecd.control.features import Sample, Window
from respecd.control.probe import SystemSample
from respecd.messages import Decision, SensorConfig

log = structlog.get_logger(__name__)

STARVED_WARN_AFTER = 5  # empty windows in a row before warning (a slow detector skips some)
NO_SIGNALS = SystemSample(None, None, None)


class Sensors(Protocol):
    """Where decisions go. ``apply`` takes requests by sensor name and answers, per sensor,
    what it really runs now, or None where applying failed (retried at the next decision)."""

    async def apply(self, requests: Mapping[str, SensorConfig]) -> Mapping[str, SensorConfig | None]: ...


class LoadProbe(Protocol):
    """System signals at a decision: CPU / GPU share, board power, detector busy share."""

    async def read(self) -> SystemSample: ...


class ControlLoop:
    """Decides every ``decision_period_s`` on the clock from the samples of the last window."""

    def __init__(self, controller: Controller, clock: Clock, sensors: Sensors, applied: AppliedConfigs,
                 probe: LoadProbe | None = None) -> None:
        self.controller = controller
        self.config = controller.config
        self.clock = clock
        self.sensors = sensors
        self.applied = applied
        self.probe = probe
        self.window = Window(self.config.window_s, self.config.latency_budget_s)
        self.last: Decision | None = None
        self.on_sample: list[Callable[[Sample], None]] = []  # each sample as the window gets it
        self.on_decision: list[Callable[[Decision], None]] = []  # after the sensors answered
        self.on_window: list[Callable[[], None]] = []  # a window closed: perception may attribute next
        self.after_decision: Callable[[Decision], Awaitable[None]] | None = None  # e.g. save the Q-table
        self._requested: dict[str, SensorConfig] = {}
        self._starved = 0  # consecutive decision windows without a sample
        controller.position = controller.space.nearest(applied)
        applied.subscribe(self._on_config)

    def add(self, sample: Sample) -> None:
        """One percept's features (or a cached outcome's), stamped with when it arrived."""
        self.window.add(sample)
        for hook in self.on_sample:
            hook(sample)

    async def run(self) -> None:
        """Forever: sleep to the next decision time on the clock, decide. Cancel to stop."""
        period = self.config.decision_period_s
        next_t = self.clock.now() + period
        while True:
            await self.clock.sleep_until(next_t)
            await self.decide(self.clock.now())
            next_t += period
            if next_t <= self.clock.now():  # fell behind (slow apply): skip, do not burst
                next_t = self.clock.now() + period

    async def decide(self, now: float) -> Decision | None:
        """One decision at ``now``; None when the window held no sample."""
        system = await self.probe.read() if self.probe is not None else NO_SIGNALS
        obs = self.window.observe(now, system.cpu, system.gpu, system.power_w, busy=system.busy)
        self._window_closed()
        if obs.n_percepts == 0:  # nothing new seen: no state, no reward, no learning
            self._starved += 1
            if self._starved == STARVED_WARN_AFTER:
                log.warning("controller_no_percepts", windows=self._starved, window_s=self.config.window_s)
            return None
        if self._starved >= STARVED_WARN_AFTER:
            log.info("controller_percepts_back", after_windows=self._starved)
        self._starved = 0
        decision = self.controller.step(obs)
        decision = replace(decision, configs=await self._apply(decision.configs))
        self.last = decision
        self._publish(decision)
        if self.after_decision is not None:
            await self.after_decision(decision)
        return decision

    def _on_config(self, name: str, applied: SensorConfig) -> None:
        self.controller.follow(self.applied)

    async def _apply(self, requests: tuple[SensorConfig, ...]) -> tuple[SensorConfig, ...]:
        """Send what changed since the last request; publish every answer; what runs now."""
        names = [slot.name for slot in self.controller.space.slots]
        changed = {name: req for name, req in zip(names, requests, strict=True)
                   if name in self.applied and self._requested.get(name) != req}
        answers = await self.sensors.apply(changed) if changed else {}
        for name, result in answers.items():
            if result is not None:
                self._requested[name] = changed[name]
                self.applied.publish(name, result)
        return tuple(self.applied.get(n, r) for n, r in zip(names, requests, strict=True))

    def _publish(self, decision: Decision) -> None:
        for hook in self.on_decision:
            try:
                hook(decision)
            except Exception:  # a broken recorder must not stop control
                log.exception("decision_hook_failed")

    def _window_closed(self) -> None:
        for hook in self.on_window:
            try:
                hook()
            except Exception:
                log.exception("window_hook_failed")
