"""A fleet worker's process: set up once (logging as the command asked, detectors shared by the
logs it evaluates), and what it can say about itself (pid, cold start, memory).

A process pool's fork server imports this module before it forks the workers, so each starts
with torch and the evaluator already imported; a Ray worker sets itself up on its first task.
"""

from __future__ import annotations

import os
import resource
import time
from dataclasses import dataclass
from typing import Any

import torch  # noqa: F401 - imported here, once, in the fork server: every forked worker starts with it

import respecd.replay.evaluate  # noqa: F401 - the same: the evaluator and its imports
from respecd.perception.stage import share_detectors


@dataclass(frozen=True)
class Settings:
    """How the command that started the workers logs."""

    log_format: str = "console"
    log_level: str = "warning"


_state: dict[str, Any] = {}  # this process's: pid, when it was set up, what that took


def start(settings: Settings) -> None:
    """Set this process up for fleet work, once (a pool's initializer, a Ray task's first step)."""
    if _state.get("pid") == os.getpid():
        return
    began = time.perf_counter()
    from respecd.logs import configure_logging

    configure_logging(settings.log_format, settings.log_level)  # type: ignore[arg-type]
    sharing = share_detectors()
    sharing.__enter__()  # for the process's life: each checkpoint loaded once for all its logs
    _state.update(pid=os.getpid(), sharing=sharing, setup_s=time.perf_counter() - began, tasks=0)


def task_done() -> dict[str, Any]:
    """What a task's result says about the process that ran it."""
    _state["tasks"] = _state.get("tasks", 0) + 1
    return {"pid": os.getpid(), "task": _state["tasks"], "setup_s": round(_state.get("setup_s", 0.0), 4),
            "max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}
