"""The shipped unit must pass ``systemd-analyze verify`` (CI installs systemd for it)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

SYSTEMD = Path(__file__).resolve().parents[1] / "systemd"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_unit_verifies(tmp_path):
    # verify checks that ExecStart exists: point it at this venv's console script
    respecd = Path(sys.executable).with_name("respecd")
    unit = (SYSTEMD / "respecd.service").read_text().replace("/opt/respecd/venv/bin/respecd", str(respecd))
    target = tmp_path / "respecd.service"
    target.write_text(unit)
    result = subprocess.run(["systemd-analyze", "verify", str(target)], capture_output=True, text=True, timeout=60)
    problems = [line for line in result.stderr.splitlines() if "respecd.service" in line]
    assert result.returncode == 0 and not problems, result.stderr


def test_unit_has_the_contract_settings():
    unit = (SYSTEMD / "respecd.service").read_text()
    for setting in (
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "StateDirectory=respecd",
        "User=respecd",
        "NoNewPrivileges=yes",
        "ProtectSystem=strict",
        "ProtectHome=yes",
        "PrivateTmp=yes",
        "SupplementaryGroups=dialout plugdev video",
        "RestartPreventExitStatus=2",
    ):
        assert setting in unit, setting
