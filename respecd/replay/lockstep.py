"""Lockstep time for ``--speed max``: the clock jumps to the next thing that is due, but only
once everything caused by the previous step has finished, worker threads included.

That makes a replay deterministic: which percepts a decision sees, which frames a tick
pairs, and what every queue drops depend on logged time alone, never on how fast this
machine's detector happens to be. Two pieces:

* ``LockstepLoop`` — an event loop that counts work handed to executors
  (``run_in_executor`` and so ``asyncio.to_thread``), so "a thread is still busy" is
  visible, and callbacks scheduled (``call_soon``, which tasks and futures use), so "one
  pass ran and caused nothing new" is visible without reading the loop's private queue;
* ``LockstepClock`` — a ``ManualClock`` whose sleepers wake one at a time, in (time,
  arrival) order, each after the loop has settled.
"""

from __future__ import annotations

import asyncio
import contextvars
import heapq
import itertools
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from respecd.clock import ManualClock

# While only a worker thread is busy, the loop sleeps until a job finishes (its result
# wakes the loop at once) or this long at most, so a ``done()`` set meanwhile is seen.
# It used to poll every 0.2 ms: 5,000 wakes per second that each took the GIL from the
# detector between two of its operators.
IDLE_WAKE_S = 0.05


class LockstepLoop(asyncio.SelectorEventLoop):
    """Counts executor jobs in flight, and hands their results back in submission order.

    Threads finish in whatever order the machine decides; if results came back in that
    order, the tasks waiting for them would resume (and, say, register their next clock
    sleep) in a different order from run to run, and equal deadlines would break ties
    differently. Delivering in submission order keeps a lockstep replay deterministic.
    """

    def __init__(self) -> None:
        super().__init__()
        self.in_flight = 0
        self.scheduled = 0  # call_soon calls so far: tasks and futures schedule through it
        self._count_lock = threading.Lock()  # worker threads schedule too (call_soon_threadsafe)
        self._jobs: deque[tuple[asyncio.Future[Any], asyncio.Future[Any]]] = deque()
        self._job_done: asyncio.Future[None] | None = None  # one waiter, however many look at it

    def call_soon(self, callback: Callable[..., object], *args: Any,  # type: ignore[override]
                  context: contextvars.Context | None = None) -> asyncio.Handle:
        with self._count_lock:
            self.scheduled += 1
        return super().call_soon(callback, *args, context=context)

    def call_soon_threadsafe(self, callback: Callable[..., object], *args: Any,  # type: ignore[override]
                             context: contextvars.Context | None = None) -> asyncio.Handle:
        with self._count_lock:
            self.scheduled += 1
        return super().call_soon_threadsafe(callback, *args, context=context)

    def run_in_executor(self, executor: Any, func: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:  # type: ignore[override]
        inner = super().run_in_executor(executor, func, *args)
        outer: asyncio.Future[Any] = self.create_future()
        self.in_flight += 1
        self._jobs.append((inner, outer))
        inner.add_done_callback(self._deliver)
        return outer

    def job_finished(self) -> asyncio.Future[None]:
        """A future done when the next executor job finishes (whether or not it is delivered yet)."""
        if self._job_done is None:
            self._job_done = self.create_future()
        return self._job_done

    def _deliver(self, _: asyncio.Future[Any]) -> None:
        """Release every finished job at the head of the submission order."""
        waiter, self._job_done = self._job_done, None
        if waiter is not None and not waiter.done():
            waiter.set_result(None)
        while self._jobs and self._jobs[0][0].done():
            inner, outer = self._jobs.popleft()
            self.in_flight -= 1
            if outer.cancelled():
                continue
            if inner.cancelled():
                outer.cancel()
            elif inner.exception() is not None:
                outer.set_exception(inner.exception())  # type: ignore[arg-type]
            else:
                outer.set_result(inner.result())

    async def drained(self) -> bool:
        """Run one pass of what is runnable now; True if that pass scheduled nothing new.

        A marker callback queued behind everything runnable sees the count of callbacks
        scheduled since it was queued: only itself means every callback ahead of it ran
        and caused no further one.
        """
        queued = self.scheduled + 1
        seen: asyncio.Future[int] = self.create_future()

        def mark() -> None:
            if not seen.done():
                seen.set_result(self.scheduled)

        self.call_soon(mark)
        return await seen == queued


class LockstepClock(ManualClock):
    """Wakes sleepers one at a time in (deadline, arrival) order; ``run`` drives it."""

    def __init__(self, start: float = 0.0) -> None:
        super().__init__(start)
        self._sleepers: list[tuple[float, int, asyncio.Future[None]]] = []
        self._arrival = itertools.count()
        self.steps = 0

    async def sleep_until(self, t: float) -> None:
        if t <= self.now():
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        heapq.heappush(self._sleepers, (t, next(self._arrival), future))
        await future

    def next_deadline(self) -> float | None:
        while self._sleepers and self._sleepers[0][2].done():
            heapq.heappop(self._sleepers)  # cancelled sleepers
        return self._sleepers[0][0] if self._sleepers else None

    def wake_next(self) -> float:
        """Move to the earliest deadline and wake that one sleeper."""
        t, _, future = heapq.heappop(self._sleepers)
        super().set(t)
        future.set_result(None)
        self.steps += 1
        return t

    async def run(
        self,
        until: float,
        on_step: Callable[[float], None] | None = None,
        done: Callable[[], bool] | None = None,
    ) -> None:
        """Drive time to ``until``, until nothing is left to wake, or until ``done()``."""
        loop = asyncio.get_running_loop()
        while True:
            await settle(loop, done)
            deadline = self.next_deadline()
            if deadline is None or deadline > until or (done is not None and done()):
                return
            t = self.wake_next()
            if on_step is not None:
                on_step(t)


async def settle(loop: asyncio.AbstractEventLoop, done: Callable[[], bool] | None = None) -> None:
    """Return once every callback and executor job caused so far has run its course, or
    once ``done()`` (a run that ended does not wait for a job nobody needs any more)."""
    idle_checks = 0
    while idle_checks < 2:  # twice in a row: a callback may schedule one more round
        drained = await loop.drained() if isinstance(loop, LockstepLoop) else await _one_pass()
        if done is not None and done():
            return
        if isinstance(loop, LockstepLoop) and loop.in_flight:
            if drained:
                # only a worker thread is busy: wait for it in real time
                await asyncio.wait([loop.job_finished()], timeout=IDLE_WAKE_S)
            idle_checks = 0
            continue
        idle_checks = idle_checks + 1 if drained else 0


async def _one_pass() -> bool:
    """On a foreign loop there is no count: best effort, one yield counts as settled."""
    await asyncio.sleep(0)
    return True
