"""sd_notify over a real AF_UNIX datagram socket, as systemd listens for it."""

from __future__ import annotations

import socket

import pytest

from respecd.sdnotify import Notifier


@pytest.fixture
def listener(tmp_path):
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(1.0)
    yield path, sock
    sock.close()


def test_messages_reach_the_socket(listener):
    path, sock = listener
    notifier = Notifier(address=path)
    notifier.ready(status="pipeline up")
    notifier.watchdog()
    notifier.status("t=1s | rgb 1280x720\nsecond line")
    notifier.stopping()
    received = [sock.recv(4096).decode() for _ in range(4)]
    notifier.close()
    assert received == [
        "READY=1\nSTATUS=pipeline up",
        "WATCHDOG=1",
        "STATUS=t=1s | rgb 1280x720 second line",
        "STOPPING=1",
    ]


def test_abstract_socket_address():
    name = f"respecd-test-{id(object())}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(1.0)
    try:
        notifier = Notifier(address="@" + name)
        notifier.watchdog()
        assert sock.recv(64) == b"WATCHDOG=1"
        notifier.close()
    finally:
        sock.close()


def test_without_notify_socket_it_is_a_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    notifier = Notifier()
    assert not notifier.enabled
    notifier.ready()  # must not raise


def test_watchdog_interval_is_half_of_watchdog_usec(monkeypatch):
    monkeypatch.setenv("WATCHDOG_USEC", "15000000")
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    assert Notifier.watchdog_interval_s() == 7.5
    monkeypatch.setenv("WATCHDOG_PID", "1")  # meant for another process
    assert Notifier.watchdog_interval_s() is None
