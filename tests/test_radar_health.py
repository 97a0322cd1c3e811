"""Radar health and recovery on the pseudo-terminal demo: stalls whatever the controller does,
failed or unanswered reconfigurations, a misbehaving but present board, the CLI's own output."""

from __future__ import annotations

import asyncio
import itertools
import time
from pathlib import Path

import pytest
import serial
import structlog
from fake_radar import CAPTURE, FakeRadar, capture_frames, radar_config, split_packets
from structlog.testing import capture_logs

from respecd.clock import MonotonicClock
from respecd.drivers.iwr6843 import IWR6843Config, IWR6843Driver
from respecd.errors import DriverIOError, DriverTimeoutError
from respecd.messages import SensorConfig
from respecd.radar import cfg
from respecd.radar.chirp import lookup
from respecd.radar.cli_port import CliPort
from respecd.radar.parser import MmwParser
from respecd.supervisor import Backoff, driver_runner, supervise

RANGE_10 = SensorConfig(modality="radar", mode="range", rate_hz=10)
VELOCITY_20 = SensorConfig(modality="radar", mode="velocity", rate_hz=20)



def _config(fake: FakeRadar, **overrides: object) -> IWR6843Config:
    quick = {"cli_timeout_s": 0.5, "reconnect_initial_s": 0.05, "reconnect_max_s": 0.4, "stall_timeout_s": 0.3}
    return radar_config(fake, **(quick | overrides))


async def _until(condition, timeout: float = 15.0) -> None:
    async with asyncio.timeout(timeout):
        while not condition():
            await asyncio.sleep(0.02)


def _events(logs: list[dict], name: str) -> list[dict]:
    return [entry for entry in logs if entry["event"] == name]


def test_fixture_cuts_the_capture_at_its_packet_boundaries() -> None:
    """Renumbering 768-byte pieces wrote frame numbers into TLV payloads (only 18 of 101 packets are 768 B)."""
    data = CAPTURE.read_bytes() if CAPTURE.exists() else pytest.skip(f"{CAPTURE} absent")
    packets = split_packets(data)
    assert len(packets) == 101 and b"".join(packets) == data
    assert sum(len(p) == 768 for p in packets) == 18
    stream = bytearray()
    for number, packet in enumerate(packets * 3, start=1):  # what the fake sends: numbered from 1, looped
        frame = bytearray(packet)
        frame[20:24] = number.to_bytes(4, "little")
        stream += frame
    parser = MmwParser()
    assert len(parser.feed(bytes(stream))) == 303
    assert parser.stats.gaps == 0 and parser.stats.bad_packets == 0 and parser.stats.bytes_skipped == 0


async def test_a_stall_is_a_stall_however_often_the_controller_switches(radar: FakeRadar) -> None:
    with capture_logs() as logs:
        driver = IWR6843Driver(_config(radar), MonotonicClock())
        await driver.start()
        try:
            await _until(lambda: driver.parser.stats.packets >= 2)
            radar.data_mode = "silent"  # the CLI still answers every switch
            deadline = time.monotonic() + 10.0  # under load a switch's CLI round trip takes longer
            for request in itertools.cycle((VELOCITY_20, RANGE_10)):
                await driver.apply(request)  # a learning controller switching every ~0.2 s
                await asyncio.sleep(0.2)
                if _events(logs, "radar.lost") or time.monotonic() > deadline:
                    break
        finally:
            await driver.stop()
    lost = _events(logs, "radar.lost")  # limit: 0.3 s + 3 frames; ten switches take ~2.3 s on a quiet machine
    assert lost and lost[0]["cause"] == "stall"


async def test_a_rejected_reconfiguration_falls_back_to_the_last_good_profile(radar: FakeRadar) -> None:
    rejected = cfg.render(lookup("velocity", 20))
    frame_cfg = next(line for line in rejected if line.startswith("frameCfg"))
    radar.reject_line = lambda line: line == frame_cfg
    with capture_logs() as logs:
        driver = IWR6843Driver(_config(radar), MonotonicClock())
        await driver.start()
        try:
            await _until(lambda: driver.parser.stats.packets >= 2)
            with pytest.raises(DriverIOError, match="restoring the last good profile"):
                await driver.apply(VELOCITY_20)
            await _until(lambda: driver.health.restarts == 1 and not driver.outage.active)
            assert radar.commands[-1] == "sensorStart"
            resent = radar.since_last("flushCfg")
            assert next(line for line in resent if line.startswith("frameCfg")) == "frameCfg 0 2 32 0 100 1 0"
            assert driver.applied.mode == "range" and driver.applied.rate_hz == 10
            frames = driver.parser.stats.packets
            await _until(lambda: driver.parser.stats.packets > frames + 2)  # streaming again
            sent = len(radar.commands)
            again = await driver.apply(VELOCITY_20)  # the demo's answer will not change: not re-sent
            assert len(radar.commands) == sent and again.mode == "range"
            assert any("rejected" in note for note in again.notes)
        finally:
            await driver.stop()
    lost = _events(logs, "radar.lost")
    assert len(lost) == 1 and lost[0]["retry_in_s"] == 0.0 and lost[0]["cause"] == "CliRejectedError"
    assert len(_events(logs, "radar.back")) == 1


async def test_a_line_without_done_restarts_the_cfg_without_duplicates(radar: FakeRadar) -> None:
    answered = {"count": 0}

    def once(line: str) -> bool:  # the first chirpCfg of the switch gets no Done (a lost reply)
        if line.startswith("chirpCfg 1 ") and answered["count"] == 0:
            answered["count"] += 1
            return True
        return False

    driver = IWR6843Driver(_config(radar), MonotonicClock())
    await driver.start()
    try:
        radar.no_done = once
        with capture_logs() as logs:
            applied = await driver.apply(VELOCITY_20)
        assert applied.mode == "velocity" and radar.commands[-1] == "sensorStart"
        final = radar.since_last("flushCfg")
        assert sum(line.startswith("profileCfg") for line in final) == 1
        assert sum(line.startswith("chirpCfg") for line in final) == 3
        assert [e["attempt"] for e in _events(logs, "radar.cfg_restart")] == [1]
    finally:
        await driver.stop()


def test_no_done_is_a_timeout_and_crash_output_is_logged(tmp_path: Path) -> None:
    fake = FakeRadar(tmp_path, [], garbage_first=False)
    port = serial.Serial(str(fake.cli_path), 115200)
    try:
        cli = CliPort(port, timeout_s=0.3, retries=1)
        fake.say("Exception: Obj Det DPC Exception\r\nmmwDemo:/>")
        time.sleep(0.1)
        with capture_logs() as logs:
            assert cli.command("sensorStop").verdict == "done"
        output = _events(logs, "radar.cli_output")
        assert output and "Exception: Obj Det DPC Exception" in output[0]["lines"]
        assert output[0]["log_level"] == "warning" and output[0]["before"] == "sensorStop"
        fake.no_done = lambda line: line.startswith("frameCfg")
        with pytest.raises(DriverTimeoutError, match="no Done for 'frameCfg 0 2 32 0 100 1 0'.*heard only"):
            cli.command("frameCfg 0 2 32 0 100 1 0")
        fake.no_done = lambda line: line.startswith("profileCfg")
        with pytest.raises(DriverTimeoutError):
            cli.command("profileCfg 0 60 10 7 28.49 0 0 100 1 256 12499 0 0 30")
        assert sum(c.startswith("profileCfg") for c in fake.commands) == 1  # appending: never re-sent
    finally:
        port.close()
        fake.unplug()


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["silent", "garbage"])
async def test_a_present_but_misbehaving_data_port_is_logged_once_and_backed_off(
    radar: FakeRadar, mode: str
) -> None:
    radar.data_mode = mode
    with capture_logs() as logs:
        quick = _config(radar, stall_timeout_s=0.05, rate_hz=30, reconnect_max_s=0.2, cli_timeout_s=0.3)
        driver = IWR6843Driver(quick, MonotonicClock())
        await driver.start()  # the CLI is fine: the board is there
        try:
            await _until(lambda: radar.commands.count("sensorStart") >= 6)
        finally:
            await driver.stop()
    assert not _events(logs, "radar.back")
    lost = _events(logs, "radar.lost")
    assert len(lost) == 1 and lost[0]["cause"] == "stall"
    retries = [e["retry_in_s"] for e in _events(logs, "radar.retry")]
    assert lost[0]["retry_in_s"] == 0.0 and retries[:4] == [0.05, 0.1, 0.2, 0.2]  # doubling to max, at debug level
    assert not [e for e in logs if e["log_level"] in ("warning", "error") and e["event"] != "radar.lost"]


async def test_a_cli_error_at_start_is_one_line_without_traceback(radar: FakeRadar) -> None:
    radar.reject = ("sensorStart",)
    driver = IWR6843Driver(_config(radar, cli_timeout_s=1.0), MonotonicClock())  # no timeouts on a loaded CI
    with capture_logs() as logs:
        task = asyncio.create_task(supervise("radar", driver_runner(driver, lambda frame: None),
                                             backoff=Backoff(initial_s=0.05, max_s=0.2)))
        await _until(lambda: radar.commands.count("sensorStart") >= 4)
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    failed = _events(logs, "driver_failed")
    assert len(failed) == 1 and "sensorStart" in failed[0]["error"] and "retry_in_s" in failed[0]
    assert not [e for e in logs if "exc_info" in e or e["event"] == "stage_crashed"]
    assert len(_events(logs, "stage_retry")) >= 2


def test_structlog_capture_sees_the_drivers_logger() -> None:
    """The radar loggers are bound per instance; capture_logs must see them (guards the tests above)."""
    with capture_logs() as logs:
        structlog.get_logger("respecd.drivers.iwr6843").bind(sensor="x").warning("radar.lost")
    assert logs and logs[0]["sensor"] == "x"


async def test_an_outage_while_disabled_ends_when_the_board_is_back(tmp_path: Path) -> None:
    """A radar the controller switched off has nothing to stream: reconnected is recovered."""
    frames = capture_frames()
    fake = FakeRadar(tmp_path, frames)
    driver = IWR6843Driver(_config(fake), MonotonicClock())
    await driver.start()
    try:
        await driver.apply(SensorConfig(modality="radar", enabled=False, mode="range", rate_hz=10))
        fake.unplug()
        await _until(lambda: driver.outage.active)
        fake = FakeRadar(tmp_path, frames)
        await _until(lambda: not driver.outage.active)
        assert fake.commands[-1] == "sensorStop" and not fake.streaming.is_set()
        assert driver.health.restarts == 1
    finally:
        await driver.stop()
        fake.unplug()
