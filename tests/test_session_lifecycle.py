"""The session's lifecycle as a robot's supervisor sees it: start-up errors exit 2 at once
(with or without a recorder), and a stop signal is honoured within 2 s at any moment,
including while the detector loads."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

pytestmark = pytest.mark.e2e  # the console script in an interpreter of its own

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
RESPECD = [sys.executable, "-m", "respecd.cli"]
STOP_BUDGET_S = 2.0


def profile(tmp_path: Path, **sections: object) -> Path:
    doc = yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())
    doc.update(sections)
    path = tmp_path / "profile.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def run(argv: list[str], timeout: float = 60) -> tuple[int, str, float]:
    start = time.monotonic()
    done = subprocess.run([*RESPECD, *argv], capture_output=True, text=True, timeout=timeout, check=False)
    return done.returncode, done.stderr, time.monotonic() - start


@pytest.mark.parametrize("record", [False, True])
def test_a_missing_checkpoint_exits_2_with_or_without_a_recorder(tmp_path: Path, record: bool) -> None:
    config = profile(tmp_path, perception={"weights": "/nonexistent/x.pt"})
    log = tmp_path / "out.mcap"
    argv = ["--config", str(config), "--duration", "5", "--state-dir", str(tmp_path / "state")]
    rc, err, elapsed = run(argv + (["--record", str(log)] if record else []))
    assert rc == 2, err[-2000:]
    assert "x.pt" in err and "Traceback" not in err
    assert not log.exists()  # the recorder was never started: the detector loads first
    assert elapsed < 10  # the whole process; the start itself is timed below


def test_a_controller_with_nothing_to_control_exits_2_with_a_recorder(tmp_path: Path) -> None:
    config = profile(tmp_path, perception={"enabled": False}, controller={"actions": {"modalities": ["depth"]}},
                     sensors=[s for s in yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())["sensors"]
                              if s["modality"] in ("rgb", "imu")])
    log = tmp_path / "out.mcap"
    rc, err, _ = run(["--config", str(config), "--duration", "5", "--record", str(log),
                      "--state-dir", str(tmp_path / "state")])
    assert rc == 2, err[-2000:]
    assert "no sensor to control" in err and "Traceback" not in err


def _wait_for(proc: subprocess.Popen[str], event: str, limit_s: float = 60) -> None:
    assert proc.stdout is not None
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        if f'"event": "{event}"' in line:
            return
    raise AssertionError(f"never logged {event}")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_while_the_detector_loads_stops_the_daemon_at_once(tmp_path: Path, sig: int) -> None:
    argv = [*RESPECD, "--log-format", "json", "--state-dir", str(tmp_path), "--duration", "30"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"},
                          preexec_fn=lambda: signal.signal(sig, signal.SIG_DFL)) as proc:  # noqa: PLW1509
        # SIG_DFL: as a terminal or systemd starts it; a runner in the background ignores SIGINT, and the
        # daemon keeps a signal it was started with ignored
        try:
            _wait_for(proc, "detector_loading")
            sent = time.monotonic()
            proc.send_signal(sig)
            out, err = proc.communicate(timeout=10)
            elapsed = time.monotonic() - sent
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, err[-2000:]
    assert elapsed <= STOP_BUDGET_S, f"took {elapsed:.2f} s to stop"
    assert "pipeline_up" not in out  # it stopped during the start, not after it
    assert "Traceback" not in err
