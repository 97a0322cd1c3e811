"""A timeout that never loses a cancellation.

On Python <= 3.11 ``asyncio.wait_for`` returns the inner result, or raises the inner error, when
a cancellation lands in the same loop iteration as the inner call completes (CPython gh-86296,
fixed in 3.12). A cancelled stage then carries on: the supervisor of a radar whose
``sensorStart`` was just rejected took the rejection for a failure and retried forever instead
of stopping, and a driver's watch task that misses its cancel keeps ``stop()`` — and SIGTERM —
waiting. ``within`` waits with ``asyncio.wait``, which always lets the caller's cancellation
through. ``asyncio.wait_for`` is banned in respecd/ and drivers/ by the lint (pyproject.toml).
``reap`` is the same care for the other common way to lose one: ``with suppress(CancelledError):
await child`` after ``child.cancel()`` also swallows a cancellation of the caller.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import TypeVar

T = TypeVar("T")


async def within(work: Awaitable[T], timeout: float | None) -> T:
    """``work``'s result; ``asyncio.TimeoutError`` after ``timeout`` seconds (``work`` is then
    cancelled and allowed to unwind, as ``wait_for`` does). The caller's cancellation always wins:
    ``work`` is cancelled and ``CancelledError`` raised, even if ``work`` had just finished."""
    inner = asyncio.ensure_future(work)
    try:
        done, _ = await asyncio.wait({inner}, timeout=timeout)
    except asyncio.CancelledError:
        inner.cancel()
        raise
    if not done:
        inner.cancel()
        await asyncio.wait({inner})  # not ``await inner``: that would swallow our own cancellation
        raise asyncio.TimeoutError(f"no result within {timeout:g} s")
    return inner.result()


async def reap(task: asyncio.Task[object]) -> None:
    """Cancel ``task`` and wait until it has ended, whatever it ends with (its error is its own
    business: a watch loop being stopped). Unlike awaiting it under ``suppress(CancelledError)``,
    a cancellation of the caller while ``task`` unwinds still reaches the caller."""
    task.cancel()
    await asyncio.wait({task})
