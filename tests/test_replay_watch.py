"""The counterfactual can be watched: ``--replay LOG --record OUT`` writes what the controller
would have done as a respecd log (frames as the sensors would have been configured, percepts,
decisions) that ``log info`` and the Python ``mcap`` reader with CRCs accept, and ``--replay LOG
--foxglove`` serves it to an independent WebSocket client that decodes its channels by the
schemas the server advertises."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import subprocess
import sys
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import websockets
import yaml
from conftest import run_cli
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from real_camera import LLVIP, photos, write_log

from respecd.drivers.replay import ACTION_RESOLUTIONS

REPO = Path(__file__).resolve().parents[1]
OP_MESSAGE_DATA = 1

pytestmark = pytest.mark.skipif(not LLVIP.is_dir(), reason=f"shared photos not found at {LLVIP}")


def _camera_log(path: Path, seconds: float, hz: float = 4.0) -> Path:
    """Real photos as a simulated rover's camera: a log whose recorded profile the replay runs."""
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["name"] = "street-camera"
    profile["sensors"] = [profile["sensors"][0] | {"resolution": [640, 512]}]
    profile["controller"] = {"decision_period_s": 0.5, "window_s": 0.5, "min_dwell_s": 0.5}
    images = photos(20)
    return write_log(path, profile, [images[i % len(images)] for i in range(round(seconds * hz))], hz)


@pytest.mark.slow
def test_the_counterfactual_session_is_recorded_as_a_log(tmp_path: Path) -> None:
    source = _camera_log(tmp_path / "street.mcap", seconds=4.0)
    out, report = tmp_path / "cf.mcap", tmp_path / "r.json"
    ran = run_cli("--replay", str(source), "--policy", "heuristic", "--speed", "max", "--record", str(out),
                  "--report", str(report), "--log-format", "json")
    assert ran.returncode == 0, ran.stderr[-2000:]
    info = run_cli("log", "info", str(out), "--json")
    assert info.returncode == 0, info.stderr
    entry = json.loads(report.read_text())["policies"]["heuristic"]
    counts, resolution, mismatched = Counter(), None, []
    with open(out, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        decoders = DecoderFactory()
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            counts[channel.topic] += 1
            if channel.topic == "/respecd/config" and json.loads(message.data)["sensor"] == "rgb":
                resolution = json.loads(message.data)["resolution"]
            elif channel.topic == "/sensors/rgb":
                image = decoders.decoder_for(channel.message_encoding, schema)(message.data)
                pixels = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_UNCHANGED)
                if [pixels.shape[1], pixels.shape[0]] != resolution:
                    mismatched.append((pixels.shape, resolution))
        replayed = {m.name: dict(m.metadata) for m in reader.iter_metadata()}["respecd.replay"]
    assert replayed["source"] == "street.mcap" and replayed["policy"] == "heuristic"
    assert counts["/sensors/rgb"] == entry["compute"]["frames"]["rgb"]  # every frame served, none dropped
    assert counts["/respecd/decision"] == len(entry["decisions"]) >= 4
    assert counts["/respecd/percept"] == len(entry["timeline"]) >= 1
    assert not mismatched  # each frame as the sensor was configured when it was taken
    assert json.loads(info.stdout)["sensors"]["rgb"]["frames"] == counts["/sensors/rgb"]


@pytest.mark.slow
def test_the_counterfactual_session_is_served_live(tmp_path: Path) -> None:
    source = _camera_log(tmp_path / "street.mcap", seconds=30.0, hz=2.0)
    argv = [sys.executable, "-m", "respecd.cli", "--replay", str(source), "--policy", "heuristic", "--speed", "1",
            "--foxglove", "127.0.0.1:0", "--log-format", "json"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        port = _served_port(proc)
        decoded = asyncio.run(_watch(port, {"/sensors/rgb", "/respecd/percept"}))
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    image = cv2.imdecode(np.frombuffer(decoded["/sensors/rgb"].data, np.uint8), cv2.IMREAD_UNCHANGED)
    # as the camera would have been configured: the log's 640x512 or a size the robot's camera offers
    offered = {(640, 512), *ACTION_RESOLUTIONS["rgb"]}
    assert image.shape[2] == 3 and (image.shape[1], image.shape[0]) in offered
    assert decoded["/sensors/rgb"].frame_id == "rgb"
    assert decoded["/respecd/percept"]["latency_s"] > 0 and "detections" in decoded["/respecd/percept"]


@pytest.mark.parametrize("lossless", [True, False])
async def test_a_lossless_recorder_waits_for_room_instead_of_dropping(tmp_path: Path, lossless: bool) -> None:
    """A lockstep replay's clock runs ahead of the encoder: its recorder holds the taps instead."""
    from respecd.clock import ManualClock
    from respecd.messages import Frame
    from respecd.record.config import RecordingConfig
    from respecd.record.recorder import Recorder

    config = RecordingConfig(path=str(tmp_path / "out.mcap"), queue_size=8, batch_s=0.0)
    recorder = Recorder(config, {"name": "cam-rig", "sensors": [{"name": "cam", "modality": "rgb"}]},
                        ManualClock(), lossless=lossless, origin=(5.0, 1_700_000_000 * 10**9))
    recorder.start()
    image = photos(1)[0]
    for i in range(60):  # far faster than the PNG encoder: no await between the taps
        recorder.on_frame("cam", Frame("rgb", 5.0 + i / 30, i, image))
    await recorder.close()
    with open(tmp_path / "out.mcap", "rb") as f:
        messages = make_reader(f, validate_crcs=True).iter_messages(topics=["/sensors/cam"])
        times = [m.log_time for _, _, m in messages]
    if lossless:
        assert recorder.dropped == 0 and len(times) == 60
        assert times[0] == 1_700_000_000 * 10**9  # session time 5.0 is the origin's log time
    else:
        assert recorder.dropped > 0 and len(times) < 60


def _served_port(proc: subprocess.Popen) -> int:
    assert proc.stdout is not None
    for line in proc.stdout:
        if '"live.serving"' in line:
            return int(json.loads(line)["url"].rsplit(":", 1)[1])
    raise AssertionError(f"the replay ended without serving (exit {proc.wait()})")


async def _watch(port: int, topics: set[str]) -> dict[str, object]:
    """An independent Foxglove WebSocket client: subscribe to ``topics`` once advertised, decode
    one message of each by the schema the server advertised for it."""
    decoded: dict[str, object] = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"],
                                  max_size=None) as ws:
        channels: dict[int, dict] = {}
        subscribed: dict[int, dict] = {}
        while set(decoded) != topics:
            data = await asyncio.wait_for(ws.recv(), 60)
            if isinstance(data, str):
                message = json.loads(data)
                if message.get("op") == "status" and "Unknown channel ID" in message.get("message", ""):
                    # foxglove-sdk advertises a channel a moment before it takes subscriptions to it
                    # (as in test_live_view): a client that is told so subscribes again
                    channel_id = int(message["message"].rsplit(" ", 1)[1])
                    await asyncio.sleep(0.2)
                    await ws.send(json.dumps({"op": "subscribe",
                                              "subscriptions": [{"id": channel_id, "channelId": channel_id}]}))
                elif message.get("op") == "advertise":
                    channels.update({c["id"]: c for c in message["channels"] if c["topic"] in topics})
                    wanted = [{"id": cid, "channelId": cid} for cid in channels if cid not in subscribed]
                    subscribed.update({cid: channels[cid] for cid in channels})
                    if wanted:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": wanted}))
            elif data[0] == OP_MESSAGE_DATA:
                subscription, _ = struct.unpack_from("<IQ", data, 1)
                channel = subscribed[subscription]
                decoded.setdefault(channel["topic"], _decode(channel, data[13:]))
    return decoded


def _decode(channel: dict, payload: bytes) -> object:
    if channel["encoding"] == "json":
        return json.loads(payload)
    schema = Schema(id=1, name=channel["schemaName"], encoding="protobuf", data=base64.b64decode(channel["schema"]))
    return DecoderFactory().decoder_for("protobuf", schema)(payload)
