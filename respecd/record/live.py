"""``--foxglove [HOST:]PORT``: the session's channels, live, over the Foxglove WebSocket
protocol, served by foxglove-sdk's own server (open it in Foxglove: "Open connection",
``ws://HOST:PORT``).

A sink of the recorder's worker thread, so a message is encoded once for the log and the
live view alike, and only while somebody is watching: a channel is advertised with its first
message, and after that a sensor frame is encoded only while a client is subscribed to it.
Handing a message to every viewer (the SDK copies it into each one's queue) is the live
view's own thread's work: ``put`` only queues it (``live.queue_mib``, oldest dropped, counted),
so viewers cost neither the recording nor the control loop. Bounded everywhere: that queue,
the server's ``live.backlog`` messages per client (oldest dropped for a slow one), and the
public port's guard (``live_bridge``: handshake timeout, connection cap, stalled viewers
dropped, browser origins allowed by the profile's ``live:`` section).

Loopback by default: the view has no authentication, so serving another interface is a
deliberate ``--foxglove 0.0.0.0:8765`` (see systemd/respecd.service for the unit's
IPAddressAllow).
"""

from __future__ import annotations

import resource
import threading
from collections import deque
from typing import Any

import structlog

from respecd.errors import ConfigError
from respecd.priority import VIEWER_NICE, lower_thread_priority
from respecd.record.codec import Message
from respecd.record.live_clients import ClientLog
from respecd.record.live_config import LiveConfig
from respecd.record.schemas import schema_def

log = structlog.get_logger(__name__)

DEFAULT_HOST = "127.0.0.1"
FDS_PER_CLIENT = 3  # the viewer's socket and both ends of its loopback connection to the SDK's server
FDS_SPARE = 256  # the rest of the daemon: devices, logs, torch's threads, the recorder's files


def parse_address(text: str) -> tuple[str, int]:
    """``8765``, ``127.0.0.1:8765``, ``[::1]:8765`` -> (host, port); ConfigError when malformed."""
    host, sep, port_text = text.rpartition(":")
    if not sep:
        host, port_text = DEFAULT_HOST, text
    host = host.strip("[]") or DEFAULT_HOST
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise ConfigError(f"--foxglove: {text!r}: expected [HOST:]PORT with a port 0-65535, e.g. 8765 or 0.0.0.0:8765")
    return host, port


def url(host: str, port: int) -> str:
    """``ws://HOST:PORT`` with an IPv6 host in brackets (``ws://[::]:8765``)."""
    return f"ws://[{host}]:{port}" if ":" in host else f"ws://{host}:{port}"


def ensure_descriptors(max_clients: int) -> None:
    """Raise the soft RLIMIT_NOFILE (up to the hard one) so ``max_clients`` viewers fit beside the
    rest of the daemon; ConfigError when the hard limit is too low (the unit's LimitNOFILE)."""
    needed = max_clients * FDS_PER_CLIENT + FDS_SPARE
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < needed:
        if hard != resource.RLIM_INFINITY and hard < needed:
            raise ConfigError(f"live.max_clients {max_clients} needs {needed} file descriptors, the limit is {hard} "
                              "(raise LimitNOFILE in the unit, ulimit -n, or lower live.max_clients)")
        resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


class LiveView:
    """The Foxglove WebSocket server as a recorder sink (``wants``/``put``/``close``)."""

    def __init__(self, host: str, port: int, name: str = "respecd", config: LiveConfig | None = None) -> None:
        self.host, self.port, self.name = host, port, name
        self.config = config or LiveConfig()
        self.dropped = 0  # messages the live view's thread did not get to (the oldest in its queue)
        self._context: Any = None
        self._server: Any = None
        self._channels: dict[str, Any] = {}
        self._bridge: Any = None
        self._clients = ClientLog()
        self._queue: deque[tuple[Message, int]] = deque()
        self._queued = 0  # payload bytes in _queue
        self._budget = int(self.config.queue_mib * (1 << 20))
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closing = False

    def open(self) -> int:
        """Start serving; the port really bound (``port`` 0 picks a free one).

        The SDK's server listens on a private loopback port; the public one is the bridge
        that also answers clients asking for the protocol's earlier name (``live_bridge``).
        """
        import foxglove

        from respecd.record.live_bridge import SubprotocolBridge

        ensure_descriptors(self.config.max_clients)
        self._context = foxglove.Context()
        self._clients.install()
        try:
            self._server = foxglove.start_server(name=self.name, host="127.0.0.1", port=0,
                                                 context=self._context, message_backlog_size=self.config.backlog)
        except Exception as err:  # the SDK raises its own error type
            self._clients.remove()
            raise ConfigError(f"--foxglove: cannot start the Foxglove server: {err}") from err
        self._bridge = SubprotocolBridge(self.host, self.port, int(self._server.port), self.config, self._clients)
        try:
            self.port = self._bridge.start()
        except OSError as err:
            self._server.stop()
            self._clients.remove()
            raise ConfigError(f"--foxglove {self.host}:{self.port}: cannot listen: {err.strerror or err}") from err
        self._thread = threading.Thread(target=self._run, name="respecd-live", daemon=True)
        self._thread.start()
        log.info("live.serving", url=url(self.host, self.port), max_clients=self.config.max_clients,
                 backlog=self.config.backlog, origins=self.config.allowed_origins)
        return self.port

    def wants(self, topic: str) -> bool:
        channel = self._channels.get(topic)
        return channel is None or channel.has_sinks()  # unknown yet: advertise it with this message

    def put(self, message: Message, log_ns: int, t: float) -> None:
        """Queue ``message`` for the viewers (the recorder's thread: returns at once)."""
        with self._cond:
            self._queue.append((message, log_ns))
            self._queued += len(message.payload)
            while self._queued > self._budget and len(self._queue) > 1:  # bounded in bytes: a frame is 5-600 kB
                old, _ = self._queue.popleft()
                self._queued -= len(old.payload)
                self.dropped += 1
            self._cond.notify()

    def _run(self) -> None:
        """The live view's thread: every queued message to every viewer subscribed to it."""
        lower_thread_priority(VIEWER_NICE)  # viewers are the least urgent work of the daemon
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if self._closing:
                    return
                message, log_ns = self._queue.popleft()
                self._queued -= len(message.payload)
            try:
                self._log(message, log_ns)
            except Exception:  # noqa: BLE001 - thread boundary: one bad message must not end the view
                log.exception("live.send_failed", topic=message.topic)

    def _log(self, message: Message, log_ns: int) -> None:
        channel = self._channels.get(message.topic)
        if channel is None:
            channel = self._channels[message.topic] = self._channel(message)
        channel.log(message.payload, log_time=log_ns)

    def _channel(self, message: Message) -> Any:
        import foxglove

        definition = schema_def(message.schema)
        schema = foxglove.Schema(name=definition.name, encoding=definition.encoding, data=definition.data)
        return foxglove.Channel(message.topic, schema=schema, message_encoding=definition.message_encoding,
                                context=self._context, metadata=dict(message.channel_meta))

    def close(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(2.0)
        bridge, self._bridge = self._bridge, None
        if bridge is not None:
            bridge.stop()
        server, self._server = self._server, None
        if server is not None:
            server.stop()
            self._clients.remove()
            log.info("live.stopped", dropped=self.dropped, refused=bridge.refusals.counts if bridge else {})
