"""respecd.timeouts: a timeout and a task reaper that let every cancellation through (docs in the module)."""

from __future__ import annotations

import asyncio

import pytest

from respecd.timeouts import reap, within


async def _cancel_as_it_completes(finish) -> asyncio.Task:
    """Cancel a task waiting in ``within`` in the same loop iteration as its work finishes."""
    work = asyncio.get_running_loop().create_future()
    task = asyncio.create_task(within(work, 5.0))
    await asyncio.sleep(0)  # the task now waits on ``work``
    finish(work)
    task.cancel()
    await asyncio.wait({task})
    return task


async def test_a_cancel_that_lands_as_the_work_returns_is_not_lost() -> None:
    task = await _cancel_as_it_completes(lambda work: work.set_result("answered"))
    assert task.cancelled()  # Python 3.11's wait_for returns "answered" here


async def test_a_cancel_that_lands_as_the_work_fails_is_not_turned_into_its_error() -> None:
    """The radar case: sensorStart rejected as the supervisor is cancelled must not look like a failure to retry."""
    task = await _cancel_as_it_completes(lambda work: work.set_exception(ConnectionError("Error -1")))
    assert task.cancelled()  # Python 3.11's wait_for raises the ConnectionError here


async def test_the_result_and_the_error_of_work_come_through() -> None:
    async def answer() -> int:
        return 7

    async def fail() -> None:
        raise ValueError("bad reply")

    assert await within(answer(), 1.0) == 7
    with pytest.raises(ValueError, match="bad reply"):
        await within(fail(), 1.0)


async def _sleep_until_cancelled(unwinding: asyncio.Event, unwind_s: float = 0.0) -> None:
    """Work that only ends by cancellation, sets ``unwinding`` and then takes ``unwind_s`` to clean up."""
    try:
        await asyncio.sleep(10)
    finally:
        unwinding.set()
        await asyncio.sleep(unwind_s)


async def test_a_timeout_cancels_the_work_and_lets_it_unwind() -> None:
    unwound = asyncio.Event()
    with pytest.raises(asyncio.TimeoutError):
        await within(_sleep_until_cancelled(unwound), 0.05)
    assert unwound.is_set()


async def test_the_caller_cancelled_while_waiting_cancels_the_work() -> None:
    work = asyncio.ensure_future(asyncio.sleep(10))
    task = asyncio.create_task(within(work, 5.0))
    await asyncio.sleep(0.01)
    task.cancel()
    await asyncio.wait({task})
    await asyncio.sleep(0)
    assert task.cancelled() and work.cancelled()


async def test_reap_ends_the_task_and_lets_the_callers_cancel_through() -> None:
    """A watch task that takes a moment to unwind; the caller is cancelled meanwhile (a stop that overran)."""
    unwinding = asyncio.Event()
    child = asyncio.create_task(_sleep_until_cancelled(unwinding, unwind_s=0.05))
    await asyncio.sleep(0)
    caller = asyncio.create_task(reap(child))
    await unwinding.wait()
    caller.cancel()
    await asyncio.wait({caller})
    assert caller.cancelled()  # `with suppress(CancelledError): await child` returns normally here
    await asyncio.wait({child})
    assert child.cancelled()


async def test_reap_of_a_task_that_failed_does_not_raise() -> None:
    async def broken() -> None:
        raise OSError("port gone")

    child = asyncio.create_task(broken())
    await asyncio.sleep(0)
    await reap(child)
    assert isinstance(child.exception(), OSError)
