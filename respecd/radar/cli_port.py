"""The radar's CLI (config) port: send a line, wait for ``Done`` or an error.

Blocking by design (pyserial); the driver runs it in a worker thread. The out-of-box demo
echoes each command after its ``mmwDemo:/>`` prompt, may print informational lines
(``Ignored: Sensor is already stopped``), and ends with ``Done`` or an error line. After a
boot the first line often arrives with stray bytes in front and is answered "is not
recognized as a CLI command" (ti_mmwave_rospkg #33, #42): ``wake`` sends a throwaway newline
first, and a command answered "not recognized" is retried. Text the demo prints on its own
(a crash report, "Obj Det DPC Exception") is read and logged before each command, never
flushed away. A command that gets no ``Done`` is a timeout; ``profileCfg``/``chirpCfg``
are never re-sent after one, because the demo appends them: the caller restarts the whole
sequence from ``sensorStop`` + ``flushCfg`` instead.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal, Protocol

import structlog

from respecd.errors import DriverIOError, DriverTimeoutError

log = structlog.get_logger(__name__)

PROMPT = "mmwDemo:/>"
Verdict = Literal["done", "error", "info"]
_ERRORS = ("error", "invalid usage", "exception", "is not recognized", "failed")
SLOW_COMMANDS = {"sensorStart": 4.0, "sensorStop": 2.0}  # timeout multipliers: RF calibration, frame end
APPENDING = frozenset({"profileCfg", "chirpCfg"})  # a second copy adds a profile/chirp instead of replacing it


class CliRejectedError(DriverIOError):
    """The demo answered a command with an error: the same line will be refused again."""


class SerialLike(Protocol):
    """What CliPort needs of ``serial.Serial``."""

    timeout: float | None

    @property
    def in_waiting(self) -> int: ...

    def write(self, data: bytes) -> int | None: ...

    def read(self, size: int = 1) -> bytes: ...

    def readline(self) -> bytes: ...


def classify(line: str) -> tuple[Verdict, str]:
    """Verdict of one reply line (prompt stripped): done, error, or info (echo, notes)."""
    text = line.replace(PROMPT, "").strip()
    lowered = text.lower()
    if lowered == "done":
        return "done", text
    if any(word in lowered for word in _ERRORS) and not lowered.startswith("ignored"):
        return "error", text
    return "info", text


@dataclass
class Reply:
    """One command's outcome: the lines it printed and how long it took."""

    command: str
    verdict: Verdict
    lines: list[str] = field(default_factory=list)
    seconds: float = 0.0
    attempts: int = 1


class CliPort:
    """Line-in, ``Done``-out state machine over a serial port."""

    def __init__(self, port: SerialLike, timeout_s: float = 1.0, retries: int = 2) -> None:
        self.port = port
        self.timeout_s = timeout_s
        self.retries = retries
        self.port.timeout = min(0.1, timeout_s)  # readline granularity; deadlines are ours

    def wake(self) -> list[str]:
        """Log what is pending, send a throwaway newline, take whatever comes back (boot garbage, prompt)."""
        self.drain("wake")
        self.port.write(b"\n")
        lines = self._read_until(time.monotonic() + min(0.3, self.timeout_s), stop_on_verdict=False)
        self.drain("wake")
        return lines

    def drain(self, before: str) -> list[str]:
        """Read (never discard unseen) what the demo printed on its own; log it when it says something."""
        text = b""
        while self.port.in_waiting:
            text += self.port.read(self.port.in_waiting)
        lines = [line.strip() for line in text.decode("ascii", errors="replace").splitlines()]
        lines = [line for line in lines if line and line != PROMPT and line.isprintable()]
        if lines:
            alarming = any(classify(line)[0] == "error" for line in lines)
            (log.warning if alarming else log.info)("radar.cli_output", before=before, lines=lines[-20:])
        return lines

    def command(self, command: str) -> Reply:
        """Send one command; retry on "not recognized" (and on timeout unless it appends); raise otherwise."""
        name = command.split()[0]
        factor = SLOW_COMMANDS.get(name, 1.0)
        started = time.monotonic()
        for attempt in range(1, self.retries + 2):
            self.drain(name)  # a crash report or a late "Done" must not answer this command
            self.port.write(command.encode("ascii") + b"\n")
            lines = self._read_until(time.monotonic() + self.timeout_s * factor)
            verdict = classify(lines[-1])[0] if lines else None
            if verdict == "done":
                return Reply(command, "done", lines, time.monotonic() - started, attempt)
            if verdict == "error" and not _garbled(lines):
                raise CliRejectedError(f"radar CLI rejected {command!r}: {classify(lines[-1])[1]}")
            if verdict is None or verdict == "info":
                if name in APPENDING:
                    break  # it may have been applied: re-sending would add a second one
            log.debug("radar.cli_retry", command=command, attempt=attempt, reply=lines[-3:])
        if lines and _garbled(lines):
            raise DriverIOError(f"radar CLI did not recognize {command!r} {self.retries + 1} times: {lines[-1]}")
        heard = f" (heard only {lines[-1]!r})" if lines else ""
        raise DriverTimeoutError(f"radar CLI gave no Done for {command!r} within {self.timeout_s * factor:g} s{heard}")

    def send_config(self, commands: Iterable[str]) -> list[Reply]:
        """Send a whole cfg in order; stop at the first command that fails (the caller restarts it)."""
        return [self.command(line) for line in commands]

    def _read_until(self, deadline: float, stop_on_verdict: bool = True) -> list[str]:
        lines: list[str] = []
        while time.monotonic() < deadline:
            raw = self.port.readline()
            if not raw:
                continue
            line = raw.decode("ascii", errors="replace").strip()
            if not line or line == PROMPT:
                continue
            lines.append(line)
            if stop_on_verdict and classify(line)[0] != "info":
                break
        return lines


def _garbled(lines: list[str]) -> bool:
    """Stray bytes before the command: the demo says it does not know it. Worth a retry."""
    return any("is not recognized" in line for line in lines)
