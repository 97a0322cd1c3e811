"""Worker threads give way to the event loop when both want a CPU.

The loop thread keeps time (sensor deadlines, the synchronizer's ticks); the detector, the
simulator's renders, the recorder and a replay's readers only have to keep up on average.
On a 2-core machine they and the loop often want the same core: at equal priority the loop
waits for a time slice whenever it wakes (``respecd bench pipeline`` shows it in the loop's
lag p99; docs/PERFORMANCE.md "pipeline"). Linux
sets a nice value per thread, so each worker lowers its own on start; elsewhere this does
nothing. A thread can only lower its priority, never raise it back, so this is for threads
that do background work for their whole life.
"""

from __future__ import annotations

import os
import sys
import threading

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
