"""Keep stages alive: restart what crashes, with exponential backoff and a rate limit.

A failure the driver diagnosed itself (a ``DriverError``: "not ready, retry later", a
device that rejects or never answers a command) is one warning line when it starts or its
cause changes, with the delay before the next try, and debug lines for the retries: no
traceback, because the message already says what is wrong. Any other exception is a bug
and is logged with its traceback every time.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import structlog

from respecd.clock import Clock, MonotonicClock
from respecd.drivers.base import Driver
from respecd.errors import DriverError
from respecd.messages import Frame

log = structlog.get_logger(__name__)

IMAGE_MODALITIES = frozenset({"rgb", "thermal", "depth"})


@dataclass(frozen=True, slots=True)
class Backoff:
    """Exponential backoff: ``initial_s`` doubling up to ``max_s``; reset after ``stable_s`` of health."""

    initial_s: float = 0.5
    max_s: float = 30.0
    stable_s: float = 30.0
    max_restarts: int = 10  # within ``window_s``; beyond it the delay stays at ``max_s``
    window_s: float = 300.0

    def delay(self, attempt: int, recent_restarts: int) -> float:
        if recent_restarts >= self.max_restarts:
            return self.max_s
        return min(self.initial_s * (2 ** max(attempt - 1, 0)), self.max_s)


def driver_backoff(driver: Driver) -> Backoff:
    """The restart backoff for a driver: its own ``reconnect_initial_s``/``reconnect_max_s`` where its
    profile entry has them (the radar's reconnect settings then also cover a board absent at start),
    else the default."""
    config = driver.config
    initial = getattr(config, "reconnect_initial_s", None)
    cap = getattr(config, "reconnect_max_s", None)
    if initial is None and cap is None:
        return Backoff()
    default = Backoff()
    initial_s = float(initial) if initial is not None else default.initial_s
    max_s = float(cap) if cap is not None else default.max_s
    return Backoff(initial_s=min(initial_s, max_s), max_s=max_s)


async def supervise(
    name: str,
    run_once: Callable[[], Awaitable[None]],
    *,
    backoff: Backoff = Backoff(),
    clock: Clock | None = None,
    on_restart: Callable[[BaseException], None] | None = None,
) -> None:
    """Run ``run_once`` forever; when it raises (or returns), wait and run it again."""
    wall = clock or MonotonicClock()
    restarts: deque[float] = deque()
    attempt = 0
    known: tuple[type, str] | None = None  # the driver-diagnosed cause already logged
    while True:
        started = wall.now()
        try:
            await run_once()
            error: BaseException = RuntimeError("stage returned")
        except asyncio.CancelledError:
            raise
        except Exception as err:  # supervisor boundary: logged below, then restart
            error = err
        now = wall.now()
        attempt = 1 if now - started > backoff.stable_s else attempt + 1
        restarts.append(now)
        while restarts and restarts[0] < now - backoff.window_s:
            restarts.popleft()
        if on_restart is not None:
            on_restart(error)
        delay = backoff.delay(attempt, len(restarts))
        known = _log_failure(name, error, delay, attempt, known)
        await asyncio.sleep(delay)


def _log_failure(
    name: str, error: BaseException, delay: float, attempt: int, known: tuple[type, str] | None
) -> tuple[type, str] | None:
    """One line per new cause (no traceback for a driver's own diagnosis); the retries at debug."""
    retry = {"stage": name, "retry_in_s": round(delay, 2), "attempt": attempt}
    if isinstance(error, DriverError):
        cause = (type(error), _kind(error))
        if cause != known:
            event = "unavailable" if type(error).__name__ == "DriverUnavailableError" else "driver_failed"
            log.warning(event, error=str(error), **retry)
        else:
            log.debug("stage_retry", error=str(error), **retry)
        return cause
    if isinstance(error, RuntimeError) and str(error) == "stage returned":
        log.warning("stage_returned", **retry)
    else:
        log.error("stage_crashed", exc_info=error, **retry)
    return None


def _kind(error: BaseException) -> str:
    """The message without its numbers: "no packets for 3.1 s" and "... 6.2 s" are one cause."""
    return "".join(ch for ch in str(error) if not ch.isdigit())


def driver_runner(driver: Driver, sink: Callable[[Frame], None]) -> Callable[[], Awaitable[None]]:
    """One life of a driver: start, stream frames into ``sink``, always stop on the way out.

    A stream that ended by itself (``driver.finished``: a video file or recording without ``loop``
    played to its end; the driver logs that once) stays ended until cancelled, instead of returning
    to ``supervise``, which would warn ``stage_returned`` and play it again after each backoff."""

    async def run_once() -> None:
        try:
            await driver.start()
            log.info("driver_started", sensor=driver.name, driver=driver.key)
            async for frame in driver.frames():
                driver.health.frame(frame.t, frame.shape if frame.modality in IMAGE_MODALITIES else None)
                sink(frame)
        except BaseException as err:
            if not isinstance(err, asyncio.CancelledError):
                driver.health.error(err)
                driver.health.restarts += 1
            raise
        finally:
            await _stop_quietly(driver)
        if driver.finished:
            log.debug("driver_finished", sensor=driver.name)
            await asyncio.Event().wait()  # until the session cancels the stage

    return run_once


async def _stop_quietly(driver: Driver) -> None:
    """Stop within 2 s. ``asyncio.wait``, not ``wait_for``: on Python <= 3.11 wait_for loses a
    cancellation that arrives as the inner call finishes, and the supervise loop then never ends."""
    stopping = asyncio.ensure_future(driver.stop())
    done, _ = await asyncio.wait({stopping}, timeout=2.0)
    if not done:
        stopping.cancel()
        log.error("driver_stop_failed", sensor=driver.name, error="stop took longer than 2 s")
    elif stopping.exception() is not None:  # a driver that cannot stop cleanly must not block the others
        log.error("driver_stop_failed", sensor=driver.name, exc_info=stopping.exception())
