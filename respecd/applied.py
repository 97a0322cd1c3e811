"""What each sensor runs now: one table, written only with a driver's answer to ``apply``.

A driver answers ``apply`` with what it really applied (clamped, with notes). Whoever asked
publishes that answer here, and every other part (synchronizer, controller, recorder, status
line, replay report) receives it as a message instead of reading a driver's attribute or
keeping its own copy to reconcile.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping

import structlog

from respecd.messages import SensorConfig

log = structlog.get_logger(__name__)

ConfigListener = Callable[[str, SensorConfig], None]


class AppliedConfigs(Mapping[str, SensorConfig]):
    """Sensor name -> the configuration it runs, and the listeners told of every change."""

    def __init__(self, initial: Mapping[str, SensorConfig]) -> None:
        self._current = dict(initial)
        self._listeners: list[ConfigListener] = []

    def __getitem__(self, name: str) -> SensorConfig:
        return self._current[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._current)

    def __len__(self) -> int:
        return len(self._current)

    def subscribe(self, listener: ConfigListener, *, current: bool = True) -> None:
        """Call ``listener(name, applied)`` on every change; ``current``: now, with every
        sensor's present configuration first (the start configuration)."""
        self._listeners.append(listener)
        if current:
            for name, applied in self._current.items():
                self._tell(listener, name, applied)

    def publish(self, name: str, applied: SensorConfig) -> None:
        """A driver applied ``applied``: record it and tell every listener."""
        self._current[name] = applied
        for listener in self._listeners:
            self._tell(listener, name, applied)

    @staticmethod
    def _tell(listener: ConfigListener, name: str, applied: SensorConfig) -> None:
        try:
            listener(name, applied)
        except Exception:  # a broken observer (recorder) must not stop the sensors being configured
            log.exception("config_listener_failed", sensor=name)
