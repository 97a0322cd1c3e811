"""The radar under the daemon's supervisor (``supervise`` + ``driver_runner``) on the pseudo-terminal
demo: each frame counted once, an outage that is one warning, damaged data surfaced in health,
start-up retries that honour the profile's reconnect settings."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from fake_radar import FakeRadar, capture_frames, radar_config
from structlog.testing import capture_logs
from test_supervisor import FlakyDriver

from respecd.clock import MonotonicClock
from respecd.drivers import iwr6843
from respecd.drivers.iwr6843 import IWR6843Config, IWR6843Driver
from respecd.messages import Frame, SensorConfig
from respecd.supervisor import Backoff, driver_backoff, driver_runner, supervise


async def _until(condition, timeout: float = 20.0) -> None:
    async with asyncio.timeout(timeout):
        while not condition():
            await asyncio.sleep(0.02)


def _supervised(driver: IWR6843Driver, sink, backoff: Backoff | None = None) -> asyncio.Task[None]:
    return asyncio.create_task(supervise("driver:radar", driver_runner(driver, sink),
                                         backoff=backoff or driver_backoff(driver)))


async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


def _warnings(logs: list[dict]) -> list[str]:
    return [e["event"] for e in logs if e["log_level"] in ("warning", "error", "critical")]


async def test_each_frame_is_counted_once_and_the_rate_is_the_streams(radar: FakeRadar) -> None:
    """The driver counted every frame and the runner counted it again: 94 frames and 20.7 Hz for 47 at 10 Hz."""
    driver = IWR6843Driver(radar_config(radar, cli_timeout_s=1.0), MonotonicClock())
    delivered: list[Frame] = []
    task = _supervised(driver, delivered.append)
    try:
        await _until(lambda: len(delivered) >= 40)
    finally:
        await _cancel(task)
    assert driver.health.frames == len(delivered)
    last = delivered[-30:]  # the meter's window
    stream_hz = (len(last) - 1) / (last[-1].t - last[0].t)
    assert driver.health.meter.rate_hz == pytest.approx(stream_hz, rel=0.05)
    assert driver.health.errors == 0  # a clean stream (and the partial packet a connection joins) is no damage


@pytest.mark.slow
async def test_a_hung_radar_is_one_warning_and_its_return_one_info_line(radar: FakeRadar) -> None:
    """A CLI that stops answering wrote a warning per try (24 in a 40-s outage): now radar.lost, then radar.back."""
    config = radar_config(radar, cli_timeout_s=0.1, cli_retries=1, stall_timeout_s=0.3,
                          reconnect_initial_s=0.05, reconnect_max_s=0.2)
    driver = IWR6843Driver(config, MonotonicClock())
    with capture_logs() as logs:
        task = _supervised(driver, lambda frame: None)
        try:
            await _until(lambda: driver.health.frames >= 3)
            radar.silent = True
            radar.mute.set()
            await _until(lambda: driver.outage.attempts >= 4)  # several reconnects, each CLI try timing out
            radar.silent = False
            await _until(lambda: driver.health.restarts >= 1 and not driver.outage.active)
        finally:
            await _cancel(task)
    assert _warnings(logs) == ["radar.lost"]
    assert [e["event"] for e in logs if e["event"] in ("radar.back", "radar.still_lost")] == ["radar.back"]
    debug = {e["event"] for e in logs if e["log_level"] == "debug"}
    assert {"radar.cli_retry", "radar.cfg_restart", "radar.retry"} <= debug  # still there, at debug


@pytest.mark.slow
async def test_a_silent_cli_at_start_is_one_warning_until_it_answers(radar: FakeRadar) -> None:
    """Silent from the start: 43 warnings in 25 s before (per CLI try and cfg restart); now the supervisor's one."""
    radar.silent = True
    config = radar_config(radar, cli_timeout_s=0.1, cli_retries=1, reconnect_initial_s=0.05, reconnect_max_s=0.1)
    driver = IWR6843Driver(config, MonotonicClock())
    delivered: list[Frame] = []
    with capture_logs() as logs:
        task = _supervised(driver, delivered.append)
        try:
            await _until(lambda: sum(e["event"] in ("unavailable", "driver_failed", "stage_retry") for e in logs) >= 4)
            radar.silent = False
            await _until(lambda: len(delivered) >= 3)
        finally:
            await _cancel(task)
    assert len(_warnings(logs)) == 1 and _warnings(logs)[0] in ("unavailable", "driver_failed")
    assert [e["event"] for e in logs if e["event"] == "driver_started"] == ["driver_started"]


async def test_damaged_packets_are_health_errors_and_logged_once_then_summed(
    radar: FakeRadar, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Cut and garbage packets were dropped silently (health.errors 0; counts only in radar.stopped)."""
    monkeypatch.setattr(iwr6843, "DAMAGE_SUMMARY_S", 0.5)
    noise = bytes(range(3, 200)) * 2  # no magic word in it

    def mangle(index: int, frame: bytes) -> bytes:
        if index % 7 == 3:
            return frame[: len(frame) // 2]  # cut: the next packet's magic word comes inside it
        if index % 7 == 5:
            return frame + noise  # garbage between two good packets
        return frame

    radar.mangle = mangle
    driver = IWR6843Driver(radar_config(radar, cli_timeout_s=1.0), MonotonicClock())
    with capture_logs() as logs:
        task = _supervised(driver, lambda frame: None)
        try:
            await _until(lambda: driver.health.errors >= 12)
            await asyncio.sleep(0.6)  # one summary period more
        finally:
            await _cancel(task)
    stats = driver.parser.stats
    assert stats.bad_packets >= 5 and driver.health.last_error.startswith("damaged radar data")
    assert driver.health.errors <= stats.damaged_runs  # one per damaged stretch, the connection's lead-in excepted
    damaged = [e for e in logs if e["event"] == "radar.damaged_data"]
    levels = [e["log_level"] for e in damaged]
    assert levels[0] == "warning" and levels[1:] == ["info"] * (len(damaged) - 1)
    assert 1 <= len(damaged) - 1 <= 1 + max(e.get("over_s", 0) for e in damaged) * 10  # summaries, not a line each
    assert sum(e["damaged"] for e in damaged) <= driver.health.errors
    assert _warnings(logs) == ["radar.damaged_data"]


def test_driver_backoff_takes_the_profiles_reconnect_settings() -> None:
    radar = IWR6843Driver(IWR6843Config(name="radar", reconnect_initial_s=0.5, reconnect_max_s=10), MonotonicClock())
    assert (driver_backoff(radar).initial_s, driver_backoff(radar).max_s) == (0.5, 10.0)
    assert driver_backoff(FlakyDriver("cam")) == Backoff()  # no such settings: the default (30 s cap)


async def test_a_radar_absent_at_start_retries_at_its_reconnect_max(tmp_path: Path) -> None:
    """Absent at start: 0.5, 1, 2, 4, 8, 16 s (the supervisor's 30-s cap), not reconnect_max_s 10 s."""
    config = IWR6843Config(name="radar", cli_port=str(tmp_path / "cli"), data_port=str(tmp_path / "data"),
                           reconnect_initial_s=0.02, reconnect_max_s=0.08)
    driver = IWR6843Driver(config, MonotonicClock())
    with capture_logs() as logs:
        task = _supervised(driver, lambda frame: None)
        try:
            await _until(lambda: sum(e["event"] in ("unavailable", "stage_retry") for e in logs) >= 6)
        finally:
            await _cancel(task)
    retries = [e["retry_in_s"] for e in logs if e["event"] in ("unavailable", "stage_retry")]
    assert retries[:6] == [0.02, 0.04, 0.08, 0.08, 0.08, 0.08]
    assert _warnings(logs) == ["unavailable"]


async def test_an_unplug_is_one_warning(tmp_path: Path) -> None:
    """An unplug wrote radar.data_read_failed, radar.lost and radar.still_lost within 1 ms."""
    frames = capture_frames()
    fake = FakeRadar(tmp_path, frames)
    driver = IWR6843Driver(radar_config(fake, cli_timeout_s=0.5, reconnect_initial_s=0.05, reconnect_max_s=0.1),
                           MonotonicClock())
    with capture_logs() as logs:
        task = _supervised(driver, lambda frame: None)
        try:
            await _until(lambda: driver.health.frames >= 3)
            fake.unplug()
            await _until(lambda: driver.outage.attempts >= 4)
            fake = FakeRadar(tmp_path, frames)
            await _until(lambda: driver.health.restarts >= 1 and not driver.outage.active)
        finally:
            await _cancel(task)
            fake.unplug()
    assert _warnings(logs) == ["radar.lost"]
    lost = next(e for e in logs if e["event"] == "radar.lost")
    assert lost["cause"] == "SerialException" and "data port read failed" in lost["error"]
    assert [e["event"] for e in logs if e["event"] in ("radar.back", "radar.still_lost")] == ["radar.back"]


async def test_switch_times_are_bounded(radar: FakeRadar, monkeypatch: pytest.MonkeyPatch) -> None:
    """switch_times_s grew by one float per chirp switch for ever (200 switches: 200 entries)."""
    monkeypatch.setattr(iwr6843, "SWITCH_TIMES_KEPT", 5)
    driver = IWR6843Driver(radar_config(radar, cli_timeout_s=1.0), MonotonicClock())
    await driver.start()
    try:
        for i in range(8):
            await driver.apply(SensorConfig(modality="radar", rate_hz=10 + i % 2, mode="range"))
    finally:
        await driver.stop()
    assert len(driver.switch_times_s) == 5 and all(0 < s < 5 for s in driver.switch_times_s)
