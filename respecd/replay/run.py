"""``respecd --replay LOG`` and ``replay(...)``: run a recorded session through the same
pipeline (a ``Session``), with every sensor replaced by a counterfactual ``ReplayDriver``,
and report how a policy did.

``--speed max`` runs in lockstep on the log's clock (``LockstepLoop`` + ``LockstepClock``)
and is deterministic: same log + profile + seed give the same decisions. Two things would
otherwise leak this machine's timing into the controller, so lockstep replaces them:
the CPU probe is off, and perception latency is modelled from the log (``LatencyModel``):
the controller sees the modelled latency, and perception is kept busy for it on the log's
clock, so it skips bundles as it did on the robot. The measured latency still goes into the
report's compute figures. ``--speed 1|2`` replays on a scaled wall clock with measured
latencies, like a live run.

A replay learns in memory: it never writes a state directory's table. ``state_dir`` only says
where to read a table from (never renamed, whatever is wrong with it); ``save_table`` is the one
place a learned table is written. (A profile with ``perception.runtime`` other than torch caches
its exported graphs in the state directory's ``exported/``, as the daemon does.) SIGTERM/SIGINT
end a replay early, with the report of what was replayed so far.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from respecd.drivers.replay import ReplayConfig
from respecd.errors import InputError
from respecd.record.reader import SessionLog, open_log
from respecd.replay import detector, report_out, watch
from respecd.replay import report as rpt
from respecd.replay.ending import LogEnd
from respecd.replay.latency import LatencyModel
from respecd.replay.profile import first_frames, replay_profile

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)


def run_replay(args: argparse.Namespace, signals: Any = None) -> int:
    """Entry point from ``respecd --replay``; InputError/ConfigError become exit 2."""
    report = replay(args.replay, config=args.config, policy=args.policy, speed=str(getattr(args, "speed", None) or "1"),
                    seed=args.seed or 0, duration=args.duration, report=args.report, state_dir=args.state_dir,
                    save_table=getattr(args, "save_table", None), signals=signals,
                    topics=getattr(args, "topics", None), record=getattr(args, "record", None),
                    foxglove=getattr(args, "foxglove", None))
    print(report_out.table(report))
    return 1 if _report_skipped(report) else 0


def _report_skipped(report: dict[str, Any]) -> bool:
    """A ROS bag's messages that could not be read, per topic (topic, index, why) on stderr; True if any
    (the exit status is then 1: the replay ran, but without those frames)."""
    skipped: dict[str, Any] = {}
    for entry in report["policies"].values():
        skipped.update(entry.get("skipped") or {})
    for topic, lost in skipped.items():
        first = "; ".join(f"index {s['index']}: {s['why']}" for s in lost["first"])
        more = f" (and {lost['count'] - len(lost['first'])} more)" if lost["count"] > len(lost["first"]) else ""
        print(f"respecd: {report['log']['path']}: {topic}: {lost['count']} message(s) skipped, unreadable: "
              f"{first}{more}", file=sys.stderr)
    return bool(skipped)


def replay(log_path: str | Path, *, config: str | Path | None = None, policy: str | None = None, speed: str = "max",
           seed: int = 0, duration: float | None = None, report: str | Path | None = None,
           state_dir: str | Path | None = None, save_table: str | Path | None = None,
           signals: Any = None, topics: str | None = None, observe: Any = None, record: str | None = None,
           foxglove: str | None = None) -> dict[str, Any]:
    """Replay ``log_path`` under ``policy``; the report (``{"log", "policies"}``), also merged
    into the JSON at ``report`` (with a PNG timeline) when given. ``config``: a profile file
    to replay with instead of the one recorded in the log. ``signals``: a ``StopSignals``
    whose SIGTERM/SIGINT end the replay early (the report then covers what was replayed).
    ``topics``: for a ROS bag, which topic is which sensor (``rgb=/cam/image_raw,imu=...``).
    ``observe``: called with the replay's ``Session`` before it starts (benchmarks attach hooks).
    ``record``/``foxglove``: the counterfactual session as a log / served live (``replay.watch``)."""
    if duration is not None and not duration > 0:
        raise InputError(f"--duration: expected a positive number of seconds, got {duration}")
    session = open_source(log_path, topics)
    if session.truncated:
        print(f"respecd: warning: {session.path} was cut short (no summary); replaying its "
              f"{session.duration_s:.2f} s up to the last complete chunk", file=sys.stderr)
        log.warning("replay.truncated", path=str(session.path), readable_s=round(session.duration_s, 3))
    base = _base_profile(config, session)
    chosen_by, foreign = detector.provenance(config, session)
    if foreign:
        detector.announce(str((base.get("perception") or {}).get("weights", "builtin:sim-rover")))
    firsts = first_frames(session)
    if not firsts:
        raise InputError(f"{session.path}: the log holds no sensor frames to replay")
    profile = replay_profile(base, session, firsts, seed=seed, lockstep=speed == "max", policy=policy)
    t0 = min(f.t for f in firsts.values())
    span = session.duration_s if duration is None else min(duration, session.duration_s)
    tables = _tables(profile, state_dir, save_table)
    exports = Path(state_dir) / "exported" if state_dir else None  # another runtime's graphs: a cache, not state
    observe = watch.observer(session, record, foxglove, speed=speed, seed=seed, then=observe)
    entry = _Replay(profile, session, speed, t0, span, seed, tables, observe, exports).run(signals)
    entry.update(policy=profile.controller.policy, seed=seed, speed=speed, truncated=session.truncated)
    if hasattr(session, "skipped_report"):  # a ROS bag: its unreadable messages, per topic
        entry["skipped"] = session.skipped_report()
    entry["detector"] = detector.entry(profile.perception, base.get("perception"), chosen_by, foreign)
    return _emit(report, session, entry)


def open_source(path: str | Path, topics: str | None) -> Any:
    """A respecd log, or a robot's ROS bag read through the topic map (guessed, and the
    guess printed, when ``topics`` is absent)."""
    from respecd.record.rosbag_in import is_bag, open_bag, parse_topics

    if not is_bag(path):
        if topics:
            raise InputError(f"--topics: applies to ROS bags only; {path} is a respecd log (its sensors are named)")
        return open_log(path)
    bag = open_bag(path, parse_topics(topics))
    if not bag.topic_map:
        raise InputError(f"{path}: no sensor_msgs Image/CompressedImage/PointCloud2/Imu topic to replay "
                         f"(topics: {', '.join(f'{t} [{c.schema}]' for t, c in sorted(bag.channels.items()))})")
    for note in bag.metadata_notes:
        print(f"respecd: warning: {path}: metadata.yaml: {note}; replaying what the storage holds", file=sys.stderr)
    if not topics:
        guess = ",".join(f"{k}={v}" for k, v in bag.topic_map.items())
        print(f"respecd: --topics not given; guessed from message types: --topics {guess}", file=sys.stderr)
    return bag


def _base_profile(config: str | Path | None, session: Any) -> dict[str, Any]:
    """``config`` when given explicitly, else the profile recorded in the log (for a ROS bag:
    the default profile's perception and controller with one sensor per mapped topic)."""
    from respecd.config import DEFAULT_PROFILE, load_profile

    explicit = config is not None and str(config) not in ("", DEFAULT_PROFILE)
    if getattr(session, "topic_map", None) is not None:
        source = config if config is not None and explicit else DEFAULT_PROFILE
        base = dict(load_profile(source).model_dump(mode="json"))
        named = {s["name"]: s for s in base.get("sensors", [])} if explicit else {}
        base["sensors"] = [named.get(name, {"name": name, "modality": name}) for name in session.topic_map]
        return base
    if config is not None and explicit:
        return dict(load_profile(config).model_dump(mode="json"))
    recorded = session.profile_dict()
    if recorded is None:
        damage = getattr(session, "damage", None)
        why = f"the log's recorded profile was lost to damage ({damage[0].describe()})" if damage else \
            "the log has no recorded profile"
        raise InputError(f"{session.path}: {why}; pass the one it ran with: --config FILE")
    return dict(recorded)


def _tables(profile: Profile, state_dir: str | Path | None, save_table: str | Path | None) -> Any:
    """Read (never rename) the state directory's table when given; write only ``save_table``."""
    from respecd.control.persist import table_path
    from respecd.control.stage import TableFiles

    load = table_path(Path(state_dir), profile.controller.table_file, profile.name) if state_dir else None
    if save_table is not None and profile.controller.policy != "learn":
        log.warning("replay.save_table_ignored", policy=profile.controller.policy, reason="only learn updates a table")
    return TableFiles(load, Path(save_table) if save_table is not None else None, set_aside=False)


class _Replay:
    """One replay run: a session around replay drivers, its clock driven to the end."""

    def __init__(self, profile: Profile, session: SessionLog, speed: str, t0: float, duration: float, seed: int,
                 tables: Any, observe: Any = None, exports: Path | None = None) -> None:
        self.profile = profile
        self.exports = exports
        self.observe = observe
        self.session = session
        self.speed = speed
        self.t0 = t0
        self.duration = duration
        self.seed = seed
        self.tables = tables
        rgb = next((s for s in profile.sensors if isinstance(s, ReplayConfig) and s.modality == "rgb"), None)
        truth, self.logged_percepts = session.side_data(rgb.source or rgb.name if rgb else None)
        self.collector = rpt.Collector(
            rpt.build_reference(truth, self.logged_percepts),
            rgb.native_resolution if rgb is not None else None,
        )
        self.latency_source = "measured" if profile.perception.enabled else "none (perception off)"

    def run(self, signals: Any) -> dict[str, Any]:
        from respecd.replay.lockstep import LockstepLoop

        if self.speed == "max":
            with asyncio.Runner(loop_factory=LockstepLoop) as runner:
                return runner.run(self._run(signals))
        return asyncio.run(self._run(signals))

    async def _run(self, signals: Any) -> dict[str, Any]:
        from respecd.clock import ScaledClock
        from respecd.drivers.base import DriverContext
        from respecd.replay.lockstep import LockstepClock
        from respecd.session import Session

        lockstep = self.speed == "max"
        stop = signals.bind() if signals is not None else asyncio.Event()
        clock: Any = LockstepClock(self.t0) if lockstep else ScaledClock(float(self.speed), start=self.t0)
        model = None
        if lockstep and self.profile.perception.enabled:
            model = LatencyModel.from_percepts(self.logged_percepts)
            self.latency_source = f"{model.source}: {model.s_per_pixel * 1e9:.1f} ns/px"
        # without a detector the controller's features read every frame: decode them ahead, off the loop
        decode_ahead = not self.profile.perception.enabled and self.profile.controller.enabled
        context = DriverContext(seed=self.seed, replay=self.session, decode_ahead=decode_ahead)
        session = Session(self.profile, clock, context, exports=self.exports,
                          tables=self.tables, observers=[self.collector], latency_model=model)
        session.hooks.inference.append(self.collector.measured)
        if self.observe is not None:
            self.observe(session)
        if not lockstep:
            session.hooks.up.insert(0, clock.restart)  # log time starts with the pipeline, not before it
        marks: list[tuple[float, float, float]] = []  # the replay loop alone: weight loading excluded
        session.hooks.up.append(lambda: marks.append((time.perf_counter(), time.process_time(), time.thread_time())))
        try:
            await self._drive(session, clock, lockstep, stop)
        finally:
            if signals is not None:
                signals.unbind()
        started, cpu0, loop0 = marks[0] if marks else (time.perf_counter(), time.process_time(), time.thread_time())
        wall, cpu, loop_cpu = time.perf_counter() - started, time.process_time() - cpu0, time.thread_time() - loop0
        end = min(max(clock.now(), self.t0), self.t0 + self.duration)
        if stop.is_set():
            log.info("replay.stopped", replayed_s=round(end - self.t0, 3), of_s=round(self.duration, 3))
        controller = session.pipeline.controller
        describe = controller.describe_action if controller is not None else None
        power = {s.name: s.power for s in self.profile.sensors}
        entry = rpt.summarize(self.collector, self.t0, end, power, describe)
        entry["wall_s"] = round(wall, 3)  # the replay loop alone: imports and weight loading excluded
        entry["cpu_s"] = round(cpu, 3)  # process CPU time (all threads) over the same span
        entry["loop_cpu_s"] = round(loop_cpu, 3)  # the event loop's thread alone
        entry["latency_model"] = self.latency_source
        entry["stopped_early"] = stop.is_set()
        return entry

    async def _drive(self, session: Any, clock: Any, lockstep: bool, stop: asyncio.Event) -> None:
        end = self.t0 + self.duration
        bar = _progress_bar()(total=round(self.duration, 1), unit="s", desc="replay", mininterval=1.0,
                              disable=not progress_shown(self.duration, sys.stderr),
                              file=sys.stderr, leave=False, bar_format=BAR_FORMAT)
        ending = LogEnd(session, end, stop)  # the log's end, then the inference still running on it
        watcher = asyncio.create_task(ending.watch(), name="replay-end")
        task = asyncio.create_task(session.run(stop=ending.finished), name="replay-session")

        def progress(t: float) -> None:
            done = round(min(t, end) - self.t0, 1)
            if done > bar.n:
                bar.update(done - bar.n)

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
            bar.close()


def _progress_bar() -> Any:
    try:
        from tqdm import tqdm
    except ImportError:  # the lab extra: without it a replay runs without a progress bar
        return _NoBar

    class Bar(tqdm):
        monitor_interval = 0  # no monitor thread: it would outlive the replay by 10 s

        @property
        def format_dict(self) -> dict[str, Any]:
            values = super().format_dict
            values["speed"] = speed_label(values["n"], values["elapsed"])
            return values

    return Bar


# log seconds over wall seconds is the replay's speed: "3.2x real time", not tqdm's "3.2s/s"
BAR_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of log [{elapsed}<{remaining}, {speed}]"


def progress_shown(duration_s: float, stream: Any) -> bool:
    """A bar for a person at a terminal, on a replay long enough to watch; never in a pipe,
    a file or the journal, where its redraws would be lines of noise."""
    isatty = getattr(stream, "isatty", None)
    return duration_s >= 20 and isatty is not None and bool(isatty())


def speed_label(log_s: float, wall_s: float) -> str:
    """How fast a replay runs, as a person reads it."""
    return f"{log_s / wall_s:.1f}× real time" if wall_s > 0 and log_s > 0 else "– × real time"


class _NoBar:
    """The part of tqdm's interface the replay uses, doing nothing."""

    def __init__(self, **_: Any) -> None:
        self.n = 0.0

    def update(self, step: float) -> None:
        self.n += step

    def close(self) -> None:
        pass


def _emit(report_path: str | Path | None, session: SessionLog, entry: dict[str, Any]) -> dict[str, Any]:
    """The report of this policy, merged into and written as JSON + PNG at ``report_path``."""
    log_id = {"path": str(session.path.resolve()), "bytes": session.size, "start_ns": session.start_ns}
    policy = entry["policy"]
    if report_path is None:
        return {"log": log_id, "policies": {policy: entry}}
    path = Path(report_path)
    report = report_out.merge(path, log_id, policy, entry)
    # stopped by a signal: the JSON only, the timeline figure would take the stop past its 2 s
    png = report_out.write(path, report, figure=not entry.get("stopped_early"))
    log.info("replay.report", json=str(path), png=str(png) if png else None, policies=list(report["policies"]))
    return report
