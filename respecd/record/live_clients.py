"""What the live view logs about its clients: connections it turns away once per reason, then
a count (``Refusals``), and how it names them.
"""

from __future__ import annotations

import time
from typing import Any

import structlog

log = structlog.get_logger("respecd.record.live")

SUMMARY_S = 60.0  # refusals after the first of a reason: one summary line at most this often


def peer_name(address: Any) -> str:
    """``host:port`` of a socket address (IPv6 in brackets)."""
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
