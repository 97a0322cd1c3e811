"""What a new user tries first: ``--version``, ``python -m respecd``."""

from __future__ import annotations

import subprocess
import sys

from respecd import __version__


def _respecd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "respecd", *args], capture_output=True, text=True, timeout=60)


def test_version_prints_the_package_version() -> None:
    done = _respecd("--version")
    assert done.returncode == 0
    assert done.stdout.strip() == f"respecd {__version__}"


def test_python_dash_m_respecd_is_the_cli() -> None:
    done = _respecd("--help")
    assert done.returncode == 0
    assert done.stdout.startswith("usage: respecd")
    assert "check-config" in done.stdout
