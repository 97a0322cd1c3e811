"""SIGTERM to a recording daemon finishes the MCAP file: summary and footer are written."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

from respecd.record.reader import open_log

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_sigterm_finishes_the_log(tmp_path: Path) -> None:
    profile = yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())
    profile["sensors"] = [s for s in profile["sensors"] if s["name"] in ("rgb", "radar")]
    profile["sensors"][0]["resolution"] = [640, 360]
    profile["perception"] = {"enabled": False}
    config = tmp_path / "profile.yaml"
    config.write_text(yaml.safe_dump(profile))
    log = tmp_path / "term.mcap"
    argv = [sys.executable, "-m", "respecd.cli", "--config", str(config), "--record", str(log),
            "--state-dir", str(tmp_path / "state"), "--log-format", "json"]
    errors = tmp_path / "stderr.txt"
    with open(errors, "wb") as err, subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=err) as proc:
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 200_000):
                assert proc.poll() is None, errors.read_text()
                time.sleep(0.1)
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(timeout=10) == 0, errors.read_text()
        finally:
            if proc.poll() is None:
                proc.kill()
    session = open_log(log)
    assert not session.truncated  # the summary was written: finish() ran
    assert session.sensors == {"rgb": "rgb", "radar": "radar"}
    assert session.channels["/sensors/rgb"].count > 0
