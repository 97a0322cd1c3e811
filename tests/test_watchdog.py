"""The systemd watchdog means "the loop is alive and supervising", not "sensors are present";
STATUS= says what is degraded."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from respecd.clock import ManualClock
from respecd.liveness import Liveness, status_text
from respecd.messages import SensorConfig

REPO = Path(__file__).resolve().parents[1]


def _driver(paused: bool = False, error: str | None = None) -> SimpleNamespace:
    return SimpleNamespace(health=SimpleNamespace(paused=paused, last_error=error))


def _task(done: bool) -> SimpleNamespace:
    return SimpleNamespace(done=lambda: done)


def test_absent_sensors_are_degraded_not_stalled() -> None:
    clock = ManualClock()
    live = Liveness(clock, stall_s=5.0, decision_budget_s=6.0)
    drivers = {"rgb": _driver(), "radar": _driver(error="radar data port /dev/x absent"), "thermal": _driver()}
    applied = {"rgb": SensorConfig("rgb", True, 30.0), "radar": SensorConfig("radar", True, 10.0),
               "thermal": SensorConfig("thermal", False, 9.0)}
    for step in range(1, 21):  # 20 s of ticks, not one frame from anybody
        clock.set(step)
        live.on_tick(step, step)
        live.on_frame("rgb", None) if step > 15 else None
    assert live.stalls({"sync": _task(False), "driver:radar": _task(False)}) == []
    assert live.degraded(drivers, applied) == ["radar no frames since start (20 s): radar data port /dev/x absent"]
    recording = {"state": "paused", "reason": "No space left on device (OSError)"}
    assert live.degraded(drivers, applied, recording)[-1] == "recording paused (No space left on device (OSError))"


def test_a_stuck_stage_or_an_ended_task_withholds_the_watchdog() -> None:
    clock = ManualClock()
    live = Liveness(clock, stall_s=5.0, decision_budget_s=6.0)
    assert live.stalls({}) == []
    clock.set(6.0)
    assert live.stalls({}) == ["synchronizer has not ticked for 6 s"]
    live.on_tick(6.0, 6.0)
    live.on_bundle(SimpleNamespace(frames={"rgb": object()}))  # input for perception...
    clock.set(10.0)
    live.on_tick(10.0, 10.0)
    assert live.stalls({}) == []
    clock.set(12.0)
    live.on_tick(12.0, 12.0)
    assert live.stalls({}) == ["perception has held input without output for 6 s"]  # ... and no output
    live.on_inference(None)
    live.on_percept(None)
    clock.set(20.0)
    live.on_tick(20.0, 20.0)
    assert live.stalls({}) == []  # a decision may take its period plus the drivers' apply timeout
    clock.set(24.0)
    live.on_tick(24.0, 24.0)
    assert live.stalls({}, ("perception",)) == []  # no controller: percepts are nobody's input
    assert live.stalls({}) == ["controller has held input without output for 12 s"]
    live.on_decision(None)
    assert live.stalls({"sync": _task(True)}) == ["task sync ended"]
    assert status_text("t=24s", ["radar paused"], []) == "DEGRADED: radar paused | t=24s"


def _absent_rover(tmp: Path) -> Path:
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["sensors"] = [
        {"name": "rgb", "driver": "uvc", "modality": "rgb", "device": "/dev/respecd-test-absent-video",
         "source": "camera"},
        {"name": "radar", "driver": "iwr6843", "modality": "radar", "cli_port": "/dev/respecd-test-absent-cli",
         "data_port": "/dev/respecd-test-absent-data"},
    ]
    profile["perception"] = {"enabled": False}
    path = tmp / "absent.yaml"
    path.write_text(yaml.safe_dump(profile))
    return path


@pytest.mark.e2e
def test_daemon_with_every_sensor_absent_keeps_feeding_the_watchdog() -> None:
    tmp = Path(tempfile.mkdtemp(prefix="rwd-", dir="/tmp"))  # AF_UNIX paths must be short
    try:
        server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        server.bind(str(tmp / "notify"))
        server.settimeout(0.5)
        env = {**os.environ, "NOTIFY_SOCKET": str(tmp / "notify"), "WATCHDOG_USEC": "3000000"}
        argv = [sys.executable, "-m", "respecd.cli", "--config", str(_absent_rover(tmp)), "--duration", "9",
                "--state-dir", str(tmp / "st"), "--log-format", "json"]
        proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        messages: list[tuple[float, str]] = []
        while proc.poll() is None or len(messages) < 2:
            try:
                messages.append((time.monotonic(), server.recv(65536).decode()))
            except TimeoutError:
                if proc.poll() is not None:
                    break
        out, err = proc.communicate(timeout=30)
        server.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    assert proc.returncode == 0, err[-2000:]
    ready = next(t for t, m in messages if "READY=1" in m)
    stopping = next(t for t, m in messages if "STOPPING=1" in m)
    pings = [ready] + [t for t, m in messages if m == "WATCHDOG=1" and ready < t < stopping] + [stopping]
    assert len(pings) > 6 and max(b - a for a, b in zip(pings, pings[1:], strict=False)) < 2.5  # WatchdogSec=3
    statuses = [m for _, m in messages if m.startswith("STATUS=") and "DEGRADED" in m]
    assert statuses and "rgb no frames" in statuses[-1] and "radar no frames" in statuses[-1]
    assert "watchdog_withheld" not in out
