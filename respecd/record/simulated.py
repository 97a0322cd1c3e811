"""A simulated session recorded in lockstep, for benchmarks and tests that need a log.

``respecd --record`` on the simulated rover runs on the wall clock: on a loaded machine its
renderers fall behind and the log holds fewer frames (a single RGB frame in 4 s, at worst).
Here the session runs on a ``LockstepClock`` instead, as fast as the renderers go: the
same profile and seed give the same frames at the same times, however busy the machine.
"""

from __future__ import annotations

import asyncio
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from respecd.config import Profile
    from respecd.record.recorder import Recorder
    from respecd.replay.lockstep import LockstepClock

TAPS = ("frame", "bundle", "percept", "decision", "config")


def record_simulated(profile: Profile, path: Path, seconds: float, seed: int = 0) -> Path:
    """Record ``seconds`` of ``profile``'s simulated session (no detector: perception off) to the
    one file ``path`` (no rotation) with the profile's ``recording:`` encodings; return ``path``.
    Nothing is dropped: a full queue waits for the writer, and the file is complete when this
    returns. RuntimeError if a message could not be encoded or the file was not written whole."""
    from respecd.record.recorder import Recorder

    config = profile.recording.model_copy(update={"enabled": True, "path": str(path), "rotate_mib": float(1 << 20),
                                                  "rotate_s": 0.0, "max_bytes": 0})
    # lossless: the tap waits for a full queue, and close writes everything queued
    (recorder,) = run_recorded(profile, lambda quiet, clock: [Recorder(config, quiet, clock, lossless=True)],
                               seconds, seed)
    if recorder.errors or recorder.paths != [path]:  # an encoding bug, or a paused (full) disk
        raise RuntimeError(f"{path}: {recorder.errors} message(s) not encoded, written to {recorder.paths}")
    return path


def run_recorded(profile: Profile, recorders_for: Callable[[Profile, LockstepClock], list[Recorder]],
                 seconds: float, seed: int) -> list[Recorder]:
    """Run ``seconds`` of ``profile``'s simulated session in lockstep, perception off, observed by the
    recorders ``recorders_for(quiet profile, clock)`` builds; return them, closed. They are closed here,
    after the session, not by its stop budget (a lockstep session queues faster than real time, and
    the daemon's budget would drop the tail), so every file has its summary and footer."""
    from respecd.drivers.base import DriverContext
    from respecd.replay.lockstep import LockstepClock, LockstepLoop
    from respecd.session import Session

    quiet = profile.model_copy(update={"perception": profile.perception.model_copy(update={"enabled": False})})

    async def session() -> list[Recorder]:
        clock = LockstepClock(0.0)
        recorders = recorders_for(quiet, clock)
        taps = [SimpleNamespace(start=_nothing, close=_nothing,
                                **{f"on_{tap}": getattr(r, f"on_{tap}") for tap in TAPS}) for r in recorders]
        try:
            for recorder in recorders:
                recorder.start()
            with tempfile.TemporaryDirectory(prefix="respecd-record-") as state:
                context = DriverContext(seed=seed, simulation=quiet.simulation)
                run = Session(quiet, clock, context, state_dir=Path(state), observers=taps)
                task = asyncio.create_task(run.run(duration=seconds))
                await clock.run(seconds)
                await task
        finally:  # a writer thread left open would keep the interpreter from exiting
            for recorder in recorders:
                await recorder.close()
        return recorders

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        return runner.run(session())


def _nothing() -> None:
    pass
