"""Perception as the robot ran it, inside a lockstep replay.

Live, the detector takes a bundle, is busy for its latency, and meanwhile the synchronizer
keeps ticking into a drop-oldest queue: a slow detector sees fewer bundles. In lockstep the
clock stands still while the detector runs, so without help every bundle would be
processed. These two queues restore the live behaviour on the log's clock, from the
modelled (not this machine's) latency:

* ``PacedBundles`` — perception may take its next bundle only once the clock has passed
  the time the previous one would have kept it busy;
* ``ModelledPercepts`` — a percept leaves perception carrying the modelled latency (what
  the controller sees) while the measured one goes to the report.
"""

from __future__ import annotations

from typing import Any

from respecd.messages import Bundle, Percept
from respecd.queues import DropOldestQueue
from respecd.replay.latency import LatencyModel


class PacedBundles(DropOldestQueue[Bundle]):
    """The bundle queue, with ``get`` held until perception would be free again."""

    def __init__(self, old: DropOldestQueue[Bundle], clock: Any) -> None:
        super().__init__(old.maxsize, old.name)
        self.taps = old.taps
        self.clock = clock
        self.busy_until = float("-inf")
        self.taken_at = 0.0

    async def get(self) -> Bundle:
        await self.clock.sleep_until(self.busy_until)
        bundle = await super().get()
        self.taken_at = self.clock.now()
        return bundle


class ModelledPercepts(DropOldestQueue[Percept]):
    """The percept queue: measured latency to ``measured``, modelled latency downstream."""

    def __init__(self, old: DropOldestQueue[Percept], model: LatencyModel, bundles: PacedBundles,
                 measured: Any) -> None:
        super().__init__(old.maxsize, old.name)
        self.taps = old.taps
        self.model = model
        self.bundles = bundles
        self.measured = measured

    def put(self, item: Percept) -> bool:
        self.measured(item)
        modelled = self.model.apply(item)
        self.bundles.busy_until = self.bundles.taken_at + modelled.latency
        return super().put(modelled)


def install(daemon: Any, clock: Any, model: LatencyModel, measured: Any) -> None:
    """Swap the daemon's bundle and percept queues for the paced ones (before ``run``)."""
    bundles = PacedBundles(daemon.bundles, clock)
    daemon.bundles = bundles
    daemon.synchronizer.output = bundles
    daemon.percepts = ModelledPercepts(daemon.percepts, model, bundles, measured)
