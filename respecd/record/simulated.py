"""A simulated session recorded in lockstep, for benchmarks and tests that need a log.

``respecd --record`` on the simulated rover runs on the wall clock: on a loaded machine its
renderers fall behind and the log holds fewer frames (a single RGB frame in 4 s, at worst).
Here the session runs on a ``LockstepClock`` instead, as fast as the renderers go: the
same profile and seed give the same frames at the same times, however busy the machine.
"""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from respecd.config import Profile

TAPS = ("frame", "bundle", "percept", "decision", "config")


def record_simulated(profile: Profile, path: Path, seconds: float, seed: int = 0) -> Path:
    """Record ``seconds`` of ``profile``'s simulated session (no detector: perception off) to the
    one file ``path`` (no rotation) with the profile's ``recording:`` encodings; return ``path``.
    Nothing is dropped: a full queue waits for the writer, and the file is complete when this
    returns. RuntimeError if a message could not be encoded or the file was not written whole."""
    from respecd.drivers.base import DriverContext
    from respecd.record.recorder import Recorder
    from respecd.replay.lockstep import LockstepClock, LockstepLoop
    from respecd.session import Session

    quiet = profile.model_copy(update={"perception": profile.perception.model_copy(update={"enabled": False})})
    config = profile.recording.model_copy(update={"enabled": True, "path": str(path), "rotate_mib": float(1 << 20),
                                                  "rotate_s": 0.0, "max_bytes": 0})

    async def session() -> None:
        clock = LockstepClock(0.0)
        # lossless: the tap waits for a full queue, and close writes everything queued (a lockstep
        # session queues faster than real time); closed here, after the session, not by its stop
        # budget, so the file has its summary and footer when this returns
        recorder = Recorder(config, quiet, clock, lossless=True)
        taps = SimpleNamespace(start=_nothing, close=_nothing,
                               **{f"on_{tap}": getattr(recorder, f"on_{tap}") for tap in TAPS})
        recorder.start()
        try:
            with tempfile.TemporaryDirectory(prefix="respecd-record-") as state:
                context = DriverContext(seed=seed, simulation=quiet.simulation)
                run = Session(quiet, clock, context, state_dir=Path(state), observers=[taps])
                task = asyncio.create_task(run.run(duration=seconds))
                await clock.run(seconds)
                await task
        finally:  # a writer thread left open would keep the interpreter from exiting
            await recorder.close()
        if recorder.errors or recorder.paths != [path]:  # an encoding bug, or a paused (full) disk
            raise RuntimeError(f"{path}: {recorder.errors} message(s) not encoded, written to {recorder.paths}")

    with asyncio.Runner(loop_factory=LockstepLoop) as runner:
        runner.run(session())
    return path


def _nothing() -> None:
    pass
