"""How a running session is watched: its declared hooks, and the ``Observer`` protocol.

Observers (the recorder, a replay's report collector) and the daemon's chores attach here,
never by replacing a running component's queues or callbacks. Every callable returns at
once: it runs on the event loop, between the stages.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Protocol

from respecd.messages import Bundle, Decision, Frame, Percept, SensorConfig


@dataclass
class Hooks:
    """The declared observation points of a running session."""

    frame: list[Callable[[str, Frame], None]] = field(default_factory=list)  # (sensor name, frame)
    bundle: list[Callable[[Bundle], None]] = field(default_factory=list)
    inference: list[Callable[[Percept], None]] = field(default_factory=list)  # as the detector produced it
    percept: list[Callable[[Percept], None]] = field(default_factory=list)  # as the controller gets it
    decision: list[Callable[[Decision], None]] = field(default_factory=list)
    config: list[Callable[[str, SensorConfig], None]] = field(default_factory=list)  # start config, then changes
    tick: list[Callable[[float, float], None]] = field(default_factory=list)  # synchronizer (scheduled, actual)
    up: list[Callable[[], None]] = field(default_factory=list)  # every component started: the pipeline runs
    stopping: list[Callable[[], None]] = field(default_factory=list)  # a started session begins to stop


class Observer(Protocol):
    """What ``Session.attach`` takes: taps on every frame, bundle, percept, decision and applied
    configuration, and a place in the lifecycle (``start`` before the stages run, ``close`` in
    reverse start order, each awaited when it returns an awaitable)."""

    def start(self) -> object: ...

    def close(self) -> Awaitable[None] | None: ...

    def on_frame(self, sensor_name: str, frame: Frame) -> None: ...

    def on_bundle(self, bundle: Bundle) -> None: ...

    def on_percept(self, percept: Percept) -> None: ...

    def on_decision(self, decision: Decision) -> None: ...

    def on_config(self, sensor_name: str, applied: SensorConfig) -> None: ...
