"""The radar's data port: a worker thread that reads UART bytes and parses them.

pyserial has no async API; a dedicated thread blocks in ``read`` with a short timeout so it
notices ``stop`` quickly, feeds the incremental parser, and hands complete packets to the
event loop with ``call_soon_threadsafe``. A read error (unplugged board) ends the thread and
is reported once through ``on_error`` (logged at debug: the driver's ``radar.lost`` warning
carries it); the driver decides about reconnecting.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any

import structlog

from respecd.radar.parser import MmwParser, Packet

log = structlog.get_logger(__name__)

READ_MAX = 1024  # bytes per read call: ~11 ms of a saturated 921600-baud port (bounds latency)
INTER_BYTE_TIMEOUT_S = 0.002  # a read returns 2 ms after a burst (a frame) ends, not per byte


class DataPortReader:
    """Owns one reading thread over an open serial port."""

    def __init__(
        self,
        port: Any,
        parser: MmwParser,
        loop: asyncio.AbstractEventLoop,
        on_packets: Callable[[list[Packet]], None],
        on_error: Callable[[BaseException], None],
        name: str = "radar-data",
    ) -> None:
        self.port = port
        self.parser = parser
        self._loop = loop
        self._on_packets = on_packets
        self._on_error = on_error
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.bytes_read = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Ask the thread to end and wait for it (blocking: call via ``asyncio.to_thread``)."""
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        try:
            while not self._stopping.is_set():
                # returns after READ_MAX bytes, a 2-ms pause in the stream, or the port timeout (stop check)
                data = self.port.read(READ_MAX)
                if not data:
                    continue
                self.bytes_read += len(data)
                packets = self.parser.feed(data)
                if packets:
                    self._call(self._on_packets, packets)
        except Exception as err:  # noqa: BLE001 - thread boundary: serial/OS errors end the thread, reported
            if not self._stopping.is_set():
                log.debug("radar.data_read_failed", error=repr(err))  # the driver's radar.lost says it
                self._call(self._on_error, err)

    def _call(self, callback: Callable[[Any], None], arg: Any) -> None:
        try:
            self._loop.call_soon_threadsafe(callback, arg)
        except RuntimeError:  # the loop closed under us during shutdown
            self._stopping.set()
