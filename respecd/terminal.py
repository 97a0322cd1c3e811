"""A person at a terminal: a small status panel refreshed in place at the bottom (sensors;
sync, drops and recording; detections, contributions and the action), log lines (warnings,
errors, lifecycle) printed above it, never interleaved with it.

Only used when stdout is a TTY; the JSON stream for machines is written as before. Each
panel line is cut to the terminal's width (a wrapped line could not be redrawn in place).
"""

from __future__ import annotations

import shutil
import sys
import threading
from typing import Any, TextIO

CLEAR_LINE = "\r\x1b[2K"
UP_CLEAR = "\x1b[1A\x1b[2K"
_SECOND = ("sync ", "drops", "rec ")
_THIRD = ("det=", "contrib ", "action ")


def panel(line: str) -> list[str]:
    """The status line's ``" | "`` parts on three lines: sensors / pipeline / perception+control."""
    rows: list[list[str]] = [[], [], []]
    for part in line.split(" | "):
        rows[1 if part.startswith(_SECOND) else 2 if part.startswith(_THIRD) else 0].append(part)
    return [" | ".join(r) for r in rows if r]


class Terminal:
    """The bottom status line and the log lines above it (thread-safe)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self._stream = stream
        self._status: list[str] = []
        self._lock = threading.Lock()
        self._gone = False  # the terminal hung up: nothing more is shown, the daemon goes on (and stops cleanly)

    @property
    def stream(self) -> TextIO:
        return self._stream or sys.stdout

    def _erase(self) -> str:
        """Escape codes that clear the panel and leave the cursor at its first line's start."""
        return CLEAR_LINE + UP_CLEAR * (len(self._status) - 1) + "\r" if self._status else ""

    def log_line(self, text: str) -> None:
        with self._lock:
            self._write(f"{self._erase()}{text}\n" + "\n".join(self._status))

    def status(self, line: str) -> None:
        width = shutil.get_terminal_size((120, 24)).columns
        lines = [row if len(row) < width else row[: max(width - 2, 1)] + "…" for row in panel(line)]
        with self._lock:
            erase, self._status = self._erase(), lines
            self._write(erase + "\n".join(lines))

    def close(self) -> None:
        """Leave the last status on screen, ending its line."""
        with self._lock:
            if self._status:
                self._write("\n")
                self._status = []

    def _write(self, text: str) -> None:
        """Write and flush; a terminal that hung up (EIO) or a closed pipe is left alone from then on:
        a log line must never stop the daemon from saving its table and finishing its log."""
        if self._gone:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # ValueError: the stream was closed
            self._gone = True


TERMINAL = Terminal()


class TerminalLogger:
    """A structlog logger whose lines go above the status line."""

    def __init__(self, *_: Any) -> None:
        pass

    def msg(self, message: str) -> None:
        TERMINAL.log_line(message)

    log = debug = info = warn = warning = error = critical = exception = fatal = msg
