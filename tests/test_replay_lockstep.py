"""Lockstep time: sleepers wake in (deadline, arrival) order, one at a time, and only after
worker-thread work caused by the previous wake-up has come back — whatever its duration."""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Coroutine
from typing import Any

from respecd.replay.lockstep import LockstepClock, LockstepLoop, settle


async def _drive(clock: LockstepClock, until: float, *coroutines: Coroutine[Any, Any, Any]) -> None:
    """Run the coroutines on the lockstep clock up to ``until``, then cancel what is left."""
    tasks = [asyncio.create_task(c) for c in coroutines]
    await clock.run(until=until)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)


def _scenario(jitter_seed: int) -> list[tuple[float, str]]:
    """Two producers and a consumer whose result depends on slow, jittery thread work."""
    jitter = random.Random(jitter_seed)  # thread durations differ run to run

    async def main() -> list[tuple[float, str]]:
        clock = LockstepClock(0.0)
        events: list[tuple[float, str]] = []
        results: asyncio.Queue[str] = asyncio.Queue()

        def work(tag: str) -> str:
            time.sleep(jitter.uniform(0.0, 0.004))
            return tag.upper()

        async def producer(name: str, period: float) -> None:
            t = 0.0
            while True:
                t += period
                await clock.sleep_until(t)
                done = await asyncio.get_running_loop().run_in_executor(None, work, f"{name}@{t:.2f}")
                await results.put(done)

        async def consumer() -> None:
            t = 0.0
            while True:
                t += 0.25
                await clock.sleep_until(t)
                seen = []
                while not results.empty():
                    seen.append(results.get_nowait())
                events.append((clock.now(), ",".join(seen)))

        await _drive(clock, 2.0, producer("a", 0.1), producer("b", 0.15), consumer())
        return events

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        return runner.run(main())


def test_lockstep_is_deterministic_despite_thread_timing() -> None:
    first, second = _scenario(1), _scenario(2)
    assert first == second
    assert [t for t, _ in first] == [0.25 * i for i in range(1, 9)]
    # at t=0.25 the consumer sees both producers' completed work up to then, in wake order
    assert first[0][1] == "A@0.10,B@0.15,A@0.20"


async def test_sleep_until_past_returns_at_once() -> None:
    clock = LockstepClock(5.0)
    await asyncio.wait_for(clock.sleep_until(4.0), timeout=1.0)
    assert clock.next_deadline() is None


class _InstantDetector:
    """Answers at once: on the lockstep clock only the modelled latency takes time."""

    def infer(self, frames, attribute):  # type: ignore[no-untyped-def]
        from respecd.messages import Percept

        return Percept(max(f.t for f in frames.values()), (), 0.0, {"rgb": 1.0} if attribute else None, 0.001)


def test_paced_perception_skips_bundles_like_a_busy_detector() -> None:
    """A 100 ms (modelled) detector fed 30 Hz bundles takes about every third one."""
    import numpy as np

    from respecd.messages import Bundle, Frame, Health, Percept, SyncStats
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.stage import PerceptionStage
    from respecd.queues import DropOldestQueue
    from respecd.replay.latency import LatencyModel

    model = LatencyModel(s_per_pixel=0.1 / (36 * 64), s_per_pixel_attributed=0.3 / (36 * 64), source="test")
    sync = SyncStats(30.0, 0.0, 0.0, Health.GOOD)

    async def main() -> tuple[list[float], list[float], list[float], int]:
        clock = LockstepClock(0.0)
        bundles = DropOldestQueue[Bundle](2, "bundles")
        percepts = DropOldestQueue[Percept](64, "percepts")
        stage = PerceptionStage(PerceptionConfig(attribution_every_s=1000.0), {}, clock, _InstantDetector(),
                                latency_model=model)
        measured: list[float] = []
        taken: list[float] = []
        stage.on_inference.append(lambda p: (measured.append(p.latency), taken.append(clock.now())))

        async def synchronizer() -> None:
            for k in range(1, 61):  # 2 s at 30 Hz
                await clock.sleep_until(k / 30)
                rgb = Frame("rgb", k / 30, k, np.zeros((36, 64, 3), np.uint8))
                bundles.put(Bundle(k / 30, {"rgb": rgb}, sync, k))

        await _drive(clock, 2.0, synchronizer(), stage.run(bundles, percepts))
        modelled = []
        while len(percepts):
            modelled.append(percepts.get_nowait().latency)
        return taken, modelled, measured, bundles.dropped

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        taken, modelled, measured, dropped = runner.run(main())
    # the first bundle (1/30 s) is attributed: 0.3 s, then ~10 per second, not 60
    assert 17 <= len(taken) <= 19
    assert abs(taken[0] - (1 / 30 + 0.3)) < 1e-9  # delivered when the robot's detector would have been done
    assert all(b - a >= 0.1 - 1e-9 for a, b in zip(taken, taken[1:], strict=False))
    assert dropped > 30  # the rest superseded in the drop-oldest queue, as live
    assert abs(modelled[0] - 0.3) < 1e-9 and all(abs(latency - 0.1) < 1e-9 for latency in modelled[1:])
    assert measured == [0.001] * len(taken)  # observers see the detector's own latency


def test_executor_results_come_back_in_submission_order() -> None:
    """The first job is the slowest; its waiter still resumes first (ties break the same way)."""

    async def main() -> list[int]:
        loop = asyncio.get_running_loop()
        resumed: list[int] = []

        async def job(i: int, seconds: float) -> None:
            await loop.run_in_executor(None, time.sleep, seconds)
            resumed.append(i)

        await asyncio.gather(*(job(i, 0.03 - 0.01 * i) for i in range(3)))
        assert loop.in_flight == 0  # type: ignore[attr-defined]
        return resumed

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        assert runner.run(main()) == [0, 1, 2]


def test_settling_sleeps_until_a_busy_worker_finishes_instead_of_polling() -> None:
    """A worker busy for 0.3 s: the loop wakes when it is done (and a few times to look at
    ``done()``), not every 0.2 ms -- each of those wakes took the GIL from the detector."""

    async def main() -> tuple[bool, int, float]:
        loop = asyncio.get_running_loop()
        job = loop.run_in_executor(None, time.sleep, 0.3)
        before, started = loop.scheduled, time.monotonic()  # type: ignore[attr-defined]
        await settle(loop)
        return job.done(), loop.scheduled - before, time.monotonic() - started  # type: ignore[attr-defined]

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        finished, callbacks, waited = runner.run(main())
    assert finished and waited >= 0.29
    assert callbacks < 100  # polling every 0.2 ms scheduled about 800 here


class _SlowDetector(_InstantDetector):
    """Takes 0.1 s of real time, and notes whether the synchronizer ticked past its bundle meanwhile."""

    def __init__(self) -> None:
        self.last_tick = 0.0
        self.ticked_beside: list[bool] = []

    def infer(self, frames, attribute):  # type: ignore[no-untyped-def]
        import time

        time.sleep(0.1)
        # the ticks up to the modelled delivery (0.1 s on) ran meanwhile; a held clock stays within a tick
        self.ticked_beside.append(self.last_tick > max(f.t for f in frames.values()) + 0.05)
        return super().infer(frames, attribute)


def _arrivals(detector: _InstantDetector) -> list[float]:
    import numpy as np

    from respecd.messages import Bundle, Frame, Health, Percept, SyncStats
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.stage import PerceptionStage
    from respecd.queues import DropOldestQueue
    from respecd.replay.latency import LatencyModel

    model = LatencyModel(s_per_pixel=0.1 / (36 * 64), s_per_pixel_attributed=0.3 / (36 * 64), source="test")
    sync = SyncStats(30.0, 0.0, 0.0, Health.GOOD)

    async def main() -> list[float]:
        clock = LockstepClock(0.0)
        bundles = DropOldestQueue[Bundle](2, "bundles")
        percepts = DropOldestQueue[Percept](64, "percepts")
        config = PerceptionConfig(attribution_every_s=1000.0)
        stage = PerceptionStage(config, {}, clock, detector, latency_model=model)
        arrived: list[float] = []
        percepts.taps.append(lambda p: arrived.append(clock.now()))

        async def synchronizer() -> None:
            for k in range(1, 31):
                await clock.sleep_until(k / 30)
                if isinstance(detector, _SlowDetector):
                    detector.last_tick = k / 30
                bundles.put(Bundle(k / 30, {"rgb": Frame("rgb", k / 30, k, np.zeros((36, 64, 3), np.uint8))}, sync, k))

        await _drive(clock, 0.7, synchronizer(), stage.run(bundles, percepts))
        return arrived

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        return runner.run(main())


def test_the_clock_runs_on_while_the_detector_computes() -> None:
    """Sensors and the synchronizer go on beside the detector; percepts still arrive at the
    modelled times, whatever the detector's real speed."""
    slow = _SlowDetector()
    assert _arrivals(slow) == _arrivals(_InstantDetector())
    # the clock ran on during each inference (a clock held by the detector would tick only after it)
    assert len(slow.ticked_beside) >= 4 and all(slow.ticked_beside)
