"""SIGTERM, SIGINT and SIGHUP as a stop request, from the first moment of a command to its last.

SIGHUP is a terminal that hung up (an ssh session that dropped under ``respecd --record ...``):
its default action would kill the process with the Q-table unsaved and the log unfinished.

A signal that arrives before the event loop runs (while profiles are read, torch imported,
the checkpoint loaded) is remembered and sets the stop event as soon as one exists, so the
session abandons its start at once instead of acting on the signal after the pipeline is up.
Inside the loop the handlers are the loop's own (``add_signal_handler``), which wake it.
"""

from __future__ import annotations

import asyncio
import signal
from types import FrameType, TracebackType
from typing import Any

SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


class StopSignals:
    """``with StopSignals() as signals:`` ... ``stop = signals.bind()`` inside the loop."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[int, Any] = {}
        self._event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def __enter__(self) -> StopSignals:
        for sig in SIGNALS:
            self._previous[sig] = signal.signal(sig, self._note)
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None) -> None:
        self.unbind()
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()

    def _note(self, signum: int, frame: FrameType | None) -> None:
        self.received = signum
        if self._event is not None and self._loop is not None:
            self._loop.call_soon_threadsafe(self._event.set)

    def bind(self) -> asyncio.Event:
        """The stop event for the running loop (already set when a signal came earlier)."""
        self._loop = asyncio.get_running_loop()
        self._event = asyncio.Event()
        if self.received is not None:
            self._event.set()
        for sig in SIGNALS:
            self._loop.add_signal_handler(sig, self._note, sig, None)
        return self._event

    def unbind(self) -> None:
        """Give the signals back to the flag-only handler (the loop is about to close)."""
        if self._loop is not None and not self._loop.is_closed():
            for sig in SIGNALS:
                self._loop.remove_signal_handler(sig)
                if self._previous:  # still inside ``with``: keep noting signals
                    signal.signal(sig, self._note)
        self._loop = None
        self._event = None
