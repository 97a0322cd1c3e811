"""structlog set-up: JSON lines for machines (journald, files), a readable terminal for people.

* JSON (stdout not a TTY, or ``--log-format json``): one object per line, as always. Under
  systemd, when stdout is the journal (``JOURNAL_STREAM`` names it), each event goes to the
  journal's native socket with its fields (``journalctl SENSOR=rgb``, ``respecd.journal``),
  or, where that socket is absent, as a line starting with its syslog priority (``<3>``
  error ... ``<7>`` debug), so ``journalctl -p warning`` filters either way.
* Console: log lines above one refreshed status line (``respecd.terminal``); the per-decision
  and per-apply lines are debug there unless ``-v``.
* Other libraries' logging and Python warnings go through the same renderer; OpenCV's own
  C++ log lines on stderr are read back and logged as ``opencv`` events (``native.py``).
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any, Literal

import structlog

from respecd import journal
from respecd.journal import JOURNAL_SOCKET

LogFormat = Literal["json", "console", "auto"]

# syslog(3) priorities, the prefixes journald reads (sd-daemon(3))
SYSLOG_PRIORITY = {"critical": 2, "exception": 3, "error": 3, "warning": 4, "warn": 4, "info": 6, "debug": 7}
# one line per controller step or driver reconfiguration: for machines, not for a terminal
CHATTY_EVENTS = frozenset({"decision", "sim_apply", "apply_clamped", "uvc_apply", "realsense_apply", "radar_apply"})


def stdout_is_journal(env: dict[str, str] | None = None) -> bool:
    """True when stdout is the journal stream systemd named in ``JOURNAL_STREAM`` (dev:inode)."""
    stream = (env if env is not None else os.environ).get("JOURNAL_STREAM", "")
    device, _, inode = stream.partition(":")
    try:
        st = os.fstat(sys.stdout.fileno())
        return (st.st_dev, st.st_ino) == (int(device), int(inode))
    except (ValueError, OSError, AttributeError):
        return False


def syslog_prefix(renderer: Any) -> Any:
    """Wrap a renderer: ``<N>`` + its line, N from the event's level."""

    def render(logger: Any, name: str, event: dict[str, Any]) -> str:
        priority = SYSLOG_PRIORITY.get(str(event.get("level", name)), 6)
        return f"<{priority}>{renderer(logger, name, event)}"

    return render


def drop_chatty(logger: Any, name: str, event: dict[str, Any]) -> dict[str, Any]:
    if event.get("event") in CHATTY_EVENTS:
        raise structlog.DropEvent
    return event


def configure_logging(fmt: LogFormat = "auto", level: str = "info", verbose: bool = False,
                      journal: bool | None = None,
                      journal_socket: str | None = JOURNAL_SOCKET) -> Literal["json", "console"]:
    """Configure structlog and stdlib logging; return the format chosen.

    ``auto`` means JSON when stdout is not a TTY (systemd, pipes), console otherwise.
    ``journal`` (default: detected): stdout is the journal, so JSON events go to
    ``journal_socket`` with their fields when it exists, else as lines prefixed with their
    syslog priority.
    """
    chosen: Literal["json", "console"]
    chosen = ("console" if sys.stdout.isatty() else "json") if fmt == "auto" else fmt
    numeric = logging.DEBUG if verbose else getattr(logging, level.upper(), logging.INFO)
    renderer: Any
    native = False
    if chosen == "json":
        renderer = structlog.processors.JSONRenderer()
        if stdout_is_journal() if journal is None else journal:
            native = journal_socket is not None and os.path.exists(journal_socket)
            renderer = JournalRenderer(renderer) if native else syslog_prefix(renderer)
    else:
        renderer = structlog.dev.ConsoleRenderer()
    shared: list[Any] = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
        structlog.processors.StackInfoRenderer(),
        structlog.processors.format_exc_info if chosen == "json" else structlog.dev.set_exc_info,
    ]
    if chosen == "console" and not verbose:
        shared.insert(0, drop_chatty)
    structlog.configure(
        processors=[*shared, renderer],
        wrapper_class=structlog.make_filtering_bound_logger(numeric),
        logger_factory=_journal_factory(journal_socket) if native and journal_socket else _factory(chosen),
        cache_logger_on_first_use=False,
    )
    _route_stdlib(max(numeric, logging.WARNING) if not verbose else logging.DEBUG)
    return chosen


class JournalRenderer:
    """The JSON line, with the event's fields beside it for the journal logger."""

    def __init__(self, renderer: Any) -> None:
        self._renderer = renderer

    def __call__(self, logger: Any, name: str, event: dict[str, Any]) -> tuple[tuple[str], dict[str, Any]]:
        priority = SYSLOG_PRIORITY.get(str(event.get("level", name)), 6)
        return (self._renderer(logger, name, event),), {"priority": priority, "fields": event}


class JournalLogger:
    """Each event one journal entry (``respecd.journal``); a refused one a ``<N>`` line on stdout."""

    def __init__(self, sender: Any) -> None:
        self._sender = sender
        self._stdout = StdoutLogger(sys.stdout)

    def msg(self, message: str, priority: int = 6, fields: dict[str, Any] | None = None) -> None:
        if not self._sender.send(journal.entry(message, priority, fields or {})):
            self._stdout.msg(f"<{priority}>{message}")

    log = debug = info = warn = warning = error = critical = exception = fatal = msg


def _journal_factory(path: str) -> Any:
    logger = JournalLogger(journal.JournalSender(path))  # one socket for every logger
    return lambda *_: logger


def _factory(chosen: str) -> Any:
    if chosen == "console" and sys.stdout.isatty():
        from respecd.terminal import TerminalLogger

        return TerminalLogger
    return lambda *_: StdoutLogger(sys.stdout)  # sys.stdout as it is at each line (pytest swaps it)


class StdoutLogger(structlog.PrintLogger):
    """structlog's PrintLogger, except that a stdout that went away (the reader of a pipe left, a
    terminal hung up) ends the output, not the daemon: the line is dropped, the caller goes on."""

    def msg(self, message: str) -> None:
        try:
            super().msg(message)
        except (OSError, ValueError):  # BrokenPipeError, EIO; ValueError: the file was closed
            pass

    log = debug = info = warn = warning = error = critical = exception = fatal = msg


class _StructlogHandler(logging.Handler):
    """stdlib records (foxglove-sdk, asyncio, py.warnings) rendered as our own events."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            logger = structlog.get_logger(record.name)
            event = "warning" if record.name == "py.warnings" else record.name
            getattr(logger, record.levelname.lower(), logger.warning)(event, message=record.getMessage())
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


def _route_stdlib(level: int) -> None:
    root = logging.getLogger()
    for handler in list(root.handlers):
        if isinstance(handler, _StructlogHandler):
            root.removeHandler(handler)
    root.addHandler(_StructlogHandler())
    root.setLevel(level)
    logging.captureWarnings(True)  # warnings.warn(...) from any library -> logger "py.warnings"
