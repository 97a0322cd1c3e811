"""What the systemd watchdog means, and what STATUS= says is degraded.

``WATCHDOG=1`` means "the event loop is alive and supervising": every stage task is still
running (supervisors retry absent sensors forever, with backoff), the synchronizer ticks,
and a stage that has input produces output. It does *not* depend on sensors being present:
a robot whose radar is unplugged is degraded, not hung, and restarting the daemon would
only interrupt the drivers' own retries (with all sensors absent the old rule stopped
pinging, and systemd restarted the daemon in a loop). What is merely degraded — a sensor
with no frames, a paused one, a paused recorder — goes into ``STATUS=`` instead.

Fed from the session's hooks; pure bookkeeping on the session clock, no I/O.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from respecd.clock import Clock


class Liveness:
    """Heartbeats of the pipeline's stages, from the session's hooks."""

    def __init__(self, clock: Clock, stall_s: float, decision_budget_s: float) -> None:
        self.clock = clock
        self.stall_s = stall_s
        # how long a stage may hold input without output: the controller may spend a decision
        # period plus the drivers' apply timeout (the radar restarts its chirp) on one decision
        self.budget_s = {"perception": stall_s, "controller": stall_s + decision_budget_s}
        self.started = clock.now()
        self.last_tick: float | None = None
        self.last_frame: dict[str, float] = {}
        self._waiting: dict[str, float | None] = {"perception": None, "controller": None}

    # -- hooks ----------------------------------------------------------------------------
    def on_tick(self, scheduled: float, actual: float) -> None:
        self.last_tick = self.clock.now()

    def on_frame(self, sensor: str, frame: Any) -> None:
        self.last_frame[sensor] = self.clock.now()

    def on_bundle(self, bundle: Any) -> None:
        if bundle.frames:
            self._wait("perception")

    def on_inference(self, percept: Any) -> None:
        self._waiting["perception"] = None

    def on_percept(self, percept: Any) -> None:
        self._wait("controller")

    def on_decision(self, decision: Any) -> None:
        self._waiting["controller"] = None

    def _wait(self, stage: str) -> None:
        if self._waiting[stage] is None:
            self._waiting[stage] = self.clock.now()

    # -- verdicts -------------------------------------------------------------------------
    def stalls(self, tasks: Mapping[str, Any], stages: tuple[str, ...] = ("perception", "controller")) -> list[str]:
        """Why the watchdog must not be fed now; empty when the loop is alive and supervising."""
        now = self.clock.now()
        problems = [f"task {name} ended" for name, task in tasks.items() if task.done()]
        tick_age = now - (self.last_tick if self.last_tick is not None else self.started)
        if tick_age > self.stall_s:
            problems.append(f"synchronizer has not ticked for {tick_age:.0f} s")
        for stage in stages:
            since = self._waiting[stage]
            if since is not None and now - since > self.budget_s[stage]:
                problems.append(f"{stage} has held input without output for {now - since:.0f} s")
        return problems

    def degraded(self, drivers: Mapping[str, Any], applied: Mapping[str, Any],
                 recording: Mapping[str, Any] | None = None, qtable: Mapping[str, Any] | None = None) -> list[str]:
        """What runs below par (for STATUS=): sensors without frames or paused, a paused recorder,
        a Q-table the state directory will not take."""
        now = self.clock.now()
        out = []
        for name, driver in drivers.items():
            if name in applied and not applied[name].enabled:
                continue  # the controller turned it off: intended, not degraded
            last = self.last_frame.get(name)
            age = now - (last if last is not None else self.started)
            if driver.health.paused and age > self.stall_s:
                out.append(f"{name} paused")
            elif age > self.stall_s:
                since = f"for {age:.0f} s" if last is not None else f"since start ({age:.0f} s)"
                error = f": {driver.health.last_error}" if driver.health.last_error else ""
                out.append(f"{name} no frames {since}{error}")
        if recording and recording.get("state") == "paused":
            out.append(f"recording paused ({recording.get('reason')})")
        if qtable:
            out.append(f"Q-table unsaved for {qtable['since_s']:.0f} s ({qtable['error']})")
        return out


def status_text(line: str, degraded: list[str], stalls: list[str]) -> str:
    """STATUS= for systemctl status: what is wrong first, then the status line."""
    lead = []
    if stalls:
        lead.append("STALLED: " + "; ".join(stalls))
    if degraded:
        lead.append("DEGRADED: " + "; ".join(degraded))
    return " | ".join([*lead, line]) if lead else line
