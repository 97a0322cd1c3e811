"""What a new user tries first: ``--version``, ``--help``, ``python -m respecd``."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import Ran

from respecd import __version__


@pytest.mark.e2e
def test_python_dash_m_respecd_is_the_cli() -> None:
    done = subprocess.run([sys.executable, "-m", "respecd", "--version"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0
    assert done.stdout.strip() == f"respecd {__version__}"


def test_version_and_help(cli: Callable[..., Ran]) -> None:
    assert cli("--version").stdout.strip() == f"respecd {__version__}"
    done = cli("--help")
    assert done.returncode == 0
    assert done.stdout.startswith("usage: respecd")
    assert "check-config" in done.stdout and "experiment" in done.stdout


def test_flags_that_do_not_apply_are_errors(cli: Callable[..., Ran]) -> None:
    for args, message in [(["--report", "r.json", "--duration", "1"], "--report: only with --replay"),
                          (["--speed", "max", "--topics", "rgb=/x"], "--speed, --topics: only with --replay")]:
        done = cli(*args)
        assert done.returncode == 2 and message in done.stderr, done.stderr
        assert "Traceback" not in done.stderr


def test_profile_is_the_flag_and_config_its_old_name(cli: Callable[..., Ran], tmp_path: Path) -> None:
    for flag in ("--profile", "--config"):
        done = cli(flag, "/nonexistent/p.yaml", "--duration", "1", "--state-dir", str(tmp_path))
        assert done.returncode == 2 and "/nonexistent/p.yaml" in done.stderr, done.stderr


def test_schema_install_writes_it_beside_a_copied_profile(tmp_path: Path, cli: Callable[..., Ran]) -> None:
    profile = tmp_path / "respecd.yaml"
    profile.write_text("name: x\n")
    done = cli("schema", "--install", str(profile))
    assert done.returncode == 0 and "add `# yaml-language-server: $schema=profile.schema.json`" in done.stdout
    assert '"title": "respecd profile"' in (tmp_path / "profile.schema.json").read_text()
    path = cli("schema", "--path").stdout.strip()
    assert path.endswith("profile.schema.json") and Path(path).is_file()
