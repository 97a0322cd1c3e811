"""Attacks on the live view's port of a real daemon (``--foxglove``): half-open connections, a
connection flood, foreign browser origins, viewers that stop reading, malformed frames and
garbage messages (``respecd bench attacks``). Each kind starts its own daemon; a kind's batch
runs at its first try and each try is then one connection's outcome."""

from __future__ import annotations

import base64
import json
import os
import random
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from respecd.lab.bench.attacks import Context, Kind

UPGRADE = ("GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           "Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.websocket.v1\r\n"
           "{extra}\r\n")


class Daemon:
    """``respecd --foxglove 127.0.0.1:PORT`` on the profile without detector, logging JSON to a file."""

    def __init__(self, ctx: Context, seconds: float = 300) -> None:
        self.folder = ctx.fresh("live")
        self.port = _free_port()
        self.log = self.folder / "log.jsonl"
        with open(self.log, "w") as out:
            self.child = subprocess.Popen(
                [sys.executable, "-m", "respecd.cli", "--profile", str(ctx.profile), "--duration", str(seconds),
                 "--foxglove", f"127.0.0.1:{self.port}", "--state-dir", str(self.folder / "st"),
                 "--log-format", "json"],
                stdout=out, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})  # lines as they come
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                return
            except OSError:
                time.sleep(0.3)
        raise RuntimeError("the daemon did not start serving")

    def alive(self) -> bool:
        return self.child.poll() is None

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.child.pid}/fd"))

    def rss_mb(self) -> int:
        status = Path(f"/proc/{self.child.pid}/status").read_text()
        return int(status.split("VmRSS:")[1].split()[0]) // 1024

    def events(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in self.log.read_text().splitlines() if line.startswith("{")]

    def stop(self) -> None:
        self.child.terminate()
        self.child.wait(30)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def handshake(port: int, extra: str = "", timeout: float = 10.0) -> tuple[socket.socket, bytes]:
    """A raw client's upgrade request and the server's answer head."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(UPGRADE.format(key=key, extra=extra).encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(4096)
        if not chunk:
            break
        head += chunk
    return sock, head


def frame(opcode: int, payload: bytes, fin: bool = True, masked: bool = True, length: int | None = None) -> bytes:
    """A WebSocket frame as a client sends it (masked), or spoiled as asked."""
    n = len(payload) if length is None else length
    first = (0x80 if fin else 0) | opcode
    size = bytes([n | (0x80 if masked else 0)]) if n < 126 else (
        bytes([126 | (0x80 if masked else 0)]) + struct.pack(">H", n) if n < 65536
        else bytes([127 | (0x80 if masked else 0)]) + struct.pack(">Q", n))
    if not masked:
        return bytes([first]) + size + payload
    mask = os.urandom(4)
    return bytes([first]) + size + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def _batch(ctx: Context, name: str, run: Callable[[Context], list[str | None]], i: int) -> str | None:
    """Run a kind's whole batch at its first try; each try is then one outcome of it."""
    cache = ctx.__dict__.setdefault("batches", {})
    if i == 0 or name not in cache:
        try:
            cache[name] = run(ctx)
        except Exception as err:  # noqa: BLE001 - the batch failed: every try of it is an escape, named once
            cache[name] = [f"harness: {type(err).__name__}: {err}"] * 1000
    outcomes = cache[name]
    return outcomes[i] if i < len(outcomes) else None


def _half_open(ctx: Context) -> list[str | None]:
    daemon = Daemon(ctx)
    try:
        base, socks = daemon.fds(), []
        for _ in range(200):
            sock = socket.create_connection(("127.0.0.1", daemon.port))
            sock.sendall(b"GET / HTTP/1.1\r\n")
            socks.append(sock)
        time.sleep(10)  # the handshake timeout is 5 s
        outcomes = []
        for sock in socks:
            sock.settimeout(0.5)
            try:
                data = sock.recv(4096)
                outcomes.append(None if data == b"" or data.startswith((b"HTTP/1.1 408", b"HTTP/1.1 503")) else
                                f"answered {data[:30]!r}")
            except TimeoutError:
                outcomes.append("still open after 10 s")
            except OSError:
                outcomes.append(None)  # reset: closed
            sock.close()
        with socket.create_connection(("127.0.0.1", daemon.port)) as probe:
            probe.settimeout(1)
        held = daemon.fds() - base
        if held > 20:
            outcomes[0] = outcomes[0] or f"{held} descriptors still held"
        errors = [e for e in daemon.events() if e.get("level") == "error"]
        if errors:
            outcomes[1] = outcomes[1] or f"{len(errors)} error lines"
        return outcomes
    finally:
        daemon.stop()


def half_open(ctx: Context, i: int) -> str | None:
    return _batch(ctx, "half_open", _half_open, i)


def _over_cap(ctx: Context) -> list[str | None]:
    daemon = Daemon(ctx)
    try:
        held = [handshake(daemon.port)[0] for _ in range(32)]  # the default cap
        outcomes = []
        for _ in range(50):
            sock, head = handshake(daemon.port)
            outcomes.append(None if head.startswith(b"HTTP/1.1 503") else f"answered {head[:30]!r}")
            sock.close()
        for sock in held:
            sock.close()
        time.sleep(1)
        sock, head = handshake(daemon.port)
        sock.close()
        if not head.startswith(b"HTTP/1.1 101"):
            outcomes[0] = f"a viewer after the flood got {head[:30]!r}"
        return outcomes
    finally:
        daemon.stop()


def over_cap(ctx: Context, i: int) -> str | None:
    return _batch(ctx, "over_cap", _over_cap, i)


ORIGINS = ["http://evil.example", "null", "http://localhost.evil.example", "https://app.foxglove.dev.evil.example",
           "https://evil.example/app.foxglove.dev", "http://127.0.0.1.nip.io", "file://evil", "chrome-extension://abc",
           "http://[::2]", "https://app.foxglove.de", "ws://evil.example", "http://169.254.169.254"]


def _origins(ctx: Context) -> list[str | None]:
    daemon = Daemon(ctx)
    try:
        outcomes = []
        for origin in ORIGINS:
            sock, head = handshake(daemon.port, f"Origin: {origin}\r\n")
            sock.close()
            outcomes.append(None if head.startswith(b"HTTP/1.1 403") else f"{origin}: {head[:30]!r}")
        return outcomes
    finally:
        daemon.stop()


def origins(ctx: Context, i: int) -> str | None:
    return _batch(ctx, "origins", _origins, i)


def _stalled(ctx: Context) -> list[str | None]:
    """30 viewers subscribe to every advertised channel and stop reading (their queue holds one message)."""
    from websockets.sync.client import connect

    daemon = Daemon(ctx)
    try:
        r0, viewers = daemon.rss_mb(), []
        for _ in range(30):
            ws = connect(f"ws://127.0.0.1:{daemon.port}", subprotocols=["foxglove.websocket.v1"],  # type: ignore[list-item]
                         max_queue=1, max_size=None, open_timeout=10, ping_interval=None, close_timeout=1)
            _subscribe_all(ws)
            viewers.append((ws, peer(ws.socket)))
        time.sleep(30)
        grown = daemon.rss_mb() - r0
        left = {e["client"] for e in daemon.events() if e["event"] == "live.client_left" and e["reason"] == "stalled"}
        outcomes: list[str | None] = []
        for ws, name in viewers:
            outcomes.append(None if name in left else "not dropped after 30 s")
            ws.close()
        if grown > 5 * len(viewers):
            outcomes[0] = outcomes[0] or f"RSS +{grown} MB"
        return outcomes
    finally:
        daemon.stop()


def _subscribe_all(ws: Any) -> None:
    """Every channel advertised within a second, subscribed until the server takes it (it may refuse a
    channel it advertised a moment before), then never read again."""
    channels: set[int] = set()
    for message in _messages(ws, 1.0):
        if isinstance(message, str) and json.loads(message).get("op") == "advertise":
            channels |= {c["id"] for c in json.loads(message)["channels"]}
    request = json.dumps({"op": "subscribe", "subscriptions": [{"id": c, "channelId": c} for c in sorted(channels)]})
    ws.send(request)
    for message in _messages(ws, 1.0):
        if isinstance(message, str) and "nknown channel" in message:
            ws.send(request)


def _messages(ws: Any, seconds: float) -> list[Any]:
    end, got = time.monotonic() + seconds, []
    while (left := end - time.monotonic()) > 0:
        try:
            got.append(ws.recv(timeout=left))
        except TimeoutError:
            break
    return got


def peer(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"{host}:{port}"


def stalled(ctx: Context, i: int) -> str | None:
    return _batch(ctx, "stalled", _stalled, i)


def _malformed() -> list[bytes]:
    rng = random.Random(52)
    big = json.dumps({"op": "subscribe", "subscriptions": [{"id": k, "channelId": k} for k in range(20000)]})
    nested = "[" * 100000 + "]" * 100000
    texts = ['{"op": "no-such-op"}', "not json", '{"op": "subscribe"}', '{"op": "subscribe", "subscriptions": 5}',
             '{"op": "unsubscribe", "subscriptionIds": [99, -1]}', '{"op": "advertise", "channels": []}',
             '{"op": "getParameters", "parameterNames": []}', '{"op": "setParameters", "parameters": [{}]}',
             '{"op": "subscribeConnectionGraph"}', '{"op": "fetchAsset", "uri": "file:///etc/shadow", "requestId": 1}',
             '{"op": "callService"}', big, nested, json.dumps({"op": "x" * 100000}), '{"op": null}', "[]", '""',
             '{"op": "subscribe", "subscriptions": [{"id": 1e400, "channelId": -1}]}']
    frames = [frame(1, t.encode()) for t in texts]
    frames += [frame(1, b"\xff\xfe\xfd"), frame(2, b"\x02" + os.urandom(40)), frame(2, b"\xff"), frame(2, b""),
               frame(3, b"x"), frame(0xB, b"x"), frame(9, b"p" * 200), frame(8, b"\x03\xe7"), frame(8, b"\x00"),
               frame(0, b"orphan continuation"), frame(1, b"{", fin=False) + frame(9, b"x", fin=False),
               frame(1, b"x", masked=False), frame(2, b"", length=2**62), bytes(rng.randbytes(64)),
               frame(1, b"{", fin=False) + frame(1, b"}"), frame(2, b"\x01" + os.urandom(100000)),
               b"\x81\xfe\xff\xff" + os.urandom(10)]
    return frames


def _garbage(ctx: Context) -> list[str | None]:
    daemon = Daemon(ctx)
    try:
        outcomes: list[str | None] = []
        for payload in _malformed():
            sock, head = handshake(daemon.port)
            try:
                sock.sendall(payload)
                sock.settimeout(1.0)
                sock.recv(65536)
            except OSError:
                pass
            sock.close()
            probe, answer = handshake(daemon.port)
            probe.close()
            outcomes.append(None if daemon.alive() and answer.startswith(b"HTTP/1.1 101") else
                            f"after {payload[:12]!r}: daemon {'up' if daemon.alive() else 'gone'}, {answer[:20]!r}")
        sock, _ = handshake(daemon.port)
        for _ in range(1000):
            sock.sendall(frame(1, b'{"op": "no-such-op"}'))
        sock.close()
        time.sleep(2)
        loud = [e for e in daemon.events() if e.get("level") in ("warning", "error")]
        if len(loud) > 2 * len(outcomes) + 2:  # at most one line a client, and its departure
            outcomes[0] = outcomes[0] or f"{len(loud)} warning/error lines for {len(outcomes) + 1} clients"
        return outcomes
    finally:
        daemon.stop()


def garbage(ctx: Context, i: int) -> str | None:
    return _batch(ctx, "garbage", _garbage, i)


KINDS = [
    Kind("live-half-open", "live view", 200, half_open, "connections that send 'GET / HTTP/1.1' and stop"),
    Kind("live-over-cap", "live view", 50, over_cap, "50 handshakes past the 32 viewers already connected"),
    Kind("live-origins", "live view", len(ORIGINS), origins,
         "browser handshakes from foreign origins (null, look-alike hosts, other schemes)"),
    Kind("live-stalled", "live view", 30, stalled, "viewers subscribed to every channel that stop reading"),
    Kind("live-malformed", "live view", len(_malformed()), garbage,
         "malformed frames and messages (bad opcodes, lengths, UTF-8, JSON), then 1,000 unknown ops"),
]
