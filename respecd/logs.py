"""structlog set-up: JSON lines for machines (journald, files), colours for people."""

from __future__ import annotations

import logging
import sys
from typing import Literal

import structlog

LogFormat = Literal["json", "console", "auto"]


def configure_logging(fmt: LogFormat = "auto", level: str = "info") -> Literal["json", "console"]:
    """Configure structlog and stdlib logging; return the format chosen.

    ``auto`` means JSON when stdout is not a TTY (systemd, pipes), console otherwise.
    """
    chosen: Literal["json", "console"]
    if fmt == "auto":
        chosen = "console" if sys.stdout.isatty() else "json"
    else:
        chosen = fmt
    renderer = structlog.processors.JSONRenderer() if chosen == "json" else structlog.dev.ConsoleRenderer()
    numeric = getattr(logging, level.upper(), logging.INFO)
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.StackInfoRenderer(),
            structlog.processors.format_exc_info if chosen == "json" else structlog.dev.set_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(numeric),
        logger_factory=structlog.PrintLoggerFactory(),  # sys.stdout as it is at each line (pytest swaps it)
        cache_logger_on_first_use=False,
    )
    logging.basicConfig(level=max(numeric, logging.WARNING), stream=sys.stdout, format="%(name)s: %(message)s")
    return chosen
