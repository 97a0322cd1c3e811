"""The live view as a public surface (issue "Open doors", items 2-5 and 13): half-open connections
time out, connections are capped, a foreign browser origin is refused, a viewer that stops
reading is dropped, client errors are logged once per client with a count, and handing messages
to viewers is the live view's own thread's work, never the recorder's."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import websockets
from structlog.testing import capture_logs

from respecd.clock import ManualClock
from respecd.messages import Frame
from respecd.record.codec import Message
from respecd.record.config import RecordingConfig
from respecd.record.live import LiveView, url
from respecd.record.live_config import DEFAULT_ORIGINS, LiveConfig, origin_allowed
from respecd.record.recorder import Recorder

PROFILE = {"name": "guard-rig", "sensors": [{"name": "cam", "modality": "rgb"}]}
PROTOCOL = ["foxglove.websocket.v1"]


class Rig:
    """A live view fed by a recorder with noisy 640x480 frames (JPEG ~250 kB: socket buffers fill fast)."""

    def __init__(self, config: LiveConfig) -> None:
        self.live = LiveView("127.0.0.1", 0, config=config)
        self.clock = ManualClock()
        self.recorder = Recorder(RecordingConfig(), PROFILE, self.clock, live=self.live, to_file=False)
        self.frames = [np.random.default_rng(k).integers(0, 255, (480, 640, 3), np.uint8) for k in range(4)]
        self.stop = asyncio.Event()

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.live.port}"

    async def __aenter__(self) -> Rig:
        self.recorder.start()
        self.feeder = asyncio.create_task(self._feed())
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.stop.set()
        await self.feeder
        await self.recorder.close()

    async def _feed(self) -> None:
        i = 0
        while not self.stop.is_set():
            self.clock.set(i / 30)
            self.recorder.on_frame("cam", Frame("rgb", i / 30, i, self.frames[i % 4]))
            i += 1
            await asyncio.sleep(0.02)


def _events(logs: list[dict], name: str) -> list[dict]:
    return [e for e in logs if e["event"] == name]


async def _until(predicate, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.05)


async def _channels(ws, topic: str = "/sensors/cam") -> list[dict]:
    """The channels advertised until ``topic`` is among them (they come as their first message does)."""
    channels: list[dict] = []
    while topic not in {c["topic"] for c in channels}:
        message = await asyncio.wait_for(ws.recv(), 10)
        if isinstance(message, str) and json.loads(message)["op"] == "advertise":
            channels += json.loads(message)["channels"]
    return channels


async def _subscribe(ws, channels: list[dict]) -> None:
    """Subscribe to every channel, until a frame arrives (the SDK may refuse a subscription to a
    channel it advertised a moment before: "Unknown channel ID"; then ask again)."""
    request = json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i, "channelId": c["id"]} for i, c in enumerate(channels)]})
    await ws.send(request)
    while True:
        message = await asyncio.wait_for(ws.recv(), 10)
        if isinstance(message, bytes) and message[0] == 1:  # op 1: message data of a subscription
            return
        if isinstance(message, str) and "Unknown channel" in message:
            await ws.send(request)


async def test_a_half_open_connection_is_answered_408_and_closed() -> None:
    async with Rig(LiveConfig(handshake_timeout_s=0.5)) as rig:
        with capture_logs() as logs:
            reader, writer = await asyncio.open_connection("127.0.0.1", rig.live.port)
            writer.write(b"GET / HTTP/1.1\r\n")  # and nothing more
            answer = await asyncio.wait_for(reader.read(), 10)
            writer.close()
            second, writer2 = await asyncio.open_connection("127.0.0.1", rig.live.port)
            assert await asyncio.wait_for(second.read(), 10)
            writer2.close()
    assert answer.startswith(b"HTTP/1.1 408 Request Timeout")
    refused = _events(logs, "live.refused")
    assert [e["reason"] for e in refused] == ["handshake_timeout"]  # once; the second one is counted
    assert rig.live._bridge is None  # closed


async def test_connections_over_the_cap_are_answered_503_and_a_viewer_gets_in_again() -> None:
    async with Rig(LiveConfig(max_clients=2)) as rig:
        first = await websockets.connect(rig.url, subprotocols=PROTOCOL)
        second = await websockets.connect(rig.url, subprotocols=PROTOCOL)
        with pytest.raises(websockets.InvalidStatus) as refused:
            await websockets.connect(rig.url, subprotocols=PROTOCOL)
        assert refused.value.response.status_code == 503
        await first.close()
        await _until(lambda: rig.live._bridge.connections < 2)
        third = await websockets.connect(rig.url, subprotocols=PROTOCOL)
        assert await _channels(third)
        for ws in (second, third):
            await ws.close()


@pytest.mark.parametrize("origin", ["http://evil.example", "null", "http://localhost.evil.example"])
async def test_a_page_from_a_foreign_origin_is_refused(origin: str) -> None:
    async with Rig(LiveConfig()) as rig:
        with pytest.raises(websockets.InvalidStatus) as refused:
            await websockets.connect(rig.url, subprotocols=PROTOCOL, origin=origin)  # type: ignore[arg-type]
        assert refused.value.response.status_code == 403
        for allowed in ("https://app.foxglove.dev", "http://localhost:8080", None):
            async with websockets.connect(rig.url, subprotocols=PROTOCOL, origin=allowed) as ws:  # type: ignore[arg-type]
                assert await _channels(ws)


def test_origins_are_matched_by_scheme_host_and_port() -> None:
    assert origin_allowed("http://127.0.0.1:5173", DEFAULT_ORIGINS)
    assert not origin_allowed("http://127.0.0.1.nip.io", DEFAULT_ORIGINS)
    assert not origin_allowed("https://app.foxglove.dev.evil.example", DEFAULT_ORIGINS)
    assert origin_allowed("http://lab.local:9000", ["http://lab.local:9000"])
    assert not origin_allowed("http://lab.local:9001", ["http://lab.local:9000"])
    assert origin_allowed("null", ["*"])
    with pytest.raises(ValueError, match="is not an origin"):
        LiveConfig(allowed_origins=["app.foxglove.dev"])


@pytest.mark.slow
async def test_a_viewer_that_stops_reading_is_dropped_and_logged_once() -> None:
    async with Rig(LiveConfig(stall_s=0.5, backlog=4)) as rig:
        with capture_logs() as logs:
            stalled = await websockets.connect(rig.url, subprotocols=PROTOCOL, max_queue=1, max_size=None)
            await _subscribe(stalled, await _channels(stalled))
            # never reads again: its client stops taking bytes from the socket once its queue is full
            await _until(lambda: _events(logs, "live.client_left"))
            async with websockets.connect(rig.url, subprotocols=PROTOCOL) as healthy:
                assert await _channels(healthy)
            await stalled.close()
    left = _events(logs, "live.client_left")[0]
    assert left["reason"] == "stalled" and left["log_level"] == "warning"
    loud = [e for e in logs if e["log_level"] in ("warning", "error") and e["event"] != "live.client_error"]
    assert loud == [left]  # once; a subscription refused in the SDK's advertise race is one client_error at most
    assert len(_events(logs, "live.client_error")) <= 1
    assert _events(logs, "live.client_connected")[0]["log_level"] == "info"


async def test_a_client_that_sends_garbage_is_logged_once_with_a_count() -> None:
    async with Rig(LiveConfig()) as rig:
        with capture_logs() as logs:
            async with websockets.connect(rig.url, subprotocols=PROTOCOL) as ws:
                drain = asyncio.create_task(_drain(ws))
                try:
                    for _ in range(300):
                        await ws.send(json.dumps({"op": "no-such-op"}))
                except websockets.ConnectionClosed:
                    pass  # the SDK may drop a client whose error answers pile up: that is fine too
                await asyncio.sleep(1.0)
                drain.cancel()
            await _until(lambda: _events(logs, "live.client_left"))
    errors = _events(logs, "live.client_error")
    assert len(errors) == 1 and "no-such-op" in errors[0]["message"]
    assert _events(logs, "live.client_left")[0]["client_errors"] > 1


async def _drain(ws) -> None:
    try:
        async for _ in ws:
            pass
    except websockets.ConnectionClosed:
        pass


def test_the_fan_out_runs_on_the_live_views_thread_and_drops_its_oldest() -> None:
    live = LiveView("127.0.0.1", 0, config=LiveConfig(queue_mib=8 * 100_000 / (1 << 20)))  # room for 8 messages
    live.open()
    release, seen = threading.Event(), []

    def slow_log(message: Message, log_ns: int) -> None:
        seen.append((threading.current_thread().name, log_ns))
        release.wait(10)

    live._log = slow_log  # type: ignore[method-assign]
    try:
        for ns in range(20):
            live.put(Message("/x", "respecd.Percept", b"x" * 100_000, {}), ns, 0.0)  # at once, whatever viewers do
        time.sleep(0.2)
        release.set()
        time.sleep(0.2)
    finally:
        live.close()
    assert {name for name, _ in seen} == {"respecd-live"}
    assert live.dropped >= 20 - 8 - 1 and seen[-1][1] == 19  # the newest kept, the oldest dropped


def test_urls_bracket_ipv6_hosts() -> None:
    assert url("::", 8765) == "ws://[::]:8765" and url("0.0.0.0", 1) == "ws://0.0.0.0:1"


@pytest.mark.e2e
def test_a_descriptor_limit_below_the_cap_is_a_config_error() -> None:
    code = ("import resource; from respecd.record.live import ensure_descriptors; "
            "resource.setrlimit(resource.RLIMIT_NOFILE, (300, 400)); "
            "from respecd.errors import ConfigError\n"
            "try:\n    ensure_descriptors(64)\nexcept ConfigError as e:\n    print(e)\n"
            "ensure_descriptors(32); print(resource.getrlimit(resource.RLIMIT_NOFILE)[0])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True).stdout
    assert "live.max_clients 64 needs 448 file descriptors, the limit is 400" in out
    assert out.splitlines()[-1] == "352"  # raised to what 32 viewers need

