"""Lockstep time: sleepers wake in (deadline, arrival) order, one at a time, and only after
worker-thread work caused by the previous wake-up has come back — whatever its duration."""

from __future__ import annotations

import asyncio
import random
import time

from respecd.record.lockstep import LockstepClock, LockstepLoop


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

        tasks = [asyncio.create_task(c) for c in (producer("a", 0.1), producer("b", 0.15), consumer())]
        await clock.run(until=2.0)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
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
