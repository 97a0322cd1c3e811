"""The radar's health as a small state machine, logged once per change.

A radar that is present but misbehaving (a silent or garbage data port, a CLI that rejects
or never answers) must not write a line per retry: ``OutageLog`` writes one warning when an
outage begins, the retries at debug level, and one info line when packets flow again. A
cause that changes kind later in the outage (ports gone, then back but the CLI silent) is an
info line; the first reconnect attempt's own cause (an unplug is a read error, then absent
ports a millisecond later) is the same event seen from the other side and stays at debug.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any


@dataclass
class OutageLog:
    """Log-once bookkeeping for one sensor's outages."""

    log: Any  # a bound structlog logger
    kind: str | None = None  # cause of the outage in progress (exception class or "stall"); None: healthy
    since: float = 0.0
    attempts: int = 0
    history: list[str] = field(default_factory=list)  # kinds seen, for tests and the status line

    @property
    def active(self) -> bool:
        return self.kind is not None

    def trouble(self, kind: str, error: str, retry_in_s: float) -> None:
        """The outage began (a warning) or an attempt failed (debug; info if the cause changed kind)."""
        self.attempts += 1
        fields = {"cause": kind, "error": error, "retry_in_s": round(retry_in_s, 3), "attempt": self.attempts}
        if self.kind is None:
            self.since = time.monotonic()
            self.kind = kind
            self.history.append(kind)
            self.log.warning("radar.lost", **fields)
            return
        if kind == self.kind or self.attempts <= 2:  # the first attempt right after the loss: same event
            self.kind = kind
            self.log.debug("radar.retry", **fields)
            return
        self.kind = kind
        self.history.append(kind)
        self.log.info("radar.still_lost", **fields)

    def back(self, **fields: Any) -> None:
        """Packets flow again: one info line with how long it took."""
        if self.kind is None:
            return
        self.log.info("radar.back", after_s=round(time.monotonic() - self.since, 2), attempts=self.attempts, **fields)
        self.kind, self.attempts = None, 0
