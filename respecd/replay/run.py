"""``respecd --replay LOG``: run a recorded session through the same pipeline, with every
sensor replaced by a counterfactual ``ReplayDriver``, and report how a policy did.

``--speed max`` runs in lockstep on the log's clock (``LockstepLoop`` + ``LockstepClock``)
and is deterministic: same log + profile + seed give the same decisions. Two things would
otherwise leak this machine's timing into the controller, so lockstep replaces them:
the CPU probe is off, and perception latency is modelled from the log (``LatencyModel``):
the controller sees the modelled latency, and perception is kept busy for it on the log's
clock (``pacing``), so it skips bundles as it did on the robot. The measured latency
still goes into the report's compute figures.
``--speed 1|2`` replays on a scaled wall clock with measured latencies, like a live run.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import structlog

from respecd.errors import InputError
from respecd.record.reader import SessionLog, open_log
from respecd.replay import pacing, report_out
from respecd.replay import report as rpt
from respecd.replay.latency import LatencyModel
from respecd.replay.profile import first_frames, replay_profile

log = structlog.get_logger(__name__)


def run_replay(args: argparse.Namespace) -> int:
    """Entry point from ``respecd --replay``; InputError/ConfigError become exit 2."""
    if args.duration is not None and not args.duration > 0:
        raise InputError(f"--duration: expected a positive number of seconds, got {args.duration}")
    session = open_log(args.replay)
    if session.truncated:
        print(f"respecd: warning: {session.path} was cut short (no summary); replaying its "
              f"{session.duration_s:.2f} s up to the last complete chunk", file=sys.stderr)
        log.warning("replay.truncated", path=str(session.path), readable_s=round(session.duration_s, 3))
    base = _base_profile(args, session)
    firsts = first_frames(session)
    if not firsts:
        raise InputError(f"{session.path}: the log holds no sensor frames to replay")
    speed = str(getattr(args, "speed", "max"))
    profile = replay_profile(base, session, firsts, seed=(args.seed or 0), lockstep=speed == "max", policy=args.policy)
    t0 = min(f.t for f in firsts.values())
    duration = session.duration_s if args.duration is None else min(args.duration, session.duration_s)
    entry = _run(profile, session, args, speed, t0, duration)
    entry.update(policy=profile.controller.policy, seed=(args.seed or 0), speed=speed, truncated=session.truncated)
    return _emit(args, session, entry)


def _base_profile(args: argparse.Namespace, session: SessionLog) -> dict[str, Any]:
    """``--config`` when given explicitly, else the profile recorded in the log."""
    from respecd.config import DEFAULT_PROFILE, load_profile

    if args.config and args.config != DEFAULT_PROFILE:
        return load_profile(args.config).model_dump(mode="json")
    recorded = session.profile_dict()
    if recorded is None:
        raise InputError(f"{session.path}: the log has no recorded profile; pass the one it ran with: --config FILE")
    return recorded


def _run(profile: Any, session: SessionLog, args: argparse.Namespace, speed: str, t0: float, duration: float) -> dict:
    from respecd.replay.lockstep import LockstepLoop

    state_dir = Path(args.state_dir) if args.state_dir else None
    with tempfile.TemporaryDirectory(prefix="respecd-replay-") as scratch:
        # a fresh Q-table per replay (unless --state-dir): two replays must not feed each other
        runner = _Replay(profile, session, speed, t0, duration, state_dir or Path(scratch), (args.seed or 0))
        if speed == "max":
            with asyncio.Runner(loop_factory=LockstepLoop) as r:
                return r.run(runner.run())
        return asyncio.run(runner.run())


class _Replay:
    """One replay run: builds the daemon around replay drivers and drives its clock."""

    def __init__(self, profile: Any, session: SessionLog, speed: str, t0: float, duration: float,
                 state_dir: Path, seed: int) -> None:
        self.profile = profile
        self.session = session
        self.speed = speed
        self.t0 = t0
        self.duration = duration
        self.state_dir = state_dir
        self.seed = seed
        rgb = next((s for s in profile.sensors if s.modality == "rgb"), None)
        truth, self.logged_percepts = session.side_data(rgb.source or rgb.name if rgb else None)
        self.collector = rpt.Collector(
            rpt.build_reference(truth, self.logged_percepts),
            tuple(rgb.native_resolution) if rgb is not None and rgb.native_resolution else None,
        )

    async def run(self) -> dict[str, Any]:
        from respecd.clock import ScaledClock
        from respecd.daemon import Daemon
        from respecd.drivers.base import DriverContext
        from respecd.replay.lockstep import LockstepClock

        lockstep = self.speed == "max"
        clock: Any = LockstepClock(self.t0) if lockstep else ScaledClock(float(self.speed), start=self.t0)
        context = DriverContext(seed=self.seed, replay=self.session)
        daemon = Daemon(self.profile, clock, context, state_dir=self.state_dir, taps=[self.collector],
                        status_sink=lambda fields, line: log.debug("status", line=line))
        self.collector.attach(daemon.drivers)
        self.latency_source = "measured" if self.profile.perception.enabled else "none (perception off)"
        if lockstep and self.profile.perception.enabled:
            model = LatencyModel.from_percepts(self.logged_percepts)
            self.latency_source = f"{model.source}: {model.s_per_pixel * 1e9:.1f} ns/px"
            pacing.install(daemon, clock, model, self.collector.measured)
        else:
            daemon.percepts.taps.insert(0, self.collector.measured)
        started, cpu0 = time.perf_counter(), time.process_time()
        await self._drive(daemon, clock, lockstep)
        wall, cpu = time.perf_counter() - started, time.process_time() - cpu0
        describe = getattr(daemon.controller, "describe_action", None)
        power = {s.name: s.power for s in self.profile.sensors}
        entry = rpt.summarize(self.collector, self.t0, self.t0 + self.duration, power, describe)
        entry["wall_s"] = round(wall, 3)  # the replay loop alone: imports and weight loading excluded
        entry["cpu_s"] = round(cpu, 3)  # process CPU time (all threads) over the same span
        entry["latency_model"] = self.latency_source
        return entry

    async def _drive(self, daemon: Any, clock: Any, lockstep: bool) -> None:
        end = self.t0 + self.duration
        bar = _progress_bar()(total=round(self.duration, 1), unit="s", desc="replay", disable=self.duration < 20,
                              mininterval=1.0, file=sys.stderr, leave=False)
        task = asyncio.create_task(daemon.run(duration=self.duration), name="replay-daemon")

        def progress(t: float) -> None:
            done = round(min(t, end) - self.t0, 1)
            if done > bar.n:
                bar.update(done - bar.n)

        try:
            if lockstep:
                await clock.run(end, on_step=progress, done=task.done)
            else:
                while not task.done():
                    progress(clock.now())
                    await asyncio.wait([task], timeout=0.5)
            await task
        finally:
            bar.close()


def _progress_bar() -> Any:
    try:
        from tqdm import tqdm
    except ImportError:  # the lab extra: without it a replay runs without a progress bar
        return _NoBar

    class Bar(tqdm):  # type: ignore[misc]
        monitor_interval = 0  # no monitor thread: it would outlive the replay by 10 s

    return Bar


class _NoBar:
    """The part of tqdm's interface the replay uses, doing nothing."""

    def __init__(self, **_: Any) -> None:
        self.n = 0.0

    def update(self, step: float) -> None:
        self.n += step

    def close(self) -> None:
        pass


def _emit(args: argparse.Namespace, session: SessionLog, entry: dict[str, Any]) -> int:
    """Print the comparison table; write JSON + PNG when ``--report`` is given."""
    log_id = {"path": str(session.path.resolve()), "bytes": session.size, "start_ns": session.start_ns}
    policy = entry["policy"]
    if args.report:
        path = Path(args.report)
        report = report_out.merge(path, log_id, policy, entry)
        png = report_out.write(path, report)
        log.info("replay.report", json=str(path), png=str(png) if png else None, policies=list(report["policies"]))
    else:
        report = {"log": log_id, "policies": {policy: entry}}
    print(report_out.table(report))
    return 0
