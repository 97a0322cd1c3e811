"""The journal's native protocol: each log event as one entry with its fields, so that
``journalctl -u respecd SENSOR=rgb`` finds a sensor's lines and ``-p warning`` filters by
priority, without libsystemd (https://systemd.io/JOURNAL_NATIVE_PROTOCOL/).

One datagram per entry to ``/run/systemd/journal/socket``: ``KEY=value`` lines, a value with
a newline in the length-prefixed form. ``MESSAGE`` is the JSON line respecd prints anyway, so
``journalctl -o cat`` reads as before; every top-level field of the event is also a field of
its own (``SENSOR``, ``EVENT``, ``PATH`` ...). An entry the socket refuses (journald
restarting, larger than a datagram) goes to stdout as the plain ``<N>``-prefixed line.
"""

from __future__ import annotations

import json
import os
import re
import socket
import struct
from typing import Any

JOURNAL_SOCKET = "/run/systemd/journal/socket"
IDENTIFIER = "respecd"
_NOT_NAME = re.compile(r"[^A-Z0-9_]")
_RESERVED = {"MESSAGE", "PRIORITY", "SYSLOG_IDENTIFIER"}


def field_name(key: str) -> str | None:
    """A journal field name for an event key: upper case, [A-Z0-9_], not starting with '_' or
    a digit, at most 64 characters (None: nothing of the key is left)."""
    name = _NOT_NAME.sub("_", key.upper()).lstrip("_0123456789")[:64]
    return name or None


def _value(value: Any) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, int, float)) or value is None:
        return json.dumps(value)
    return json.dumps(value, default=str, separators=(",", ":"))


def entry(message: str, priority: int, event: dict[str, Any]) -> bytes:
    """One native-protocol datagram."""
    fields = [("MESSAGE", message), ("PRIORITY", str(priority)), ("SYSLOG_IDENTIFIER", IDENTIFIER)]
    for key, value in event.items():
        name = field_name(str(key))
        if name is not None and name not in _RESERVED:
            fields.append((name, _value(value)))
    out = bytearray()
    for name, text in fields:
        data = text.encode("utf-8", "replace")
        if b"\n" in data:  # binary-safe form: NAME\n, 64-bit little-endian length, data, \n
            out += name.encode() + b"\n" + struct.pack("<Q", len(data)) + data + b"\n"
        else:
            out += name.encode() + b"=" + data + b"\n"
    return bytes(out)


def available(path: str = JOURNAL_SOCKET) -> bool:
    return os.path.exists(path)


class JournalSender:
    """Sends entries to journald; ``send`` returns False when the journal did not take one."""

    def __init__(self, path: str = JOURNAL_SOCKET) -> None:
        self.path = path
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._socket.setblocking(False)  # a full journal queue costs the line its fields, never a wait

    def send(self, data: bytes) -> bool:
        try:
            self._socket.sendto(data, self.path)
        except OSError:  # journald gone or restarting, queue full, EMSGSIZE
            return False
        return True

    def close(self) -> None:
        self._socket.close()
