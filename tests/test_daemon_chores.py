"""The live daemon's process chores belong to ``Daemon``, not to the ``Session`` it runs.

A session (what a replay, a benchmark or a test runs) leaves the process as it found it; the
daemon sets the GIL switch interval and freezes start-up's objects while it runs, puts both back
when it ends, and hands the C heap's freed pages back to the kernel while it runs (recording
torch's and the recorder's buffers leave freed blocks that glibc keeps: RSS grows while the
bytes in use stay flat, docs/PERFORMANCE.md "soak").
"""

from __future__ import annotations

import gc
import shutil
import socket
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import structlog
import yaml

from respecd.clock import MonotonicClock
from respecd.config import load_profile
from respecd.daemon import GIL_SWITCH_INTERVAL_S, Daemon
from respecd.heap import heap_mb
from respecd.sdnotify import Notifier
from respecd.session import Session

REPO = Path(__file__).resolve().parents[1]


def _quiet_rover(tmp_path: Path) -> Session:
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["perception"] = {"enabled": False}
    profile["controller"] = {"enabled": False}
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(profile))
    return Session(load_profile(path), MonotonicClock())


def _rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


async def test_a_session_leaves_the_process_globals_alone(tmp_path: Path) -> None:
    interval, frozen = sys.getswitchinterval(), gc.get_freeze_count()
    session = _quiet_rover(tmp_path)
    seen: list[tuple[float, int]] = []
    session.hooks.up.append(lambda: seen.append((sys.getswitchinterval(), gc.get_freeze_count())))
    await session.run(duration=0.5)
    assert seen == [(interval, frozen)]  # while it runs, too
    assert (sys.getswitchinterval(), gc.get_freeze_count()) == (interval, frozen)
    structlog.reset_defaults()


async def test_the_daemon_sets_them_while_it_runs_and_puts_them_back(tmp_path: Path) -> None:
    assert sys.getswitchinterval() != GIL_SWITCH_INTERVAL_S and gc.get_freeze_count() == 0
    interval = sys.getswitchinterval()
    session = _quiet_rover(tmp_path)
    seen: list[tuple[float, int]] = []
    daemon = Daemon(session)
    session.hooks.up.append(lambda: seen.append((sys.getswitchinterval(), gc.get_freeze_count())))
    await daemon.run(duration=0.5)
    assert seen[0][0] == GIL_SWITCH_INTERVAL_S and seen[0][1] > 0
    assert (sys.getswitchinterval(), gc.get_freeze_count()) == (interval, 0)
    structlog.reset_defaults()


@pytest.mark.slow
async def test_freed_heap_pages_go_back_while_the_daemon_runs(tmp_path: Path) -> None:
    if heap_mb() is None:
        pytest.skip("not glibc: there is no malloc_trim to call")
    daemon = Daemon(_quiet_rover(tmp_path), trim_period_s=0.3)  # seconds, not the daemon's 30
    blocks = [np.ones(1000) for _ in range(100_000)]  # 800 MB of 8 KB heap blocks
    del blocks[::2]  # 400 MB freed in holes between live blocks: glibc keeps those pages
    held = _rss_mb()
    await daemon.run(duration=1.2)
    assert held - _rss_mb() > 100, "the freed pages are still resident"
    del blocks
    structlog.reset_defaults()


@pytest.mark.slow
async def test_the_daemon_says_ready_status_watchdog_and_stopping(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    folder = Path(tempfile.mkdtemp(prefix="rdc-", dir="/tmp"))  # AF_UNIX paths must be short
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        server.bind(str(folder / "notify"))
        server.setblocking(False)
        monkeypatch.setenv("WATCHDOG_USEC", "1000000")  # fed every 0.5 s
        monkeypatch.delenv("WATCHDOG_PID", raising=False)
        lines: list[str] = []
        daemon = Daemon(_quiet_rover(tmp_path), notifier=Notifier(address=str(folder / "notify")),
                        status_sink=lambda fields, line: lines.append(line))
        await daemon.run(duration=2.5)
        messages = []
        while True:
            try:
                messages.append(server.recv(65536).decode())
            except BlockingIOError:
                break
    finally:
        server.close()
        shutil.rmtree(folder, ignore_errors=True)
    assert messages[0] == "READY=1\nSTATUS=pipeline up" and messages[-1] == "STOPPING=1"
    assert messages.count("WATCHDOG=1") >= 3
    statuses = [m for m in messages if m.startswith("STATUS=t=")]
    assert statuses and lines and statuses[0] == f"STATUS={lines[0]}" and "sync" in lines[0]
    structlog.reset_defaults()
