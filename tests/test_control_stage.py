"""ControllerStage driving real simulated drivers on a ManualClock: decisions, applies,
taps, hints, a failing driver, and the Q-table surviving a restart."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from respecd.clock import ManualClock
from respecd.config import load_profile
from respecd.control.persist import read_table
from respecd.control.shipped import shipped_table_path
from respecd.control.stage import ControllerStage
from respecd.drivers.base import DriverContext
from respecd.drivers.sim import SimDriver
from respecd.errors import DriverIOError
from respecd.messages import Bundle, Decision, Health, Percept, SensorConfig, SyncStats
from respecd.queues import DropOldestQueue
from respecd.sim.world import SimulationConfig

TICK_S = 0.1  # synchronizer tick of the test pipeline (10 Hz)


class BrokenRadar(SimDriver):
    """A simulated radar whose CLI port stopped answering: every apply fails."""

    async def apply(self, request: SensorConfig) -> SensorConfig:
        raise DriverIOError("radar CLI did not answer 'Done'")


class Rig:
    """Real SimDrivers + the stage; the test moves the clock and plays the synchronizer."""

    def __init__(self, tmp_path: Path, policy: str, broken_radar: bool = False, save_every: int = 1000,
                 warm_start: bool = False) -> None:
        profile = load_profile("builtin:sim-rover")
        self.clock = ManualClock()
        context = DriverContext(
            seed=5,
            simulation=SimulationConfig(scenarios=["good-light-static", "poor-light-static"], scenario_duration_s=3.0),
        )
        self.drivers: dict[str, SimDriver] = {}
        for sensor in profile.sensors:
            if sensor.modality in ("rgb", "thermal", "radar"):
                cls = BrokenRadar if broken_radar and sensor.modality == "radar" else SimDriver
                self.drivers[sensor.name] = cls(
                    sensor.model_copy(update={"render_in_thread": "never"}), self.clock, context
                )
        config = profile.controller.model_copy(
            update={"policy": policy, "system_probe": False, "min_dwell_s": 0.0, "save_every": save_every,
                    "warm_start": warm_start}
        )
        self.stage = ControllerStage(config, profile, self.drivers, self.clock, tmp_path)
        self.decisions: list[Decision] = []
        self.hints = 0
        self.stage.on_decision.append(self.decisions.append)
        self.stage.loop.on_window.append(self._hint)
        self.percepts: DropOldestQueue[Percept] = DropOldestQueue(4, "percepts")
        self.latest: dict = {}

    def _hint(self) -> None:
        self.hints += 1

    async def _read(self, driver: SimDriver) -> None:
        async for frame in driver.frames():
            self.latest[frame.modality] = frame

    async def run(self, seconds: float, percept_lag_s: float = 0.0) -> None:
        for driver in self.drivers.values():
            await driver.start()
        readers = [asyncio.create_task(self._read(d), name=f"read-{n}") for n, d in self.drivers.items()]
        stage = asyncio.create_task(self.stage.run(self.percepts), name="controller")
        try:
            for _ in range(round(seconds / TICK_S)):
                self.clock.advance(TICK_S)
                for _ in range(20):
                    await asyncio.sleep(0)
                conf = 0.8 if "thermal" in self.latest else 0.2
                t = self.clock.now() - percept_lag_s  # a slow detector hands over old bundles
                bundle = Bundle(t, dict(self.latest), SyncStats(10.0, 1.0, 0.0, Health.GOOD))
                self.percepts.put(Percept(t, (), conf, {"rgb": 0.3, "thermal": 0.7}, 0.01, bundle))
            await asyncio.sleep(0.05)  # let the last decision's apply finish
        finally:
            stage.cancel()
            await asyncio.gather(stage, return_exceptions=True)
            await self.stage.close()
            for driver in self.drivers.values():
                await driver.stop()
            await asyncio.gather(*readers)


@pytest.mark.slow
async def test_learn_run_decides_applies_and_persists(tmp_path: Path) -> None:
    rig = Rig(tmp_path, "learn")
    await rig.run(6.0)
    assert len(rig.decisions) >= 5
    assert rig.hints >= len(rig.decisions)
    assert rig.stage.last is rig.decisions[-1]
    names = [slot.name for slot in rig.stage.controller.space.slots]
    for name, applied in zip(names, rig.decisions[-1].configs, strict=True):
        if name in rig.drivers:
            assert rig.drivers[name].applied == applied  # what the drivers really run
    assert {"quality", "power", "latency", "switch", "reward", "td_error"} <= set(rig.decisions[-1].terms)
    assert len(rig.decisions[-1].q_values) == rig.stage.controller.space.columns
    table = rig.stage.controller.table
    assert table.updates == len(rig.decisions) - 1
    assert rig.stage.table_path.exists()

    again = Rig(tmp_path, "exploit")
    await again.stage._prepare()
    assert again.stage.controller.table.updates == table.updates
    assert (again.stage.controller.table.q == table.q).all()


async def test_learn_on_a_fresh_state_dir_starts_from_the_shipped_table(tmp_path: Path) -> None:
    _, shipped_q, _ = read_table(shipped_table_path())
    rig = Rig(tmp_path, "learn", warm_start=True)
    await rig.stage._prepare()
    table = rig.stage.controller.table
    assert rig.stage.table_source is not None and rig.stage.table_source.startswith("shipped")
    assert (table.q == shipped_q).all() and table.updates > 0
    assert table.epsilon < rig.stage.config.learning.epsilon_start  # the trained table's, not a fresh start

    cold = Rig(tmp_path / "cold", "learn", warm_start=False)
    await cold.stage._prepare()
    assert cold.stage.table_source == "new" and cold.stage.controller.table.updates == 0


async def test_a_warm_started_learner_acts_on_what_the_shipped_table_learned(tmp_path: Path) -> None:
    """Greedy over a loaded table's optimistic (never tried) cells would run each sensor at whatever the
    shipped table tried least; a warm-started learner acts as exploit does and explores at epsilon only."""
    rig = Rig(tmp_path, "learn", warm_start=True)
    await rig.stage._prepare()
    controller, table = rig.stage.controller, rig.stage.controller.table
    assert controller.refining
    table.epsilon = 0.0
    exploit = Rig(tmp_path / "exploit", "exploit")
    await exploit.stage._prepare()
    chosen = [controller._choose(state, ())[0] for state in range(table.shape[0])]
    assert chosen == [exploit.stage.controller._choose(state, ())[0] for state in range(table.shape[0])]
    optimistic = [s for s in range(table.shape[0]) if table.greedy(s) != chosen[s]]
    assert len(optimistic) > table.shape[0] // 2  # states the shipped table barely knows: greedy picks untried cells

    table.epsilon = 1.0  # every sensor explores: it still tries what the table never tried
    assert len({controller._choose(optimistic[0], ())[0] for _ in range(50)}) > 1
    newcomer, known = optimistic[0], next(s for s in range(table.shape[0]) if s in controller._learned_states())
    assert newcomer not in controller._learned_states()
    for _ in range(rig.stage.config.learning.exploit_min_visits):  # its own updates make a state learned
        controller.learn(newcomer, chosen[newcomer], 0.5, newcomer)
    assert newcomer in controller._learned_states() and known in controller._learned_states()

    cold = Rig(tmp_path / "cold", "learn", warm_start=False)
    await cold.stage._prepare()
    assert not cold.stage.controller.refining  # learning from nothing: optimism explores


async def test_learn_keeps_its_own_table_over_the_shipped_one(tmp_path: Path) -> None:
    rig = Rig(tmp_path, "learn", warm_start=False)
    await rig.run(3.0)
    learned = rig.stage.controller.table.q.copy()
    again = Rig(tmp_path, "learn", warm_start=True)
    await again.stage._prepare()
    assert again.stage.table_source is not None and not again.stage.table_source.startswith("shipped")
    assert (again.stage.controller.table.q == learned).all()


async def test_scene_turning_dark_moves_the_heuristic_to_thermal(tmp_path: Path) -> None:
    rig = Rig(tmp_path, "heuristic")
    await rig.run(6.0)  # 3 s of good light, then 3 s of poor light
    states = [rig.stage.controller.states.names(d.state)["illumination"] for d in rig.decisions]
    assert states[-1] == "dark" and "dark" not in states[:2]
    thermal = rig.drivers["thermal"].applied
    rgb = rig.drivers["rgb"].applied
    assert thermal.resolution == (320, 240)
    assert rgb.resolution == (640, 360)
    assert not (tmp_path / "qtable-sim-rover.npz").exists()  # baselines keep no table


async def test_a_failing_driver_is_logged_and_the_rest_are_configured(tmp_path: Path) -> None:
    rig = Rig(tmp_path, "static", broken_radar=True)
    radar_before = rig.drivers["radar"].applied
    await rig.run(2.0)
    assert rig.decisions
    assert rig.drivers["rgb"].applied.resolution == (1280, 720) and rig.drivers["rgb"].applied.rate_hz == 30.0
    assert rig.drivers["thermal"].applied.resolution == (320, 240)
    assert rig.drivers["radar"].applied == radar_before  # unchanged, retried at every decision


async def test_percepts_count_when_they_arrive_even_from_a_slow_detector(tmp_path: Path) -> None:
    rig = Rig(tmp_path, "learn")
    await rig.run(4.0, percept_lag_s=2.5)  # 2.5 s of inference latency: older than the 1 s window
    assert len(rig.decisions) >= 3


@pytest.mark.parametrize("policy", ["learn", "static"])
async def test_close_before_run_does_not_clobber_a_saved_table(tmp_path: Path, policy: str) -> None:
    rig = Rig(tmp_path, policy)
    await rig.stage.close()
    assert list(tmp_path.iterdir()) == []


async def test_exploit_with_an_empty_state_dir_uses_the_shipped_table(tmp_path: Path) -> None:
    rig = Rig(tmp_path, "exploit")
    await rig.run(1.5)
    assert rig.stage.controller.table.updates > 0  # learned offline by `respecd train-policy`
    assert not list(tmp_path.glob("*.npz"))  # exploit never writes a table


async def test_a_truth_quality_profile_says_the_daemon_learns_from_confagg(tmp_path: Path) -> None:
    from structlog.testing import capture_logs

    rig = Rig(tmp_path, "learn")
    reward = rig.stage.config.reward.model_copy(update={"quality": "truth"})
    rig.stage.config = rig.stage.config.model_copy(update={"reward": reward})
    with capture_logs() as logs:
        await rig.stage.prepare()
    said = [e for e in logs if e["event"] == "reward_quality_without_truth"]
    assert len(said) == 1 and said[0]["log_level"] == "warning" and said[0]["reads"] == "conf_agg"


@pytest.mark.slow
async def test_a_state_directory_that_fails_is_one_error_a_status_flag_and_a_summary(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A state directory that refused every save logged qtable_save_failed once a second (40 in 40 s)."""
    import errno

    from structlog.testing import capture_logs

    import respecd.control.stage as stage_module
    from respecd.status import format_line

    rig = Rig(tmp_path, "learn", save_every=1)
    real_save, statuses = stage_module.save_table, []

    def flaky_save(*args, **kwargs):
        statuses.append(rig.stage.table_status())
        if rig.clock.now() < 20.0:
            raise OSError(errno.EROFS, "Read-only file system")
        return real_save(*args, **kwargs)

    monkeypatch.setattr(stage_module, "save_table", flaky_save)
    with capture_logs() as logs:
        await rig.run(40.0)
    failed = [e for e in logs if e["event"] == "qtable_save_failed"]
    recovered = [e for e in logs if e["event"] == "qtable_save_recovered"]
    assert len(failed) == 1 and failed[0]["log_level"] == "error" and failed[0]["error"] == "Read-only file system"
    assert len(recovered) == 1 and recovered[0]["failures"] >= 2 and recovered[0]["unsaved_s"] >= 15
    assert len(statuses) < 30  # retried with backoff, not at every decision
    unsaved = next(s for s in statuses if s is not None)
    assert unsaved["state"] == "unsaved" and unsaved["error"] == "Read-only file system"
    assert rig.stage.table_status() is None and rig.stage.table_path.exists()
    line = format_line({"t": 9.0, "sensors": {}, "sync": {"rate_hz": 10, "health": "good", "jitter_ms": 0,
                                                           "stale": 0}, "drops": {}, "qtable": unsaved}, {})
    assert "qtable UNSAVED" in line and "Read-only file system" in line
