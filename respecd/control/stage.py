"""The controller stage: the daemon's side of the control loop.

It turns percepts into the loop's samples (per-percept features, in a worker thread on a wall
clock, on the loop in a lockstep replay), gives
the loop the drivers to apply decisions to (each with a timeout, concurrently; a failing
driver is logged and retried at the next decision) and the system probe (worker thread),
and keeps the Q-table on disk: loaded when ``run`` first starts, saved every ``save_every``
updates and on ``close``. The decision itself is ``ControlLoop``'s, the same code a replay,
policy training and the scenario benchmark run.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from respecd.applied import AppliedConfigs
from respecd.clock import Clock, MonotonicClock
from respecd.control.config import ControllerConfig
from respecd.control.controller import Controller
from respecd.control.features import FeatureExtractor
from respecd.control.loop import ControlLoop
from respecd.control.persist import StoredTable, load_into, save_table, table_path
from respecd.control.probe import SystemProbe, SystemSample
from respecd.control.shipped import load_shipped
from respecd.drivers.base import Driver
from respecd.errors import DriverError, InputError
from respecd.messages import Decision, Percept, SensorConfig
from respecd.queues import DropOldestQueue
from respecd.sensors import Capabilities
from respecd.timeouts import within

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class TableFiles:
    """Where a run's Q-table comes from and where it goes.

    A live run reads and writes its state directory's table and renames a bad one aside; a
    replay reads one without ever changing it, and writes only where it is told to. A replay is
    ``strict``: a table that does not fit its profile, or ``exploit`` with no table at all, is an
    error (exit 2) naming why — unless ``allow_none``, when it runs without one and says so.
    ``given``: the table's contents, already read (a fleet's workers are given it, not a path).
    """

    load: Path | None
    save: Path | None
    set_aside: bool = False
    given: StoredTable | None = None
    strict: bool = False
    allow_none: bool = False

    @classmethod
    def state_dir(cls, directory: Path, config: ControllerConfig, profile_name: str) -> TableFiles:
        path = table_path(Path(directory), config.table_file, profile_name)
        return cls(path, path, set_aside=True)


SAVE_RETRY_S = 5.0  # first wait (session s) before a failed save is tried again; doubles
MAX_SAVE_RETRY_S = 300.0


@dataclass
class SaveFailure:
    """Saves of the Q-table failing since ``since`` (the state directory full, read-only, gone)."""

    since: float
    first_error: str
    error: str = ""
    failures: int = 0
    retry_at: float = 0.0


class DriverSensors:
    """The loop's ``Sensors`` on drivers: every apply concurrently, each with a timeout."""

    def __init__(self, drivers: Mapping[str, Driver], timeout_s: float) -> None:
        self.drivers = drivers
        self.timeout_s = timeout_s

    async def apply(self, requests: Mapping[str, SensorConfig]) -> dict[str, SensorConfig | None]:
        names = list(requests)
        results = await asyncio.gather(*(self._apply_one(n, requests[n]) for n in names))
        return dict(zip(names, results, strict=True))

    async def _apply_one(self, name: str, request: SensorConfig) -> SensorConfig | None:
        try:
            applied = await within(self.drivers[name].apply(request), self.timeout_s)
        except (DriverError, asyncio.TimeoutError) as err:
            log.warning("apply_failed", sensor=name, error=repr(err))
            return None
        except Exception:  # one driver's bug must not stop the others being configured
            log.exception("apply_crashed", sensor=name)
            return None
        if applied.notes:
            log.info("apply_clamped", sensor=name, notes=list(applied.notes))
        return applied


class ThreadedProbe:
    """The loop's ``LoadProbe`` on /proc and sysfs: reads run in a worker thread."""

    def __init__(self, probe: SystemProbe) -> None:
        self.probe = probe

    async def read(self) -> SystemSample:
        return await asyncio.to_thread(self.probe.read)


class ControllerStage:
    """Owns the controller of one run; the session constructs it and runs ``run``."""

    def __init__(
        self,
        config: ControllerConfig,
        profile: Profile,
        drivers: dict[str, Driver],
        clock: Clock,
        state_dir: Path | None = None,
        applied: AppliedConfigs | None = None,
        tables: TableFiles | None = None,
    ) -> None:
        self.config = config
        self.profile = profile
        self.drivers = drivers
        self.clock = clock
        self.controller = Controller.from_profile(config, profile, _capabilities(drivers))
        self.applied = applied if applied is not None else AppliedConfigs({n: d.applied for n, d in drivers.items()})
        self.tables = tables or TableFiles.state_dir(state_dir or Path("."), config, profile.name)
        self.table_path = self.tables.load or self.tables.save
        self.loop = ControlLoop(self.controller, clock, DriverSensors(drivers, config.apply_timeout_s), self.applied)
        self.loop.on_decision.append(self._log_decision)
        self.loop.after_decision = self._maybe_save
        self._features = FeatureExtractor()
        self._features_off_loop = isinstance(clock, MonotonicClock)  # a wall clock (live, --speed 1|2)
        self._prepared = False
        self._saved_updates = 0
        self._unsaved: SaveFailure | None = None  # the state directory refusing the table's saves
        self.table_source: str | None = None  # which table the run started from (the replay's report says)

    # public ---------------------------------------------------------------------------
    @property
    def on_decision(self) -> list[Callable[[Decision], None]]:
        return self.loop.on_decision

    @property
    def last(self) -> Decision | None:
        return self.loop.last

    def describe_action(self, action: int) -> str:
        return self.controller.describe_action(action)

    def describe_state(self, bins: tuple[int, ...]) -> str:
        return self.controller.states.describe(bins)

    async def run(self, percepts: DropOldestQueue[Percept]) -> None:
        """Forever: percepts into the window, a decision every period. Cancel to stop (then ``close``)."""
        await self.prepare()
        tasks = [
            asyncio.create_task(self._consume(percepts), name="controller-percepts"),
            asyncio.create_task(self.loop.run(), name="controller-decide"),
        ]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in done:
                task.result()  # re-raise a crash for the supervisor
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    async def decide(self, now: float) -> Decision | None:
        return await self.loop.decide(now)

    async def close(self) -> None:
        """Save the Q-table (learn mode) so the next start resumes from it."""
        if self._prepared and self.config.policy == "learn":
            await self._save()
            failure, table = self._unsaved, self.controller.table
            if failure is not None and table is not None:  # what this run learned since is lost
                log.error("qtable_unsaved_at_stop", path=str(self.tables.save), error=failure.error,
                          failures=failure.failures, unsaved_s=round(self.clock.now() - failure.since, 1),
                          updates_lost=table.updates - self._saved_updates)

    async def prepare(self) -> None:
        """Load the Q-table and prime the system probe (once: a supervisor restart keeps the table)."""
        if self._prepared:
            return
        if self.controller.table is not None:
            await self._load_table()
        if self.config.system_probe:
            rails = self.profile.telemetry.power_rails == "auto"
            probe = await asyncio.to_thread(SystemProbe, Path("/"), rails)
            await asyncio.to_thread(probe.read)  # prime the CPU counters
            self.loop.probe = ThreadedProbe(probe)
        self._prepared = True
        if self.config.policy == "learn" and self.config.reward.quality == "truth":
            log.warning("reward_quality_without_truth", reads="conf_agg",
                        note="reward.quality: truth is for training in the simulator; no ground truth comes here")
        log.info("controller_ready", policy=self.config.policy, states=self.controller.states.size,
                 actions=self.controller.space.n, table_columns=self.controller.space.columns,
                 table=str(self.table_path))

    _prepare = prepare  # the name the tests used

    async def _load_table(self) -> None:
        table, layout, tables = self.controller.table, self.controller.layout(), self.tables
        assert table is not None
        source = None
        if tables.strict and tables.given is None and tables.load is not None and tables.load.is_file():
            tables = replace(tables, given=await asyncio.to_thread(StoredTable.read, tables.load))
        if tables.given is not None:
            tables.given.restore_into(table, layout, self.profile.name)  # InputError: it does not fit
            source = f"{tables.given.name} ({tables.given.updates} updates)"
        elif tables.load is not None and await asyncio.to_thread(load_into, tables.load, table, layout,
                                                                  tables.set_aside):
            source = f"{tables.load.name} ({table.updates} updates)"
        if source is None and self._starts_from_shipped():  # nothing learned here yet: the shipped table
            if await asyncio.to_thread(load_shipped, table, layout):
                source = f"shipped ({table.updates} updates)"
        self._saved_updates = table.updates
        self.controller.refining = self.config.policy == "learn" and source is not None
        if source is None and self.config.policy == "exploit":
            if tables.strict and not tables.allow_none:
                where = str(tables.load) if tables.load is not None else "no --table given"
                raise InputError(f"--policy exploit: no Q-table fits this profile ({self.profile.name!r}; {where}; "
                                 "the shipped table is for another layout): pass one learned for it, or "
                                 "--allow-no-table to run without one (its report row then says 'no table')")
            log.warning("exploit_without_table", path=str(self.table_path))
            source = "no table"
        self.table_source = source or "new"  # learn from scratch

    def _starts_from_shipped(self) -> bool:
        """exploit always falls back to the shipped table; learn does when warm-started, so a fresh robot
        runs what was learned for its layout instead of exploring at random (epsilon_start) for minutes."""
        return self.config.policy == "exploit" or (self.config.policy == "learn" and self.config.warm_start)

    # internals ------------------------------------------------------------------------
    async def _consume(self, percepts: DropOldestQueue[Percept]) -> None:
        while True:
            percept = await percepts.get()
            # stamped on arrival: with a slow detector percept.t lags the clock by its latency
            received = self.clock.now()
            if self._features_off_loop:
                # ~0.3 ms of numpy for 720p, each call a chance for another thread to take the
                # GIL while the loop waits: in a worker (one at a time: the motion state is ordered)
                sample = await asyncio.to_thread(self._features.sample, percept, received)
            else:  # a lockstep clock: nothing waits on the loop, and a hop would only slow a replay
                sample = self._features.sample(percept, received)
            self.loop.add(sample)

    def _log_decision(self, decision: Decision) -> None:
        log.info(
            "decision",
            state=self.describe_state(decision.state),
            action=self.describe_action(decision.action),
            reward=round(decision.reward, 4),
            epsilon=round(decision.epsilon, 4),
            held=bool(decision.terms.get("held")),
            **{k: round(v, 4) for k, v in decision.terms.items() if k not in ("reward", "held")},
        )

    def table_status(self) -> dict[str, Any] | None:
        """For the status line: None while saves succeed, else since when and why they fail."""
        failure = self._unsaved
        if failure is None:
            return None
        return {"state": "unsaved", "since_s": round(self.clock.now() - failure.since, 1),
                "failures": failure.failures, "error": failure.error}

    async def _maybe_save(self, decision: Decision) -> None:
        table = self.controller.table
        if self.config.policy == "learn" and table is not None:
            due = table.updates - self._saved_updates >= self.config.save_every
            if due and (self._unsaved is None or self.clock.now() >= self._unsaved.retry_at):
                await self._save()

    async def _save(self) -> None:
        table = self.controller.table
        if table is None or self.tables.save is None:
            return
        info = {"profile": self.profile.name, "policy": self.config.policy}
        try:
            await asyncio.to_thread(save_table, self.tables.save, table, self.controller.layout(), info)
        except OSError as err:
            self._save_failed(err)
            return
        self._saved_updates = table.updates
        if self._unsaved is not None:
            failure, self._unsaved = self._unsaved, None
            log.info("qtable_save_recovered", path=str(self.tables.save), failures=failure.failures,
                     unsaved_s=round(self.clock.now() - failure.since, 1), first_error=failure.first_error)
        log.info("qtable_saved", path=str(self.tables.save), updates=table.updates)

    def _save_failed(self, err: OSError) -> None:
        """One error line when saves start failing; then retries back off (the status line says it
        is unsaved), and ``qtable_save_recovered`` sums it up once a save succeeds."""
        now, error = self.clock.now(), err.strerror or str(err)
        failure = self._unsaved
        if failure is None:
            failure = self._unsaved = SaveFailure(since=now, first_error=error)
            log.error("qtable_save_failed", path=str(self.tables.save), error=error,
                      retry="with backoff; the status line shows it unsaved, recovery is logged once")
        failure.failures += 1
        failure.error = error
        failure.retry_at = now + min(SAVE_RETRY_S * 2 ** (failure.failures - 1), MAX_SAVE_RETRY_S)


def _capabilities(drivers: Mapping[str, Driver]) -> dict[str, Capabilities]:
    caps = {}
    for name, driver in drivers.items():
        with contextlib.suppress(Exception):  # capabilities may need start(); fall back to the profile
            caps[name] = driver.capabilities
    return caps
