"""SIGTERM, SIGINT and SIGHUP as a stop request, from the first moment of a command to its last.

SIGHUP is a terminal that hung up (an ssh session that dropped under ``respecd --record ...``):
its default action would kill the process with the Q-table unsaved and the log unfinished.

A signal that arrives before the event loop runs (while profiles are read, torch imported,
the checkpoint loaded) is remembered and sets the stop event as soon as one exists, so the
session abandons its start at once instead of acting on the signal after the pipeline is up.
Inside the loop the handlers are the loop's own (``add_signal_handler``), which wake it.
The console script notes signals from its first line (``note_early``), before the second
of imports that building the command line takes: a SIGINT there was a KeyboardInterrupt
traceback, or nothing at all.

A signal the process was started with ignored stays ignored: ``nohup respecd ...`` (SIGHUP)
or a background job of a shell (SIGINT) keeps running as its caller asked, at every moment —
the handlers used to take a SIGINT or SIGHUP after the first second and not before.
"""

from __future__ import annotations

import os
import signal
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import asyncio

SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
_early: list[int] = []  # signals noted before a StopSignals took over (note_early)


def _handled() -> tuple[signal.Signals, ...]:
    """The stop signals this process was not started with ignored."""
    return tuple(sig for sig in SIGNALS if signal.getsignal(sig) is not signal.SIG_IGN)


def note_early() -> None:
    """From the console script's first line: note a stop signal instead of dying of it (or of a
    KeyboardInterrupt) while the command line is built."""
    for sig in _handled():
        signal.signal(sig, lambda signum, frame: _early.append(signum))


def release_early() -> None:
    """A command that is not the daemon or a replay: the signals' usual actions again, and one noted
    meanwhile delivered now."""
    for sig in _handled():
        signal.signal(sig, signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL)
    if _early:
        os.kill(os.getpid(), _early[0])


class StopSignals:
    """``with StopSignals() as signals:`` ... ``stop = signals.bind()`` inside the loop."""

    def __init__(self) -> None:
        self.received: int | None = _early[0] if _early else None
        self._previous: dict[int, Any] = {}
        self._event: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._signals = _handled()

    def __enter__(self) -> StopSignals:
        for sig in self._signals:
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
        import asyncio

        self._loop = asyncio.get_running_loop()
        self._event = asyncio.Event()
        if self.received is not None:
            self._event.set()
        for sig in self._signals:
            self._loop.add_signal_handler(sig, self._note, sig, None)
        return self._event

    def unbind(self) -> None:
        """Give the signals back to the flag-only handler (the loop is about to close)."""
        if self._loop is not None and not self._loop.is_closed():
            for sig in self._signals:
                self._loop.remove_signal_handler(sig)
                if self._previous:  # still inside ``with``: keep noting signals
                    signal.signal(sig, self._note)
        self._loop = None
        self._event = None
