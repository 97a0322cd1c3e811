"""``evaluate(log, profile, policy, table, seed) -> Report``: how a policy would have done on one log.

The one counterfactual evaluator: ``respecd --replay`` is a shell around it (report file, figure,
progress bar, signals), ``respecd fleet`` maps it over many logs in other processes or on Ray.
It runs a ``Session`` in which every sensor is a counterfactual ``ReplayDriver``.

It is pure as far as a fleet needs: it reads the log and nothing else, writes no file, draws no
progress bar, and its report holds no absolute path (the log is named by its file name). At
``speed="max"`` it runs in lockstep on the log's clock (``LockstepLoop`` + ``LockstepClock``) and
is deterministic: same log, profile, policy, table and seed give the same ``Report.result``
whatever the machine, its load or the process it runs in. What this machine's speed decides
(wall and CPU time, measured inference latency) is in ``Report.timing`` alone.

Two things would otherwise leak this machine's timing into the controller, so lockstep
replaces them: the CPU probe is off, and perception latency is modelled from the log
(``LatencyModel``): the controller sees the modelled latency, and perception is kept busy for
it on the log's clock, so it skips bundles as it did on the robot. ``speed="1"|"2"`` replays
on a scaled wall clock with measured latencies, like a live run (not deterministic).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from respecd.control.features import IMAGE_FEATURE_MODALITIES
from respecd.control.persist import StoredTable, table_meta, table_path
from respecd.drivers.replay import ReplayConfig
from respecd.errors import InputError
from respecd.gcfreeze import StartupFreeze
from respecd.replay import detector, watch
from respecd.replay import report as rpt
from respecd.replay.ending import LogEnd
from respecd.replay.latency import LatencyModel
from respecd.replay.profile import first_frames, replay_profile
from respecd.replay.source import base_profile, open_source

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)

# measured on this machine: never part of a result
TIMING_KEYS = ("wall_s", "cpu_s", "loop_cpu_s", "inference_ms_per_s", "mean_latency_ms")


@dataclass(frozen=True)
class Report:
    """One log under one policy. ``result`` depends on the inputs alone; ``timing`` on this machine.
    ``learned``: the table a ``learn`` replay ends with (not part of the report's JSON)."""

    log: dict[str, Any]  # name (the file's name, never its path), bytes, start_ns
    policy: str
    seed: int
    result: dict[str, Any]
    timing: dict[str, float]
    learned: StoredTable | None = field(default=None, compare=False, repr=False)

    def entry(self) -> dict[str, Any]:
        """The per-policy entry of a replay report: the result, with its timings under ``timing``."""
        return {**self.result, "timing": dict(self.timing)}


@dataclass
class RunControl:
    """What a shell may attach to one evaluation (none of it changes the result).

    ``signals``: a ``StopSignals`` whose SIGTERM/SIGINT end the replay early (the report then
    covers what was replayed); ``on_progress(done_s, total_s)``: called as log time advances;
    ``observe``: called with the ``Session`` before it starts (benchmarks attach hooks);
    ``state_dir``: read (never change) that directory's table when no table is given (a
    non-torch ``perception.runtime`` caches its exported graphs in its ``exported/``);
    ``record``/``foxglove``: write / serve the counterfactual session (``replay.watch``)."""

    signals: Any = None
    on_progress: Callable[[float, float], None] | None = None
    observe: Callable[[Any], None] | None = None
    state_dir: Path | None = None
    record: str | None = None
    foxglove: str | None = None


def evaluate(log_path: str | Path, profile: str | Path | dict[str, Any] | None = None, policy: str | None = None,
             table: StoredTable | None = None, seed: int = 0, *, duration: float | None = None,
             topics: str | None = None, speed: str = "max", allow_no_table: bool = False,
             control: RunControl | None = None) -> Report:
    """Replay ``log_path`` under ``policy`` (None: the profile's) and report how it did.

    ``profile``: a profile file or dict to replay with instead of the one the log recorded.
    ``table``: the Q-table ``exploit`` acts on (or ``learn`` starts from); one that does not fit the
    profile, or ``exploit`` without any table that fits, is an InputError naming why, unless
    ``allow_no_table`` (then the report's ``table`` says ``no table``). ``topics``: for a ROS bag,
    which topic is which sensor (``rgb=/cam/image_raw,imu=...``)."""
    control = control or RunControl()
    if duration is not None and not duration > 0:
        raise InputError(f"--duration: expected a positive number of seconds, got {duration}")
    session = open_source(log_path, topics)
    if session.truncated:
        log.warning("replay.truncated", log=session.path.name, readable_s=round(session.duration_s, 3))
    firsts = first_frames(session)
    if not firsts:
        raise InputError(f"{session.path}: the log holds no sensor frames to replay")
    base = base_profile(profile, session)
    chosen_by, foreign = detector.provenance(profile, session)
    if foreign:
        detector.announce(str((base.get("perception") or {}).get("weights", "builtin:sim-rover")))
    replayed = replay_profile(base, session, firsts, seed=seed, lockstep=speed == "max", policy=policy)
    t0 = min(f.t for f in firsts.values())
    span = session.duration_s if duration is None else min(duration, session.duration_s)
    tables = _tables(replayed, table, control.state_dir, allow_no_table)
    run = _Replay(replayed, session, speed, t0, span, seed, tables, control)
    result, timing = run.run()
    result.update(policy=replayed.controller.policy, seed=seed, speed=speed, truncated=session.truncated,
                  damage=sorted(d.describe() for d in getattr(session, "damage", ())))  # stretches skipped
    if hasattr(session, "skipped_report"):  # a ROS bag: its unreadable messages, per topic
        result["skipped"] = session.skipped_report()
    result["detector"] = detector.entry(replayed.perception, base.get("perception"), chosen_by, foreign)
    log_id = {"name": session.path.name, "bytes": session.size, "start_ns": session.start_ns}
    return Report(log_id, replayed.controller.policy, seed, result, timing, run.learned)


def _tables(profile: Profile, given: StoredTable | None, state_dir: Path | None, allow_none: bool) -> Any:
    """The replay's tables: the one given, else the state directory's (read, never changed); strict."""
    from respecd.control.stage import TableFiles

    load = table_path(Path(state_dir), profile.controller.table_file, profile.name) if state_dir else None
    return TableFiles(load, None, set_aside=False, given=given, strict=True, allow_none=allow_none)


class _Replay:
    """One replay run: a session around replay drivers, its clock driven to the end."""

    def __init__(self, profile: Profile, session: Any, speed: str, t0: float, duration: float, seed: int,
                 tables: Any, control: RunControl) -> None:
        self.profile = profile
        self.session = session
        self.speed = speed
        self.t0 = t0
        self.duration = duration
        self.seed = seed
        self.tables = tables
        self.control = control
        # another runtime's exported graphs: a cache beside the table read, not state
        self.exports = control.state_dir / "exported" if control.state_dir else None
        self.learned: StoredTable | None = None
        rgb = next((s for s in profile.sensors if isinstance(s, ReplayConfig) and s.modality == "rgb"), None)
        truth, self.logged_percepts = session.side_data(rgb.source or rgb.name if rgb else None)
        self.collector = rpt.Collector(
            rpt.build_reference(truth, self.logged_percepts),
            rgb.native_resolution if rgb is not None else None,
        )
        self.latency_source = "measured" if profile.perception.enabled else "none (perception off)"

    def run(self) -> tuple[dict[str, Any], dict[str, float]]:
        from respecd.replay.lockstep import LockstepLoop

        if self.speed == "max":
            with asyncio.Runner(loop_factory=LockstepLoop) as runner:
                return runner.run(self._run())
        return asyncio.run(self._run())

    async def _run(self) -> tuple[dict[str, Any], dict[str, float]]:
        from respecd.clock import ScaledClock
        from respecd.drivers.base import DriverContext
        from respecd.replay.lockstep import LockstepClock
        from respecd.session import Session

        lockstep = self.speed == "max"
        signals = self.control.signals
        stop = signals.bind() if signals is not None else asyncio.Event()
        clock: Any = LockstepClock(self.t0) if lockstep else ScaledClock(float(self.speed), start=self.t0)
        model = None
        if lockstep and self.profile.perception.enabled:
            model = LatencyModel.from_percepts(self.logged_percepts)
            self.latency_source = f"{model.source}: {model.s_per_pixel * 1e9:.1f} ns/px"
        # without a detector the controller's features read every RGB and thermal frame: decode
        # those ahead, off the loop (depth's pixels are then read by nothing)
        features_read = not self.profile.perception.enabled and self.profile.controller.enabled
        decode_ahead = IMAGE_FEATURE_MODALITIES if features_read else frozenset()
        context = DriverContext(seed=self.seed, replay=self.session, decode_ahead=decode_ahead)
        session = Session(self.profile, clock, context, exports=self.exports,
                          tables=self.tables, observers=[self.collector], latency_model=model)
        session.hooks.inference.append(self.collector.measured)
        observe = watch.observer(self.session, self.control.record, self.control.foxglove, speed=self.speed,
                                 seed=self.seed, then=self.control.observe)
        if observe is not None:
            observe(session)
        if not lockstep:
            session.hooks.up.insert(0, clock.restart)  # log time starts with the pipeline, not before it
        marks: list[tuple[float, float, float]] = []  # the replay loop alone: weight loading excluded
        session.hooks.up.append(lambda: marks.append((time.perf_counter(), time.process_time(), time.thread_time())))
        # as in the daemon: a full collection would hold the GIL the detector's thread, the replay's
        # critical path, waits for (no collection first: the replay's clock is running by then)
        freeze = StartupFreeze(collect=False)
        session.hooks.up.append(freeze.up)
        try:
            await self._drive(session, clock, lockstep, stop)
        finally:
            if signals is not None:
                signals.unbind()
            freeze.release()
        started, cpu0, loop0 = marks[0] if marks else (time.perf_counter(), time.process_time(), time.thread_time())
        wall, cpu, loop_cpu = time.perf_counter() - started, time.process_time() - cpu0, time.thread_time() - loop0
        end = min(max(clock.now(), self.t0), self.t0 + self.duration)
        if stop.is_set():
            log.info("replay.stopped", replayed_s=round(end - self.t0, 3), of_s=round(self.duration, 3))
        result = self._result(session, end)
        result["stopped_early"] = stop.is_set()
        timing = {"wall_s": round(wall, 3),  # the replay loop alone: imports and weight loading excluded
                  "cpu_s": round(cpu, 3),  # process CPU time (all threads) over the same span
                  "loop_cpu_s": round(loop_cpu, 3)}  # the event loop's thread alone
        for key in TIMING_KEYS:  # measured latency: this machine's detector, not the robot's
            if key in result["compute"]:
                timing[key] = result["compute"].pop(key)
        return result, timing

    def _result(self, session: Any, end: float) -> dict[str, Any]:
        stage = session.pipeline.controller
        describe = stage.describe_action if stage is not None else None
        power = {s.name: s.power for s in self.profile.sensors}
        result = rpt.summarize(self.collector, self.t0, end, power, describe)
        result["latency_model"] = self.latency_source
        unserved = {name: u for name, d in sorted(session.pipeline.drivers.items())
                    if (u := getattr(d, "unserved", lambda _: None)(end)) is not None}
        result["unserved"] = unserved  # requests above what the log recorded, served at the recorded rate
        if stage is not None and stage.controller.table is not None:
            result["table"] = stage.table_source
            if self.profile.controller.policy == "learn":
                table, layout = stage.controller.table, stage.controller.layout()
                meta = table_meta(table, layout, {"profile": self.profile.name, "policy": "learn"})
                self.learned = StoredTable(meta, table.q.copy(), table.visits.copy(), "learned")
        return result

    async def _drive(self, session: Any, clock: Any, lockstep: bool, stop: asyncio.Event) -> None:
        end = self.t0 + self.duration
        ending = LogEnd(session, end, stop)  # the log's end, then the inference still running on it
        watcher = asyncio.create_task(ending.watch(), name="replay-end")
        task = asyncio.create_task(session.run(stop=ending.finished), name="replay-session")
        on_progress = self.control.on_progress

        def progress(t: float) -> None:
            if on_progress is not None:
                on_progress(min(t, end) - self.t0, self.duration)

        try:
            if lockstep:
                await clock.run(math.inf, on_step=progress, done=task.done)
            else:
                while not task.done():
                    progress(clock.now())
                    await asyncio.wait([task], timeout=0.5)
            await task
        finally:
            watcher.cancel()
