"""The shipped unit must pass ``systemd-analyze verify`` and score an exposure of at most 2.0 in
``systemd-analyze security`` (CI installs systemd for it), while still reaching the devices."""

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
        "SupplementaryGroups=plugdev video",
        "RestartPreventExitStatus=2",
    ):
        assert setting in unit, setting


def _settings(unit: str) -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in unit.splitlines():
        if "=" in line and not line.lstrip().startswith("#"):
            key, _, value = line.partition("=")
            settings.setdefault(key.strip(), []).append(value.strip())
    return settings


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_unit_exposure_is_at_most_2():
    result = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", "--threshold=20", str(SYSTEMD / "respecd.service")],
        capture_output=True, text=True, timeout=60,
    )
    line = next(ln for ln in result.stdout.splitlines() if "Overall exposure level" in ln)
    assert result.returncode == 0 and float(line.split(":")[1].split()[0]) <= 2.0, line


def test_hardening_still_reaches_the_devices():
    """What the drivers and the system probe need must survive the hardening."""
    settings = _settings((SYSTEMD / "respecd.service").read_text())
    allowed = {value.split()[0] for value in settings["DeviceAllow"]}
    assert {"char-ttyUSB", "char-ttyACM", "char-usb_device", "char-video4linux"} <= allowed  # radar, USB, UVC
    assert settings.get("PrivateDevices", ["no"]) == ["no"]  # would hide /dev/ttyUSB*, /dev/bus/usb, /dev/video*
    assert "AF_NETLINK" in settings["RestrictAddressFamilies"][0]  # udev/libusb hot-plug events
    assert settings.get("ProcSubset", ["all"]) == ["all"]  # the load factor reads /proc/stat
    paths = " ".join(settings.get("InaccessiblePaths", []) + settings.get("TemporaryFileSystem", []))
    assert "/sys" not in paths  # Jetson power rails and GPU load are read from sysfs
    assert settings["SystemCallFilter"][0] == "@system-service"  # ioctl on tty, usbfs and v4l2 nodes
    assert all("@resources" not in v for v in settings["SystemCallFilter"])  # torch: sched_setaffinity, mbind
    for key in ("ProtectKernelTunables", "PrivateMounts", "RemoveIPC"):
        assert settings[key] == ["yes"], key
    assert settings["ProtectProc"] == ["invisible"] and settings["SystemCallErrorNumber"] == ["EPERM"]
    assert settings["MemoryMax"] and settings["TasksMax"]


def _expand(group: str, seen: set[str]) -> set[str]:
    out = subprocess.run(["systemd-analyze", "syscall-filter", group], capture_output=True, text=True, timeout=30)
    names: set[str] = set()
    for line in out.stdout.splitlines()[1:]:
        item = line.strip()
        if item.startswith("@") and item not in seen:
            seen.add(item)
            names |= _expand(item, seen)
        elif item and not item.startswith("#"):
            names.add(item)
    return names


@pytest.mark.skipif(shutil.which("systemd-analyze") is None or shutil.which("strace") is None,
                    reason="needs systemd-analyze and strace")
@pytest.mark.e2e
def test_every_syscall_the_daemon_makes_passes_the_filter(tmp_path):
    """The simulated rover with recording, traced: no call the unit's SystemCallFilter refuses."""
    settings = _settings((SYSTEMD / "respecd.service").read_text())
    allowed: set[str] = set()
    for value in settings["SystemCallFilter"]:
        groups = value.lstrip("~").split()
        names = set().union(*(_expand(g, set()) if g.startswith("@") else {g} for g in groups))
        allowed = allowed - names if value.startswith("~") else allowed | names
    trace = tmp_path / "trace.txt"
    respecd = Path(sys.executable).with_name("respecd")
    subprocess.run(["strace", "-f", "-c", "-o", str(trace), str(respecd), "--duration", "4", "--record",
                    str(tmp_path / "r.mcap"), "--state-dir", str(tmp_path / "st"), "--log-format", "json"],
                   capture_output=True, timeout=180, check=True)
    used = {line.split()[-1] for line in trace.read_text().splitlines()[2:] if line.split() and
            line.split()[0][0].isdigit() and line.split()[-1] != "total"}
    assert len(used) > 30 and not used - allowed, sorted(used - allowed)


def test_the_descriptor_limit_holds_the_live_views_largest_cap():
    from respecd.record.live import FDS_PER_CLIENT, FDS_SPARE
    from respecd.record.live_config import MAX_CLIENTS

    limit = int(_settings((SYSTEMD / "respecd.service").read_text())["LimitNOFILE"][-1])
    assert limit >= MAX_CLIENTS * FDS_PER_CLIENT + FDS_SPARE


def test_serial_access_is_the_radars_ports_only_and_recordings_age_by_the_profile():
    """The udev rules plus dialout opened every serial port on the robot to the service; the tmpfiles
    age rule (30d) deleted recordings whatever the profile's retention said."""
    unit = _settings((SYSTEMD / "respecd.service").read_text())
    assert "dialout" not in unit["SupplementaryGroups"][-1].split()
    assert "dialout" not in (SYSTEMD / "respecd.sysusers").read_text().split()
    rules = [line for line in (SYSTEMD / "99-respecd.rules").read_text().splitlines()
             if line.startswith("SUBSYSTEM==\"tty\"")]
    assert rules and all('GROUP="respecd"' in line and "SYMLINK+=\"respecd-radar-" in line for line in rules)
    entries = [line.split() for line in (SYSTEMD / "respecd.tmpfiles").read_text().splitlines()
               if line and not line.startswith("#")]
    assert entries and all(len(entry) < 6 or entry[5] == "-" for entry in entries)
