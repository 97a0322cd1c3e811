"""Worker threads give way to the event loop when both want a CPU, and the loop to nobody.

The loop thread keeps time (sensor deadlines, the synchronizer's ticks); the detector, the
simulator's renders, the recorder and a replay's readers only have to keep up on average.
On a 2-core machine they and the loop often want the same core: at equal priority the loop
waits for a time slice whenever it wakes (``respecd bench pipeline`` shows it in the loop's
lag p99; docs/PERFORMANCE.md "pipeline"). Linux
sets a nice value per thread, so each worker lowers its own on start; elsewhere this does
nothing. A thread can only lower its priority, never raise it back, so this is for threads
that do background work for their whole life.

Against other processes, nice values do little: with autogroups (the default) or one cgroup
per service, nice only ranks threads inside their own group, and a busy neighbour still
keeps the loop waiting for a core, often longer than a tick (docs/PERFORMANCE.md "pipeline").
So the live daemon puts its loop thread, and that thread alone, in the real-time class where
the process may (``realtime_loop``): ``SCHED_FIFO`` at a low priority wakes it ahead of every
normal thread, whatever its group. It is asked with ``SCHED_RESET_ON_FORK``, so the threads
the loop starts later (the detector, the renders, the recorder, the executors) begin in normal
scheduling and cannot hog a core at real-time priority; the loop itself blocks in
``epoll_wait`` every iteration. It still needs the GIL: a worker holding it while a neighbour
has the worker's core delays the loop however the loop is scheduled.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable

WORKER_NICE = 10  # added to the process's nice value (CFS weight about a tenth of the loop's)
VIEWER_NICE = 19  # the live view's threads: below the recorder, whose log must not pay for viewers


def lower_thread_priority(step: int = WORKER_NICE) -> None:
    """Lower the calling thread's CPU priority by ``step`` (Linux; quietly a no-op elsewhere or
    where it is refused). Use as a ThreadPoolExecutor ``initializer``."""
    if sys.platform != "linux":
        return
    tid = threading.get_native_id()
    try:
        current = os.getpriority(os.PRIO_PROCESS, tid)
        os.setpriority(os.PRIO_PROCESS, tid, min(19, current + step))
    except OSError:
        pass


def realtime_loop(priority: int) -> tuple[str, Callable[[], None]]:
    """Put the calling thread in ``SCHED_FIFO`` at ``priority`` (threads it starts afterwards
    reset to normal scheduling). Returns what the thread now runs as (``"fifo 10"``, or
    ``"normal: why"``) and how to put back what it ran as before."""
    if priority <= 0:
        return "normal: off in the profile (sync.realtime_priority: 0)", _nothing
    if sys.platform != "linux":
        return "normal: real-time scheduling is Linux's", _nothing
    previous = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
    except OSError as err:
        return (f"normal: SCHED_FIFO {priority} refused ({err.strerror}); allow it with LimitRTPRIO={priority} "
                "or CAP_SYS_NICE, and without RestrictRealtime=yes (docs/DEPLOY.md)"), _nothing

    def restore() -> None:
        try:
            os.sched_setscheduler(0, previous[0], previous[1])
        except OSError:
            pass  # a lower class is always allowed; nothing else to do if the kernel says otherwise

    return f"fifo {priority}", restore


def _nothing() -> None:
    pass
