"""A long-running session hands the C heap's freed pages back to the kernel.

Torch's buffers and the recorder's chunk buffers leave freed blocks that glibc keeps: over an
hour's recording soak the heap's bytes in use stayed flat while RSS grew by 153 MB/h
(docs/PERFORMANCE.md "soak"). The session trims the heap periodically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import structlog
import yaml

import respecd.session
from respecd.clock import MonotonicClock
from respecd.config import load_profile
from respecd.heap import heap_mb
from respecd.session import Session

REPO = Path(__file__).resolve().parents[1]


def _rss_mb() -> float:
    with open("/proc/self/status", encoding="ascii") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024


async def test_freed_heap_pages_go_back_while_the_session_runs(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    if heap_mb() is None:
        pytest.skip("not glibc: there is no malloc_trim to call")
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["perception"] = {"enabled": False}
    profile["controller"] = {"enabled": False}
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(profile))
    session = Session(load_profile(path), MonotonicClock())
    monkeypatch.setattr(respecd.session, "HEAP_TRIM_PERIOD_S", 0.3)  # seconds, not the daemon's 30
    blocks = [np.ones(1000) for _ in range(100_000)]  # 800 MB of 8 KB heap blocks
    del blocks[::2]  # 400 MB freed in holes between live blocks: glibc keeps those pages
    held = _rss_mb()
    await session.run(duration=1.2)
    assert held - _rss_mb() > 100, "the freed pages are still resident"
    del blocks
    structlog.reset_defaults()
