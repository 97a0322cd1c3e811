"""A person at a terminal: one status line refreshed in place at the bottom, log lines
(warnings, errors, lifecycle) printed above it, never interleaved with it.

Only used when stdout is a TTY; the JSON stream for machines is written as before. The
status line is cut to the terminal's width (a wrapped line could not be redrawn in place).
"""

from __future__ import annotations

import shutil
import sys
import threading
from typing import Any, TextIO

CLEAR_LINE = "\r\x1b[2K"


class Terminal:
    """The bottom status line and the log lines above it (thread-safe)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self._stream = stream
        self._status = ""
        self._lock = threading.Lock()

    @property
    def stream(self) -> TextIO:
        return self._stream or sys.stdout

    def log_line(self, text: str) -> None:
        with self._lock:
            prefix = CLEAR_LINE if self._status else ""
            self.stream.write(f"{prefix}{text}\n{self._status}")
            self.stream.flush()

    def status(self, line: str) -> None:
        width = shutil.get_terminal_size((120, 24)).columns
        line = line if len(line) < width else line[: max(width - 2, 1)] + "…"
        with self._lock:
            self._status = line
            self.stream.write(CLEAR_LINE + line)
            self.stream.flush()

    def close(self) -> None:
        """Leave the last status on screen, on its own line."""
        with self._lock:
            if self._status:
                self.stream.write("\n")
                self.stream.flush()
                self._status = ""


TERMINAL = Terminal()


class TerminalLogger:
    """A structlog logger whose lines go above the status line."""

    def __init__(self, *_: Any) -> None:
        pass

    def msg(self, message: str) -> None:
        TERMINAL.log_line(message)

    log = debug = info = warn = warning = error = critical = exception = fatal = msg
