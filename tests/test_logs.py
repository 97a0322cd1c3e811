"""Log lines: syslog priorities when stdout is the journal, a refreshed status line on a
terminal with log lines above it, chatty per-step lines only with -v, OpenCV's own
warnings and other libraries' logging as our events."""

from __future__ import annotations

import io
import json
import os
import socket
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from respecd.terminal import CLEAR_LINE, UP_CLEAR, Terminal

SCRIPT = """
import logging, os, sys, warnings
import structlog
from respecd.logs import configure_logging
configure_logging("json", "info", journal_socket=os.environ.get("TEST_JOURNAL_SOCKET"))
log = structlog.get_logger("t")
log.debug("hidden"); log.info("started"); log.bind(sensor="rgb").warning("slow", note="a\\nb"); log.error("broken")
logging.getLogger("foxglove.websocket").warning("client dropped")
warnings.warn("old API", DeprecationWarning)
"""


def _run(script: str, out: Path, env: dict[str, str]) -> list[str]:
    with open(out, "w") as stdout:
        st = os.fstat(stdout.fileno())
        env = {**os.environ, **{k: v.format(dev=st.st_dev, ino=st.st_ino) for k, v in env.items()}}
        subprocess.run([sys.executable, "-c", script], stdout=stdout, env=env, check=True, timeout=60)
    return out.read_text().splitlines()


@pytest.mark.e2e
def test_under_systemd_every_line_starts_with_its_syslog_priority(tmp_path: Path) -> None:
    lines = _run(SCRIPT, tmp_path / "out", {"JOURNAL_STREAM": "{dev}:{ino}"})
    assert [line[:3] for line in lines] == ["<6>", "<4>", "<3>", "<4>", "<4>"]
    events = [json.loads(line[3:]) for line in lines]
    assert [e["event"] for e in events] == ["started", "slow", "broken", "foxglove.websocket", "warning"]
    assert events[3]["message"] == "client dropped" and "old API" in events[4]["message"]


@pytest.mark.e2e
def test_under_systemd_events_are_journal_entries_with_their_fields(tmp_path: Path) -> None:
    """The journal's native protocol: ``journalctl SENSOR=rgb`` finds the sensor's lines."""
    path = tmp_path / "journal.socket"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as journald:
        journald.bind(str(path))
        lines = _run(SCRIPT, tmp_path / "out", {"JOURNAL_STREAM": "{dev}:{ino}", "TEST_JOURNAL_SOCKET": str(path)})
        journald.settimeout(5)
        entries = [_fields(journald.recv(65536)) for _ in range(5)]
    assert lines == []  # nothing on stdout: every event went to the journal
    assert [e["PRIORITY"] for e in entries] == ["6", "4", "3", "4", "4"]
    slow = entries[1]
    assert slow["SENSOR"] == "rgb" and slow["EVENT"] == "slow" and slow["SYSLOG_IDENTIFIER"] == "respecd"
    assert slow["NOTE"] == "a\nb"  # a value with a newline, in the length-prefixed form
    assert json.loads(slow["MESSAGE"])["sensor"] == "rgb"  # the JSON line, as journalctl -o cat shows it


@pytest.mark.e2e
def test_a_journal_socket_that_refuses_gives_the_prefixed_line(tmp_path: Path) -> None:
    lines = _run(SCRIPT, tmp_path / "out", {"JOURNAL_STREAM": "{dev}:{ino}",
                                              "TEST_JOURNAL_SOCKET": str(tmp_path)})  # exists, not a socket
    assert [line[:3] for line in lines] == ["<6>", "<4>", "<3>", "<4>", "<4>"]


def _fields(datagram: bytes) -> dict[str, str]:
    """Parse one native-protocol entry (KEY=value lines; KEY, 64-bit length, binary value)."""
    fields, i = {}, 0
    while i < len(datagram):
        end = datagram.index(b"\n", i)
        line = datagram[i:end]
        if b"=" in line:
            key, _, value = line.partition(b"=")
            i = end + 1
        else:
            key, size = line, struct.unpack("<Q", datagram[end + 1:end + 9])[0]
            value = datagram[end + 9:end + 9 + size]
            assert datagram[end + 9 + size:end + 10 + size] == b"\n"
            i = end + 10 + size
        fields[key.decode()] = value.decode()
    return fields


@pytest.mark.e2e
def test_without_the_journal_the_json_stream_is_unchanged(tmp_path: Path) -> None:
    lines = _run(SCRIPT, tmp_path / "out", {"JOURNAL_STREAM": "1:2"})  # another stream: not ours
    assert all(line.startswith("{") for line in lines)


@pytest.mark.e2e
def test_opencv_warnings_become_events(tmp_path: Path) -> None:
    script = """
import cv2, structlog
from respecd.logs import configure_logging
from respecd.native import StderrRelay
configure_logging("json", "info")
relay = StderrRelay(); relay.start()
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_WARNING)
cv2.VideoCapture(99)
import sys; print("plain text on stderr", file=sys.stderr, flush=True)
relay.stop()
"""
    out = tmp_path / "out"
    with open(out, "w") as stdout:
        done = subprocess.run([sys.executable, "-c", script], stdout=stdout, stderr=subprocess.PIPE, text=True,
                              timeout=60)
    events = [json.loads(line) for line in out.read_text().splitlines()]
    opencv = [e for e in events if e["event"] == "opencv"]
    assert opencv and opencv[0]["level"] == "warning" and "open" in opencv[0]["message"]
    assert "[ WARN" not in done.stderr and "plain text on stderr" in done.stderr


def test_status_panel_is_redrawn_and_log_lines_go_above_it() -> None:
    stream = io.StringIO()
    terminal = Terminal(stream)
    terminal.status("t=1s | rgb 30Hz | sync 30Hz good | drops bundles=0 | det=1 conf=0.80 | action a r=+0.1")
    terminal.log_line("warning: radar reconnecting")
    terminal.status("t=2s | rgb 30Hz")
    terminal.close()
    panel = "t=1s | rgb 30Hz\nsync 30Hz good | drops bundles=0\ndet=1 conf=0.80 | action a r=+0.1"
    erase = CLEAR_LINE + UP_CLEAR * 2 + "\r"  # three panel lines: clear them, back to the first
    assert stream.getvalue() == (f"{panel}{erase}warning: radar reconnecting\n{panel}{erase}t=2s | rgb 30Hz\n")


@pytest.mark.e2e
def test_per_decision_lines_are_for_machines_or_verbose(tmp_path: Path) -> None:
    script = """
import structlog, sys
from respecd.logs import configure_logging
configure_logging("console", "info", verbose=len(sys.argv) > 1)
structlog.get_logger().info("decision", action=3); structlog.get_logger().info("pipeline_up")
"""
    quiet = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60).stdout
    loud = subprocess.run([sys.executable, "-c", script, "-v"], capture_output=True, text=True, timeout=60).stdout
    assert "pipeline_up" in quiet and "decision" not in quiet
    assert "decision" in loud
    machine = subprocess.run([sys.executable, "-c", script.replace('"console"', '"json"')], capture_output=True,
                             text=True, timeout=60).stdout
    assert '"event": "decision"' in machine  # the JSON stream keeps them
