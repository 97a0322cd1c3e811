"""systemd's sd_notify protocol, spoken directly (one datagram per message, no libsystemd).

READY=1 once the pipeline is up, STATUS= with the status line, WATCHDOG=1 only while frames
flow, STOPPING=1 on shutdown. Outside systemd ($NOTIFY_SOCKET unset) every call is a no-op.
"""

from __future__ import annotations

import os
import socket

import structlog

log = structlog.get_logger(__name__)


class Notifier:
    def __init__(self, address: str | None = None) -> None:
        address = address if address is not None else os.environ.get("NOTIFY_SOCKET")
        self._address: str | None = None
        self._socket: socket.socket | None = None
        if address:
            # '@' marks an abstract socket (leading NUL byte on Linux)
            self._address = "\0" + address[1:] if address.startswith("@") else address
            self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._socket is not None

    @staticmethod
    def watchdog_interval_s() -> float | None:
        """Half of systemd's WatchdogSec (from $WATCHDOG_USEC), the recommended feeding period."""
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        if not usec or (pid and pid != str(os.getpid())):
            return None
        return int(usec) / 2e6

    def notify(self, **fields: str | int) -> None:
        if self._socket is None or self._address is None:
            return
        message = "\n".join(f"{key.upper()}={value}" for key, value in fields.items())
        try:
            self._socket.sendto(message.encode(), self._address)
        except OSError as err:  # systemd went away: keep running, say it once per failure
            log.warning("sd_notify_failed", error=str(err))

    def ready(self, status: str = "") -> None:
        self.notify(ready=1, status=status) if status else self.notify(ready=1)

    def status(self, line: str) -> None:
        self.notify(status=line.replace("\n", " "))

    def watchdog(self) -> None:
        self.notify(watchdog=1)

    def stopping(self) -> None:
        self.notify(stopping=1)

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None
