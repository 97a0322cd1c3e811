import asyncio

import pytest

from respecd.queues import DropOldestQueue


def test_put_never_blocks_and_drops_oldest():
    q: DropOldestQueue[int] = DropOldestQueue(3)
    results = [q.put(i) for i in range(5)]
    assert results == [True, True, True, False, False]
    assert q.dropped == 2
    assert [q.get_nowait() for _ in range(len(q))] == [2, 3, 4]


def test_get_nowait_on_empty_raises():
    with pytest.raises(asyncio.QueueEmpty):
        DropOldestQueue(1).get_nowait()


def test_maxsize_must_be_positive():
    with pytest.raises(ValueError):
        DropOldestQueue(0)


async def test_get_waits_for_a_put():
    q: DropOldestQueue[str] = DropOldestQueue(2)
    getter = asyncio.create_task(q.get())
    await asyncio.sleep(0)
    assert not getter.done()
    q.put("frame")
    assert await asyncio.wait_for(getter, 1.0) == "frame"


async def test_cancelled_getter_does_not_swallow_items():
    q: DropOldestQueue[int] = DropOldestQueue(2)
    cancelled = asyncio.create_task(q.get())
    await asyncio.sleep(0)
    cancelled.cancel()
    await asyncio.gather(cancelled, return_exceptions=True)
    q.put(7)
    assert await asyncio.wait_for(q.get(), 1.0) == 7


def test_taps_see_every_put_even_dropped_ones():
    q: DropOldestQueue[int] = DropOldestQueue(1)
    seen: list[int] = []
    q.taps.append(seen.append)
    for i in range(3):
        q.put(i)
    assert seen == [0, 1, 2]
    assert len(q) == 1
