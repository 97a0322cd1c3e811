"""SIGTERM to a recording daemon finishes the MCAP file: summary and footer are written."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from respecd.record.reader import open_log

pytestmark = pytest.mark.e2e  # the console script in an interpreter of its own

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_sigterm_finishes_the_log(tmp_path: Path) -> None:
    log = tmp_path / "term.mcap"
    argv = [sys.executable, "-m", "respecd.cli", "--config", str(_small_profile(tmp_path)), "--record", str(log),
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


def test_a_terminal_hangup_stops_like_sigterm(tmp_path: Path) -> None:
    """`respecd --record ...` in an ssh session that drops: the kernel hangs up the terminal (SIGHUP to
    the session, then EIO on every write to it). The log is finished and the Q-table saved all the same."""
    import os
    import pty
    import threading

    log, state = tmp_path / "hup.mcap", tmp_path / "state"
    argv = [sys.executable, "-m", "respecd.cli", "--config", str(_small_profile(tmp_path)), "--record", str(log),
            "--state-dir", str(state), "--log-format", "console"]
    master, slave = pty.openpty()
    terminal = os.ttyname(slave)

    def own_session() -> None:  # the daemon leads a session whose controlling terminal is the pty, as in ssh
        os.setsid()
        os.close(os.open(terminal, os.O_RDWR))
        signal.signal(signal.SIGHUP, signal.SIG_DFL)  # as sshd starts it (a runner under nohup ignores SIGHUP)

    shown = bytearray()

    def drain() -> None:
        try:
            while chunk := os.read(master, 65536):
                shown.extend(chunk)
        except OSError:  # the master was closed: the hangup
            pass

    with subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, preexec_fn=own_session) as proc:
        os.close(slave)
        reader = threading.Thread(target=drain, daemon=True)
        reader.start()
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 200_000):
                assert proc.poll() is None, bytes(shown).decode(errors="replace")[-2000:]
                time.sleep(0.1)
            os.close(master)  # the connection drops
            status = proc.wait(timeout=15)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert status == 0, bytes(shown).decode(errors="replace")[-2000:]
    assert not open_log(log).truncated  # finish() ran: summary and footer written
    assert list(state.glob("*.npz")), "the Q-table was not saved"


def _small_profile(tmp_path: Path) -> Path:
    """The simulated rover with RGB (640x360) and radar only, no detector: a light recording daemon."""
    profile = yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())
    profile["sensors"] = [s for s in profile["sensors"] if s["name"] in ("rgb", "radar")]
    profile["sensors"][0]["resolution"] = [640, 360]
    profile["perception"] = {"enabled": False}
    config = tmp_path / "profile.yaml"
    config.write_text(yaml.safe_dump(profile))
    return config


def test_a_reader_that_leaves_the_pipe_does_not_stop_the_daemon(tmp_path: Path) -> None:
    """`respecd --record ... | head`: once the reader is gone every line written fails (EPIPE); the daemon
    records on and a SIGTERM still finishes the log."""
    log = tmp_path / "pipe.mcap"
    argv = [sys.executable, "-m", "respecd.cli", "--config", str(_small_profile(tmp_path)), "--record", str(log),
            "--state-dir", str(tmp_path / "state"), "--log-format", "json"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL) as proc:
        try:
            assert proc.stdout is not None
            proc.stdout.readline()
            proc.stdout.close()  # the reader leaves
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 400_000):
                assert proc.poll() is None, "the daemon died when its stdout went away"
                time.sleep(0.1)
            proc.send_signal(signal.SIGTERM)
            status = proc.wait(timeout=15)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert status == 0
    assert not open_log(log).truncated


def _daemon(tmp_path: Path, ignore: tuple[int, ...] = ()) -> subprocess.Popen[str]:
    """The console script with the usual signal dispositions (a terminal, systemd), less ``ignore``."""

    def dispositions() -> None:
        for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN if sig in ignore else signal.SIG_DFL)

    return subprocess.Popen([sys.executable, "-m", "respecd.cli", "--duration", "30", "--state-dir",
                             str(tmp_path / "st"), "--log-format", "json"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=dispositions)  # noqa: PLW1509


def test_a_sigint_while_the_command_line_is_built_stops_cleanly(tmp_path: Path) -> None:
    """`respecd bench attacks` found it: a SIGINT in the first second (while the command line's modules are
    imported) was a KeyboardInterrupt traceback."""
    daemon = _daemon(tmp_path)
    time.sleep(0.3)
    daemon.send_signal(signal.SIGINT)
    out, err = daemon.communicate(timeout=60)
    assert daemon.returncode == 0 and "Traceback" not in err, err[-2000:]


def test_a_signal_started_ignored_stays_ignored(tmp_path: Path) -> None:
    """`nohup respecd ...`: SIGHUP ignored at start was taken as a stop request once the handlers were in,
    a second later, so the daemon still stopped when the session that started it logged out."""
    daemon = _daemon(tmp_path, ignore=(signal.SIGHUP,))
    for delay in (0.3, 4.0):
        time.sleep(delay)
        daemon.send_signal(signal.SIGHUP)
    time.sleep(1.0)
    assert daemon.poll() is None, "SIGHUP stopped a daemon started with it ignored"
    daemon.send_signal(signal.SIGTERM)
    out, err = daemon.communicate(timeout=60)
    assert daemon.returncode == 0 and "Traceback" not in err, err[-2000:]
