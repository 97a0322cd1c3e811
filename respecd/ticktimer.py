"""The synchronizer's wake-up at its tick's deadline, to the microsecond rather than the millisecond.

asyncio's timers wait in ``epoll_wait``, whose timeout is whole milliseconds rounded up: a tick
due at 12.3 ms from now wakes at 13 ms, 0.5 ms late on average and up to 1 ms, before the
machine adds any lateness of its own — half the synchronizer's 2 ms jitter budget gone to
rounding. A ``timerfd`` armed for the absolute deadline on ``CLOCK_MONOTONIC`` (what
``time.monotonic`` reads on Linux) becomes readable at the deadline itself, and the loop's
``epoll_wait`` returns for it as for any other file descriptor: the tick needs no thread of its
own and no extra GIL hand-off.

``timerfd`` is Linux's; ``os.timerfd_create`` comes with Python 3.13, so libc's is called
through ctypes. Elsewhere, on a loop without ``add_reader``, or for a clock that is not the
monotonic wall clock (a lockstep replay's, a test's manual one), ``sleep_until`` is the
clock's own.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import os
import sys
from functools import cache
from typing import Any

import structlog

from respecd.clock import Clock

log = structlog.get_logger(__name__)

CLOCK_MONOTONIC = 1
TFD_NONBLOCK = os.O_NONBLOCK
TFD_CLOEXEC = os.O_CLOEXEC
TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


@cache
def _libc() -> Any:
    """libc with timerfd_create/timerfd_settime typed, or None (not Linux, no such symbols)."""
    if not sys.platform.startswith("linux"):
        return None
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    if not hasattr(libc, "timerfd_create") or not hasattr(libc, "timerfd_settime"):
        return None
    libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.timerfd_create.restype = ctypes.c_int
    libc.timerfd_settime.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Itimerspec),
                                     ctypes.POINTER(_Itimerspec)]
    libc.timerfd_settime.restype = ctypes.c_int
    return libc


class TickTimer:
    """``sleep_until(t)`` on ``clock``, woken by a timerfd where the clock maps onto CLOCK_MONOTONIC.

    One file descriptor for the timer's life; ``close`` releases it (the synchronizer's task
    does, when it ends). Not for concurrent sleepers: one tick source waits on it at a time.
    """

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self._monotonic_at = getattr(clock, "monotonic_at", None)  # clock time -> time.monotonic()
        self._fd: int | None = None
        self._waiter: asyncio.Future[None] | None = None
        self._libc: Any = None
        libc = _libc()
        if libc is not None and self._monotonic_at is not None:
            fd = libc.timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
            if fd >= 0:
                self._fd, self._libc = fd, libc
            else:
                log.info("tick_timer_unavailable", reason=os.strerror(ctypes.get_errno()))

    @property
    def precise(self) -> bool:
        """Whether deadlines are kept by a timerfd (else by the clock's own, ms-rounded, sleep)."""
        return self._fd is not None

    async def sleep_until(self, t: float) -> None:
        """Return once ``clock.now() >= t``."""
        loop = asyncio.get_running_loop()
        if self._fd is None or self._monotonic_at is None:
            await self.clock.sleep_until(t)
            return
        if t <= self.clock.now():
            return
        self._arm(self._monotonic_at(t))
        self._waiter = loop.create_future()
        try:
            loop.add_reader(self._fd, self._expired)
        except NotImplementedError:  # a loop without file-descriptor readers: the clock's own sleep
            self.close()
            await self.clock.sleep_until(t)
            return
        try:
            await self._waiter
        finally:
            loop.remove_reader(self._fd)
            self._waiter = None

    def close(self) -> None:
        """Release the timer's file descriptor; ``sleep_until`` then falls back to the clock's."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    def _arm(self, monotonic_deadline: float) -> None:
        spec = _Itimerspec()
        whole, frac = divmod(monotonic_deadline, 1.0)
        spec.it_value.tv_sec, spec.it_value.tv_nsec = int(whole), max(int(frac * 1e9), 1)  # all zero disarms
        if self._libc.timerfd_settime(self._fd, TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")

    def _expired(self) -> None:
        assert self._fd is not None
        try:
            os.read(self._fd, 8)  # the expiration count; reading it re-arms readability
        except BlockingIOError:
            return  # woken for nothing (re-armed meanwhile): wait on
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)
