"""Both names of the Foxglove WebSocket protocol on one port.

foxglove-sdk's server speaks the protocol under its current subprotocol name,
``foxglove.sdk.v1``, and refuses the handshake of a client that asks for the earlier name,
``foxglove.websocket.v1`` (older Foxglove apps, Lichtblick before it added the new name, the
ws-protocol reference clients). The protocol is the same under both names (Foxglove's own
statement in its bridge migration notes), so this bridge takes the public port, rewrites the
name in the HTTP upgrade handshake, and from then on passes bytes through unchanged to the
SDK's server on a private loopback port.

It runs its own event loop in its own thread: a viewer's traffic never touches the control
loop. A slow viewer stops reading; the SDK then drops that client's oldest messages
(``message_backlog_size``), so the bridge's buffers stay bounded.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import structlog

log = structlog.get_logger(__name__)

CURRENT = b"foxglove.sdk.v1"
EARLIER = b"foxglove.websocket.v1"
MAX_HEADER = 16 * 1024
CHUNK = 256 * 1024


def rewrite_request(head: bytes) -> tuple[bytes, bool]:
    """The upgrade request with ``foxglove.sdk.v1`` offered; True when the client only knew
    the earlier name (its answer must then name that one)."""
    lines = head.split(b"\r\n")
    for i, line in enumerate(lines):
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol":
            offered = [v.strip() for v in value.split(b",")]
            if CURRENT in offered or EARLIER not in offered:
                return head, False
            lines[i] = name + b": " + b", ".join([CURRENT if v == EARLIER else v for v in offered])
            return b"\r\n".join(lines), True
    return head, False


class SubprotocolBridge:
    """``host:port`` (public) -> ``127.0.0.1:upstream_port`` (the SDK's server)."""

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self.host, self.port, self.upstream_port = host, port, upstream_port
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._server: Any = None
        self._tasks: set[asyncio.Task[None]] = set()

    def start(self) -> int:
        """Bind the public port (OSError if it cannot) and serve; the port bound."""
        self._thread = threading.Thread(target=self._run, name="respecd-foxglove-bridge", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise self._error
        return self.port

    def _run(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        try:
            self._server = loop.run_until_complete(
                asyncio.start_server(self._handle, self.host, self.port, limit=MAX_HEADER))
            self.port = int(self._server.sockets[0].getsockname()[1])
        except OSError as err:
            self._error = err
            self._ready.set()
            loop.close()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            self._server.close()
            for task in list(self._tasks):
                task.cancel()
            loop.run_until_complete(asyncio.gather(*self._tasks, return_exceptions=True))
            loop.run_until_complete(self._server.wait_closed())
            loop.run_until_complete(asyncio.sleep(0.01))  # let closed transports release their sockets
            loop.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
        up_writer: asyncio.StreamWriter | None = None
        try:
            head = await reader.readuntil(b"\r\n\r\n")
            head, earlier = rewrite_request(head)
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port, limit=MAX_HEADER)
            up_writer.write(head)
            answer = await up_reader.readuntil(b"\r\n\r\n")
            writer.write(answer.replace(CURRENT, EARLIER) if earlier else answer)
            await asyncio.gather(_pipe(reader, up_writer), _pipe(up_reader, writer))
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass  # a client that went away or spoke no HTTP: nothing to keep
        finally:
            for stream in (writer, up_writer):
                if stream is not None:
                    stream.close()
            if task is not None:
                self._tasks.discard(task)

    def stop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5.0)


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    try:
        while data := await source.read(CHUNK):
            sink.write(data)
            await sink.drain()  # a slow reader holds us here, and the SDK drops for it
    finally:
        sink.close()
