"""The IWR6843 driver through real pyserial on pseudo-terminals playing the radar (``fake_radar``)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import pytest
from fake_radar import REAL, FakeRadar, capture_frames, radar_config
from pydantic import ValidationError

from respecd.clock import MonotonicClock
from respecd.drivers.iwr6843 import IWR6843Config, IWR6843Driver
from respecd.errors import DriverIOError, DriverTimeoutError, DriverUnavailableError
from respecd.messages import SensorConfig
from respecd.radar import cfg
from respecd.radar.chirp import lookup
from respecd.radar.cli_port import CliPort
from respecd.radar.tlv import MAGIC


def _row_lines(mode: str, rate: int, command: str) -> list[str]:
    """The lines of ``command`` in the ISK cfg the driver sends for a table row."""
    return [line for line in cfg.render(lookup(mode, rate)) if line.split()[0] == command]  # type: ignore[arg-type]


def _config(fake: FakeRadar, **overrides: object) -> IWR6843Config:
    quick = {"cli_timeout_s": 0.5, "reconnect_initial_s": 0.05, "reconnect_max_s": 0.2}
    return radar_config(fake, **(quick | overrides))


async def _take(driver: IWR6843Driver, count: int, timeout: float = 5.0) -> list:
    frames = []
    stream = driver.frames()
    async with asyncio.timeout(timeout):
        async for frame in stream:
            frames.append(frame)
            if len(frames) == count:
                break
    await stream.aclose()
    return frames


async def test_start_streams_real_frames_and_stop_is_clean(radar: FakeRadar) -> None:
    driver = IWR6843Driver(_config(radar), MonotonicClock())
    await driver.start()
    try:
        assert radar.commands[0] == "sensorStop" and radar.commands[1] == "flushCfg"
        assert radar.commands[-1] == "sensorStart" and _row_lines("range", 10, "frameCfg")[0] in radar.commands
        assert "bpmCfg -1 0 0 1" in radar.commands  # the ISK's HWA+DSP demo refuses sensorStart without it
        assert not driver.health.paused and driver.applied.mode == "range" and driver.applied.rate_hz == 10
        frames = await _take(driver, 6)
    finally:
        await driver.stop()
    numbers = [f.meta["frame_number"] for f in frames]
    assert numbers == list(range(numbers[0], numbers[0] + 6))
    for frame in frames:
        assert frame.modality == "radar" and frame.data.dtype == np.float32 and frame.data.shape[1] == 5
        assert frame.meta["raw"].startswith(MAGIC) and frame.meta["mode"] == "range"
    assert radar.commands[-1] == "sensorStop" and not radar.streaming.is_set()
    await driver.stop()  # idempotent
    async with asyncio.timeout(2):  # frames() drains what arrived before stop, then ends
        rest = [frame async for frame in driver.frames()]
    assert len(rest) <= driver.config.frame_queue and all(f.meta["mode"] == "range" for f in rest)


async def test_reconfigure_switches_chirp_and_reports_the_time(radar: FakeRadar) -> None:
    driver = IWR6843Driver(_config(radar), MonotonicClock())
    await driver.start()
    try:
        await _take(driver, 2)
        sent = len(radar.commands)
        applied = await driver.apply(SensorConfig(modality="radar", rate_hz=20, mode="velocity"))
        switch = radar.commands[sent:]
        assert switch[:2] == ["sensorStop", "flushCfg"] and switch[-1] == "sensorStart"
        assert _row_lines("velocity", 20, "profileCfg")[0] in switch
        assert _row_lines("velocity", 20, "frameCfg")[0] in switch
        assert applied.mode == "velocity" and applied.rate_hz == 20
        assert any("reconfigured in" in note for note in applied.notes) and len(driver.switch_times_s) == 2
        frames = await _take(driver, driver.config.frame_queue + 3)  # frames queued before the switch come first
        assert all(f.meta["mode"] == "velocity" for f in frames[-3:]) and not driver.health.paused
        assert frames[-1].meta["frame_number"] > frames[-2].meta["frame_number"]
        sent = len(radar.commands)
        same = await driver.apply(SensorConfig(modality="radar", rate_hz=20.2, mode="velocity"))
        assert len(radar.commands) == sent and same.rate_hz == 20  # same table row: nothing sent
        capped = await driver.apply(SensorConfig(modality="radar", rate_hz=45, mode="range"))
        assert capped.rate_hz == 30 and any("capped" in note for note in capped.notes)
    finally:
        await driver.stop()


async def test_disable_stops_the_sensor_and_enable_restarts_it(radar: FakeRadar) -> None:
    driver = IWR6843Driver(_config(radar), MonotonicClock())
    await driver.start()
    try:
        off = await driver.apply(SensorConfig(modality="radar", enabled=False, mode="range", rate_hz=10))
        assert not off.enabled and radar.commands[-1] == "sensorStop" and driver.health.paused
        await driver.apply(SensorConfig(modality="radar", mode="range", rate_hz=10))
        assert radar.commands[-1] == "sensorStart" and len(await _take(driver, 2)) == 2
    finally:
        await driver.stop()


async def test_absent_ports_are_unavailable_not_fatal(tmp_path: Path) -> None:
    config = IWR6843Config(name="radar", cli_port=str(tmp_path / "nope-cli"), data_port=str(tmp_path / "nope-data"))
    driver = IWR6843Driver(config, MonotonicClock())
    with pytest.raises(DriverUnavailableError, match="absent"):
        await driver.start()
    await driver.stop()


async def test_rejected_command_names_it(tmp_path: Path) -> None:
    fake = FakeRadar(tmp_path, capture_frames(), reject=("frameCfg",))
    try:
        driver = IWR6843Driver(_config(fake), MonotonicClock())
        with pytest.raises(DriverIOError, match="frameCfg"):
            await driver.start()
        await driver.stop()
    finally:
        fake.unplug()


async def test_unplug_reconnects_with_backoff_and_reconfigures(tmp_path: Path) -> None:
    frames = capture_frames()
    fake = FakeRadar(tmp_path, frames)
    driver = IWR6843Driver(_config(fake), MonotonicClock())
    await driver.start()
    try:
        await _take(driver, 2)
        fake.unplug()
        async with asyncio.timeout(5):
            while not driver.health.errors or driver.health.errors < 2:  # read error, then absent ports
                await asyncio.sleep(0.02)
        offline = await driver.apply(SensorConfig(modality="radar", rate_hz=20, mode="velocity"))
        assert any("disconnected" in note for note in offline.notes) and driver.health.paused
        fake = FakeRadar(tmp_path, frames)
        async with asyncio.timeout(5):
            while driver.health.restarts < 1:
                await asyncio.sleep(0.02)
        assert fake.commands[-1] == "sensorStart" and _row_lines("velocity", 20, "frameCfg")[0] in fake.commands
        assert driver.applied.mode == "velocity" and len(await _take(driver, 3)) == 3
    finally:
        await driver.stop()
        fake.unplug()


async def test_stop_during_an_outage_returns_promptly(tmp_path: Path) -> None:
    fake = FakeRadar(tmp_path, capture_frames())
    driver = IWR6843Driver(_config(fake, reconnect_initial_s=5.0), MonotonicClock())
    await driver.start()
    await _take(driver, 1)
    fake.unplug()
    async with asyncio.timeout(5):
        while driver.health.errors < 2:  # read error, then the first reconnect found no ports
            await asyncio.sleep(0.02)
    started = time.monotonic()
    await driver.stop()  # the 5-s backoff sleep must not delay it
    assert time.monotonic() - started < 2.0 and driver.health.paused


async def test_silent_stream_is_detected_and_restarted(radar: FakeRadar) -> None:
    driver = IWR6843Driver(_config(radar, stall_timeout_s=0.2), MonotonicClock())
    await driver.start()
    try:
        await _take(driver, 2)
        radar.mute.set()
        async with asyncio.timeout(5):
            while driver.health.restarts < 1:
                await asyncio.sleep(0.02)
        assert driver.health.last_error.startswith("no radar packets")
        assert len(await _take(driver, 2)) == 2
    finally:
        await driver.stop()


async def test_people_counting_firmware_is_reported_not_streamed(tmp_path: Path) -> None:
    path = REAL / "ti_iwr6843aop_pplcount_niek" / "data.bin"
    if not path.exists():
        pytest.skip(f"shared capture {path} absent")
    data = path.read_bytes()[:200_000]
    starts = [i for i in range(len(data) - 8) if data.startswith(MAGIC, i)]
    packets = [data[a:b] for a, b in zip(starts, starts[1:], strict=False)]
    fake = FakeRadar(tmp_path, packets, renumber=False)
    driver = IWR6843Driver(_config(fake), MonotonicClock())
    try:
        await driver.start()
        async with asyncio.timeout(5):
            while driver.foreign_packets < 5:
                await asyncio.sleep(0.02)
        assert driver.health.frames == 0 and driver.parser.stats.foreign_packets >= 5
    finally:
        await driver.stop()
        fake.unplug()


def test_cli_port_retries_a_garbled_first_command_and_times_out(tmp_path: Path) -> None:
    import serial

    fake = FakeRadar(tmp_path, [], garbage_first=True)
    port = serial.Serial(str(fake.cli_path), 115200)
    try:
        cli = CliPort(port, timeout_s=0.5, retries=1)
        reply = cli.command("sensorStop")  # no wake(): the boot garbage lands on this line
        assert reply.verdict == "done" and reply.attempts == 2
        assert "Ignored: Sensor is already stopped" in reply.lines
        with pytest.raises(DriverIOError, match="Error -1"):
            fake.reject = ("bogusCmd",)
            cli.command("bogusCmd 1 2")
        fake.silent = True
        quick = CliPort(port, timeout_s=0.1, retries=0)
        with pytest.raises(DriverTimeoutError):
            quick.command("sensorStop")
    finally:
        port.close()
        fake.unplug()


def test_config_checks_antennas_and_defaults() -> None:
    config = IWR6843Config(name="radar")
    assert config.cli_baud == 115200 and config.data_baud == 921600 and config.modality == "radar"
    with pytest.raises(ValidationError, match="num_tx 2"):
        IWR6843Config(name="radar", board="aop", num_tx=2)
    with pytest.raises(ValidationError):
        IWR6843Config(name="radar", data_baud=9600)
    driver = IWR6843Driver(config, MonotonicClock())
    caps = driver.capabilities
    assert caps.modes == ("range", "velocity") and caps.min_rate_hz == 1 and caps.max_rate_hz == 30


def test_profile_yaml_entry_loads_and_errors_name_the_line(tmp_path: Path) -> None:
    from respecd.config import load_profile
    from respecd.errors import ConfigError

    good = tmp_path / "radar.yaml"
    good.write_text("name: r\nsensors:\n  - driver: iwr6843\n    name: radar\n    mode: velocity\n    rate_hz: 15\n")
    entry = load_profile(good).sensors[0]
    assert isinstance(entry, IWR6843Config) and entry.mode == "velocity" and entry.data_baud == 921600
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: r\nsensors:\n  - driver: iwr6843\n    name: radar\n    board: aop\n    data_baud: 9600\n")
    with pytest.raises(ConfigError) as err:
        load_profile(bad)
    assert any(line.startswith(f"{bad}:6: sensors.0.data_baud") for line in err.value.problems)
