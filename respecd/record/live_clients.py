"""What the live view logs about its clients: once per client or per reason, then a count.

A viewer is anyone who can reach the port, and what a client does must not flood the journal:
foxglove-sdk logs an error line for every malformed message a client sends (100,000 unknown
ops were 2,600-3,600 error lines a second) and one per message it could not deliver to a
viewer that left. ``ClientLog`` takes the SDK's log records about one client (they name it by
its address, which is the bridge's side of the private loopback connection): the first is
logged as ``live.client_error`` with the viewer's real address, the rest are counted and the
count goes into that viewer's ``live.client_left`` line. ``Refusals`` does the same for
connections the bridge turns away.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import deque
from typing import Any

import structlog

log = structlog.get_logger("respecd.record.live")

SDK_LOGGER = "foxglove"  # foxglove-sdk's Rust logs reach Python logging under foxglove.*
ADDRESS = re.compile(r"(?:\d{1,3}(?:\.\d{1,3}){3}|\[[0-9A-Fa-f:.]+\]):\d{1,5}")
SUMMARY_S = 60.0  # refusals after the first of a reason: one summary line at most this often


def peer_name(address: Any) -> str:
    """``host:port`` of a socket address (IPv6 in brackets), as the SDK's log lines write it."""
    if not isinstance(address, tuple) or len(address) < 2:
        return str(address)
    host = str(address[0])
    return f"[{host}]:{address[1]}" if ":" in host else f"{host}:{address[1]}"


def header_value(head: bytes, name: bytes) -> str | None:
    """The value of HTTP header ``name`` (lower case) in a request head, or None."""
    for line in head.split(b"\r\n")[1:]:
        key, sep, value = line.partition(b":")
        if sep and key.strip().lower() == name:
            return value.strip().decode("latin-1")
    return None


class Refusals:
    """Connections turned away: the first of each reason logged, later ones counted and summed up
    at most once per ``SUMMARY_S``, and in ``counts`` for the closing line."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self._unreported: dict[str, int] = {}
        self._reported_at = time.monotonic()

    def note(self, reason: str, **fields: Any) -> None:
        first = reason not in self.counts
        self.counts[reason] = self.counts.get(reason, 0) + 1
        if first:
            log.warning("live.refused", reason=reason, note="further refusals for this reason are counted", **fields)
            return
        self._unreported[reason] = self._unreported.get(reason, 0) + 1
        now = time.monotonic()
        if now - self._reported_at >= SUMMARY_S:
            log.warning("live.refused_since", counts=dict(self._unreported), seconds=round(now - self._reported_at))
            self._unreported.clear()
            self._reported_at = now


class ClientLog(logging.Handler):
    """foxglove-sdk's log records, gated per client while the live view runs (``install``)."""

    def __init__(self) -> None:
        super().__init__()
        self._peers: dict[str, str] = {}  # the SDK's name of a connection -> the viewer's address
        self._counts: dict[str, int] = {}
        self._gone: deque[str] = deque(maxlen=1024)  # left: lines about their last messages are dropped
        self._lock = threading.Lock()
        self._propagate = True

    def install(self) -> None:
        sdk = logging.getLogger(SDK_LOGGER)
        self._propagate, sdk.propagate = sdk.propagate, False
        sdk.addHandler(self)

    def remove(self) -> None:
        sdk = logging.getLogger(SDK_LOGGER)
        sdk.removeHandler(self)
        sdk.propagate = self._propagate

    def arrived(self, key: str, peer: str) -> None:
        with self._lock:
            self._peers[key] = peer
            self._counts[key] = 0
            if key in self._gone:  # the kernel reused the port
                self._gone.remove(key)

    def left(self, key: str) -> int:
        """The viewer behind ``key`` left: how many of the SDK's lines named it."""
        with self._lock:
            self._peers.pop(key, None)
            self._gone.append(key)
            return self._counts.pop(key, 0)

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
            match = ADDRESS.search(message) if record.levelno >= logging.WARNING else None
            if match is None:
                logging.getLogger().handle(record)  # not about one client: as any library's line
                return
            key = match.group(0)
            with self._lock:
                if key in self._gone:
                    return
                count = self._counts[key] = self._counts.get(key, 0) + 1
                peer = self._peers.get(key, key)
            if count == 1:
                log.warning("live.client_error", client=peer, message=ADDRESS.sub(peer, message, count=1),
                            note="further errors of this client are counted in its live.client_left line")
        except Exception:  # noqa: BLE001 - logging must never raise into the SDK's threads
            self.handleError(record)
