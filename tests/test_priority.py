"""The loop thread in SCHED_FIFO where permitted; the threads it starts in normal scheduling."""

from __future__ import annotations

import errno
import os
import sys
import threading
from typing import Any

import pytest

from respecd import priority

linux_only = pytest.mark.skipif(sys.platform != "linux", reason="real-time scheduling is Linux's")


def in_thread(job: Any) -> Any:
    """Run ``job`` on a thread of its own, so the test runner's thread keeps its scheduling."""
    out: list[Any] = []
    worker = threading.Thread(target=lambda: out.append(job()))
    worker.start()
    worker.join()
    return out[0]


def policy_of_this_thread() -> int:
    return os.sched_getscheduler(threading.get_native_id()) & ~os.SCHED_RESET_ON_FORK


def test_priority_zero_leaves_the_thread_alone() -> None:
    def job() -> tuple[str, int]:
        runs_as, restore = priority.realtime_loop(0)
        restore()
        return runs_as, policy_of_this_thread()

    runs_as, policy = in_thread(job)
    assert runs_as.startswith("normal: off in the profile")
    assert policy == os.SCHED_OTHER


@linux_only
def test_the_loop_runs_fifo_its_new_threads_do_not_and_restore_puts_it_back() -> None:
    def job() -> tuple[str, int, int, int]:
        runs_as, restore = priority.realtime_loop(7)
        during = policy_of_this_thread()
        child = in_thread(policy_of_this_thread)  # a worker the loop starts afterwards
        restore()
        return runs_as, during, child, policy_of_this_thread()

    try:
        os.sched_param(1)
        allowed = os.sched_get_priority_max(os.SCHED_FIFO) >= 7 and (os.geteuid() == 0 or _rtprio_limit() >= 7)
    except (AttributeError, OSError):
        allowed = False
    if not allowed:
        pytest.skip("this process may not use SCHED_FIFO (not root, RLIMIT_RTPRIO below 7)")
    runs_as, during, child, after = in_thread(job)
    assert runs_as == "fifo 7"
    assert during == os.SCHED_FIFO
    assert child == os.SCHED_OTHER
    assert after == os.SCHED_OTHER


@linux_only
def test_a_refusal_says_how_to_allow_it(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: Any) -> None:
        raise PermissionError(errno.EPERM, os.strerror(errno.EPERM))

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    runs_as, restore = priority.realtime_loop(10)
    restore()
    assert runs_as.startswith("normal: SCHED_FIFO 10 refused (Operation not permitted)")
    assert "LimitRTPRIO=10" in runs_as and "docs/DEPLOY.md" in runs_as


def _rtprio_limit() -> int:
    import resource

    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return soft if soft != resource.RLIM_INFINITY else 99
