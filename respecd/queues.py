"""Bounded queues that never block a producer: when full, the oldest item is dropped.

A stale frame is worth less than a fresh one, so memory stays flat whatever the sensor
rates and however slow inference is. Drops are counted for the status line.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")


class DropOldestQueue(Generic[T]):
    """An asyncio queue of fixed capacity whose ``put`` never waits."""

    def __init__(self, maxsize: int, name: str = "") -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be >= 1")
        self.name = name
        self.maxsize = maxsize
        self.dropped = 0
        self.put_count = 0
        self._items: deque[T] = deque()
        self._waiters: deque[asyncio.Future[None]] = deque()
        self.taps: list[Callable[[T], None]] = []  # observers (recorder, watchdog) called on every put

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: T) -> bool:
        """Append ``item``; return False when an old item had to be dropped for it."""
        self.put_count += 1
        dropped = len(self._items) >= self.maxsize
        if dropped:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._wake_one()
        for tap in self.taps:
            tap(item)
        return not dropped

    def pending(self) -> tuple[T, ...]:
        """The items queued now, in the order ``get`` takes them."""
        return tuple(self._items)

    def get_nowait(self) -> T:
        if not self._items:
            raise asyncio.QueueEmpty
        return self._items.popleft()

    async def get(self) -> T:
        while not self._items:
            waiter = asyncio.get_running_loop().create_future()
            self._waiters.append(waiter)
            try:
                await waiter
            finally:
                if waiter in self._waiters:
                    self._waiters.remove(waiter)
        return self._items.popleft()

    def _wake_one(self) -> None:
        while self._waiters:
            waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return
