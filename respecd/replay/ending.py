"""When a replay ends: at the log's end (or ``--duration``), once the inference running then has
delivered its percept.

On the robot the detector would have finished the frames it had taken; ending the session at the
last logged frame threw that inference away, and a short camera bag whose only inference outlives
the bag (a second of 1280x1024 with attribution, say) reported 0 percepts. A stop signal still
ends a replay at once. The wait starts when the pipeline is up, so a scaled clock's restart
and a detector still loading do not count against the log's time.
"""

from __future__ import annotations

import asyncio
from typing import Any

import structlog

log = structlog.get_logger(__name__)


class LogEnd:
    """``finished`` is set at the log's end plus the last inference, or at once on ``stop``;
    the replay's session runs until it is set."""

    def __init__(self, session: Any, end: float, stop: asyncio.Event) -> None:
        self.session = session
        self.end = end
        self.stop = stop
        self.finished = asyncio.Event()
        self.waited_s = 0.0  # log time past the end spent on the last inference
        self._up = asyncio.Event()
        session.hooks.up.append(self._up.set)

    async def watch(self) -> None:
        """Set ``finished`` when the replay is over; run beside the session."""
        stopped = asyncio.ensure_future(self.stop.wait())
        try:
            if await self._unless_stopped(self._up.wait(), stopped):
                clock = self.session.clock
                if await self._unless_stopped(clock.sleep_until(self.end), stopped):
                    await self._last_inference(stopped)
        finally:
            stopped.cancel()
            self.finished.set()

    async def _last_inference(self, stopped: asyncio.Future[Any]) -> None:
        perception = self.session.pipeline.perception
        pending = perception.finish() if perception is not None else None
        if pending is None:
            return
        await asyncio.wait([pending, stopped], return_when=asyncio.FIRST_COMPLETED)
        self.waited_s = max(0.0, self.session.clock.now() - self.end)
        log.info("replay.last_inference", after_end_s=round(self.waited_s, 3))

    @staticmethod
    async def _unless_stopped(work: Any, stopped: asyncio.Future[Any]) -> bool:
        """Await ``work`` unless ``stopped`` comes first; True when ``work`` finished."""
        job = asyncio.ensure_future(work)
        await asyncio.wait([job, stopped], return_when=asyncio.FIRST_COMPLETED)
        if not job.done():
            job.cancel()
            await asyncio.gather(job, return_exceptions=True)
            return False
        return True
