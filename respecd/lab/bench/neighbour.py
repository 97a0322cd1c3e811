"""A reproducible busy neighbour: N processes that spin on a core each, beside a benchmark.

A robot's computer runs other nodes beside the daemon (a Jetson with its ROS 2 stack), and a
development machine runs other jobs: the loop's timing must hold while they compete for the
cores. ``bench pipeline --neighbour N`` measures it against a load anyone can start again: N
Python interpreters running ``while True: pass`` at the benchmark's own nice value, each
wanting a whole core for as long as the measurement lasts. Each runs in a session of its own,
as another service would (with autogroups the kernel shares the CPU between sessions first,
so a neighbour in the benchmark's own session would be weighed against its threads' nice
values instead).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager

SPIN = "while True: pass"


@contextmanager
def busy_neighbours(count: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``count`` spinning processes for the ``with`` block's length; always stopped after it."""
    spinners: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(count):
            spinners.append(subprocess.Popen([sys.executable, "-c", SPIN], stdin=subprocess.DEVNULL,
                                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                             start_new_session=True))
        yield spinners
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait()


def cpu_seconds(spinners: list[subprocess.Popen[bytes]]) -> float:
    """CPU seconds the running spinners have had (Linux /proc; 0.0 where it cannot be read)."""
    total = 0.0
    ticks = os.sysconf("SC_CLK_TCK")
    for spinner in spinners:
        try:
            with open(f"/proc/{spinner.pid}/stat") as stat:
                fields = stat.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / ticks  # utime, stime (fields 14, 15 of stat)
    return total
