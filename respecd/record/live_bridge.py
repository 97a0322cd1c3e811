"""The live view's public port: both names of the Foxglove WebSocket protocol, and a guard.

foxglove-sdk's server speaks the protocol under its current subprotocol name,
``foxglove.sdk.v1``, and refuses the handshake of a client that asks for the earlier name,
``foxglove.websocket.v1`` (older Foxglove apps, Lichtblick before it added the new name, the
ws-protocol reference clients). The protocol is the same under both names (Foxglove's own
statement in its bridge migration notes), so this bridge takes the public port, rewrites the
name in the HTTP upgrade handshake, and from then on passes bytes through unchanged to the
SDK's server on a private loopback port.

The port has no authentication, so the bridge guards it (``LiveConfig``): a handshake must
complete within ``handshake_timeout_s``; at most ``max_clients`` connections at once (more are
answered 503); a browser page from an origin not allowed is answered 403; a viewer whose socket
takes nothing for ``stall_s`` is dropped. Each viewer's arrival and departure is one log line;
refusals are logged once per reason, then counted (``live.refused`` at most once a minute).

It runs its own event loop in its own thread: a viewer's traffic never touches the control
loop. A slow viewer reads slowly; the SDK then drops that client's oldest messages
(``backlog``), so the bridge's buffers stay bounded.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

import structlog

from respecd.priority import VIEWER_NICE, lower_thread_priority
from respecd.record.live_clients import Refusals, header_value, peer_name
from respecd.record.live_config import LiveConfig, origin_allowed
from respecd.timeouts import within

log = structlog.get_logger(__name__)

CURRENT = b"foxglove.sdk.v1"
EARLIER = b"foxglove.websocket.v1"
MAX_HEADER = 16 * 1024
CHUNK = 256 * 1024
WRITE_HIGH = 256 * 1024  # bytes a viewer's transport buffers before the bridge stops reading for it
ANSWERS = {503: b"Service Unavailable", 403: b"Forbidden", 408: b"Request Timeout", 400: b"Bad Request"}


class Stalled(Exception):
    """A viewer took nothing from its socket for ``stall_s``."""


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

    def __init__(self, host: str, port: int, upstream_port: int, config: LiveConfig | None = None,
                 clients: Any = None) -> None:
        self.host, self.port, self.upstream_port = host, port, upstream_port
        self.config = config or LiveConfig()
        self.clients = clients  # live_clients.ClientLog: the SDK's log lines per viewer (None: not gated)
        self.refusals = Refusals()
        self.connections = 0  # open now, handshakes in progress included
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
        lower_thread_priority(VIEWER_NICE)  # copying bytes to viewers yields to the loop and the recorder
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
        peer = peer_name(writer.get_extra_info("peername"))
        self.connections += 1
        try:
            if self.connections > self.config.max_clients:
                await self._refuse(writer, 503, "max_clients", peer, max_clients=self.config.max_clients)
                return
            await self._serve(reader, writer, peer)
        except asyncio.CancelledError:
            pass  # the bridge is stopping: this connection's task simply ends
        finally:
            self.connections -= 1
            writer.close()
            if task is not None:
                self._tasks.discard(task)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str) -> None:
        try:
            head = await within(reader.readuntil(b"\r\n\r\n"), self.config.handshake_timeout_s)
        except asyncio.TimeoutError:
            await self._refuse(writer, 408, "handshake_timeout", peer, after_s=self.config.handshake_timeout_s)
            return
        except asyncio.LimitOverrunError:
            await self._refuse(writer, 400, "header_too_long", peer, limit=MAX_HEADER)
            return
        except (OSError, asyncio.IncompleteReadError):
            return  # a client that went away before it said anything: nothing to keep or log
        origin = header_value(head, b"origin")
        if origin is not None and not origin_allowed(origin, self.config.allowed_origins):
            await self._refuse(writer, 403, "origin", peer, origin=origin[:200])
            return
        await self._pass_through(head, reader, writer, peer, origin)

    async def _pass_through(self, head: bytes, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                            peer: str, origin: str | None) -> None:
        head, earlier = rewrite_request(head)
        started, reason, up_writer, key = time.monotonic(), "closed", None, None
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port, limit=MAX_HEADER)
            key = peer_name(up_writer.get_extra_info("sockname"))  # how the SDK's log lines name this viewer
            if self.clients is not None:
                self.clients.arrived(key, peer)
            up_writer.write(head)
            answer = await within(up_reader.readuntil(b"\r\n\r\n"), self.config.handshake_timeout_s)
            writer.write(answer.replace(CURRENT, EARLIER) if earlier else answer)
            writer.transport.set_write_buffer_limits(high=WRITE_HIGH)
            log.info("live.client_connected", client=peer, origin=origin, clients=self.connections,
                     subprotocol=(EARLIER if earlier else CURRENT).decode())
            await _until_both_end(_pipe(reader, up_writer, None), _pipe(up_reader, writer, self.config.stall_s))
        except Stalled:
            reason = "stalled"
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError):
            reason = "closed"
        except asyncio.CancelledError:
            reason = "stopped"
            raise
        finally:  # gone first: the SDK's complaints about the connection closed here are not the viewer's
            errors = self.clients.left(key) if self.clients is not None and key is not None else 0
            if up_writer is not None:
                up_writer.close()
            level = log.warning if reason == "stalled" else log.info
            level("live.client_left", client=peer, reason=reason, seconds=round(time.monotonic() - started, 1),
                  client_errors=errors, clients=self.connections - 1,
                  **({"stall_s": self.config.stall_s} if reason == "stalled" else {}))

    async def _refuse(self, writer: asyncio.StreamWriter, status: int, reason: str, peer: str, **fields: Any) -> None:
        """Answer a refused connection with an HTTP status and close it (logged once per reason)."""
        self.refusals.note(reason, client=peer, status=status, **fields)
        try:
            writer.write(b"HTTP/1.1 %d %s\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
                         % (status, ANSWERS[status]))
            await within(writer.drain(), 1.0)
        except (OSError, asyncio.TimeoutError):
            pass

    def stop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5.0)


async def _until_both_end(*pipes: Any) -> None:
    """Run the two directions; the first to fail (a stall, a reset) ends the other one too."""
    tasks = [asyncio.ensure_future(p) for p in pipes]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
        for task in done:
            task.result()
        await asyncio.gather(*tasks)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter, stall_s: float | None) -> None:
    """Copy until ``source`` ends, then close ``sink`` (an end passed on); ``stall_s``: raise Stalled
    when ``sink`` takes nothing for that long. On an error the caller closes both sides."""
    while data := await source.read(CHUNK):
        sink.write(data)
        if stall_s is None or sink.transport.get_write_buffer_size() <= WRITE_HIGH:
            await sink.drain()  # at once below the high-water mark (raises if the connection is gone)
            continue
        try:
            await within(sink.drain(), stall_s)  # a slow reader holds us here, and the SDK drops for it
        except asyncio.TimeoutError:
            raise Stalled from None
    sink.close()
