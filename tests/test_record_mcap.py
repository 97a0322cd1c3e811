"""Recorder → MCAP file: readable by the mcap library, sensor channels valid against the
Foxglove JSON schemas stored in the file, bit-exact where the encoding is lossless, cut
files readable up to the cut, rotation and drop-oldest accounting."""

from __future__ import annotations

import asyncio
import base64
import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from respecd.clock import ManualClock
from respecd.errors import InputError
from respecd.messages import Bundle, Decision, Detection, Frame, Health, Percept, SensorConfig, SyncStats
from respecd.record.channels import MODELS
from respecd.record.config import RecordingConfig
from respecd.record.reader import open_log
from respecd.record.recorder import Recorder

INTRINSICS = {"fx": 457.0, "fy": 457.0, "cx": 320.0, "cy": 180.0, "width": 640, "height": 360}
PROFILE = {"name": "test-rig",
           "sensors": [{"name": "cam", "modality": "rgb", "calibration": {"intrinsics": INTRINSICS}}]}


def _validate(value: Any, schema: dict[str, Any], path: str = "$") -> None:
    """The subset of JSON Schema the Foxglove schemas use: type, properties, items, bounds, oneOf/const."""
    kinds = schema.get("type")
    if kinds is not None:
        kinds = kinds if isinstance(kinds, list) else [kinds]
        checks = {
            "object": lambda v: isinstance(v, dict),
            "array": lambda v: isinstance(v, list),
            "string": lambda v: isinstance(v, str),
            "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
            "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
            "boolean": lambda v: isinstance(v, bool),
            "null": lambda v: v is None,
        }
        assert any(checks[k](value) for k in kinds), f"{path}: {value!r:.60} is not {kinds}"
    if "minimum" in schema:
        assert value >= schema["minimum"], path
    if "maximum" in schema:
        assert value <= schema["maximum"], path
    if "oneOf" in schema:
        assert sum(1 for s in schema["oneOf"] if s.get("const") == value) == 1, f"{path}: {value!r} not one of"
    if schema.get("contentEncoding") == "base64":
        base64.b64decode(value, validate=True)
    if isinstance(value, dict):
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                _validate(value[key], sub, f"{path}.{key}")
        if isinstance(schema.get("additionalProperties"), dict):
            for key in set(value) - set(schema.get("properties", {})):
                _validate(value[key], schema["additionalProperties"], f"{path}.{key}")
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            _validate(item, schema["items"], f"{path}[{i}]")


def _frames(i: int, rng: np.random.Generator) -> dict[str, Frame]:
    t = i / 30
    rgb = np.zeros((360, 640, 3), np.uint8)
    cv2.rectangle(rgb, (100 + i, 80), (220 + i, 300), (40, 200, 90), -1)  # a smooth scene: JPEG-friendly
    return {
        "cam": Frame("rgb", t, i, rgb, {"gt": [[100.0 + i, 80.0, 220.0 + i, 300.0]]}),
        "ir": Frame("thermal", t, i, rng.integers(2900, 4100, (120, 160), dtype=np.uint16)),
        "depth": Frame("depth", t, i, rng.integers(300, 3000, (48, 64), dtype=np.uint16)),
        "radar": Frame("radar", t, i, rng.normal(size=(5 + i % 4, 5)).astype(np.float32), {"raw": bytes([i]) * 9}),
        "imu": Frame("imu", t, i, rng.normal(size=6).astype(np.float32)),
    }


async def _record(tmp_path: Path, n: int = 45, **overrides: Any) -> tuple[Recorder, list[dict[str, Frame]]]:
    overrides.setdefault("queue_size", 8192)  # a busy machine must not make this test drop (it is not about drops)
    config = RecordingConfig(enabled=True, path=str(tmp_path / "log-{time}.mcap"), chunk_size_kib=32, **overrides)
    clock = ManualClock()
    recorder = Recorder(config, PROFILE, clock)
    recorder.start()
    rng = np.random.default_rng(7)
    sent = []
    for i in range(n):
        clock.set(i / 30)
        frames = _frames(i, rng)
        sent.append(frames)
        for name, frame in frames.items():
            recorder.on_frame(name, frame)
        if i % 15 == 0:
            detections = (Detection((1, 2, 30, 40), 0.8),)
            bundle = Bundle(i / 30, {"rgb": frames["cam"]}, SyncStats(30.0, 0.1, 0.0, Health.GOOD), i)
            attributed = {"dependence": {"rgb": 0.1, "thermal": 0.05}, "sufficiency": {"rgb": 0.9, "thermal": 0.8}}
            recorder.on_percept(Percept(i / 30, detections, 0.8, {"rgb": 0.6, "thermal": 0.4}, 0.02, bundle,
                                        **(attributed if i else {})))
            recorder.on_decision(Decision(i / 30, (0, 1, 2, 0, 0, 1), 4, -0.1, 0.2, (0.0, 0.5)))
            recorder.on_config("cam", SensorConfig("rgb", True, 15.0, (640, 360)))
        await asyncio.sleep(0.002)  # let the writer keep up: this test is not about drops
    for _ in range(1000):  # nor about the close's drain budget: all is encoded before it
        if not recorder._queue:
            break
        await asyncio.sleep(0.01)
    await recorder.close()
    return recorder, sent


async def test_log_opens_with_mcap_reader_and_decodes_with_foxglove_schemas(tmp_path: Path) -> None:
    recorder, sent = await _record(tmp_path, rgb_format="jpeg")
    assert recorder.dropped == 0 and len(recorder.paths) == 1
    with open(recorder.paths[0], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == recorder.written
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        assert json.loads(metadata["respecd.profile"]["json"])["name"] == "test-rig"
        seen: dict[str, int] = {}
        image_stamps: dict[int, Any] = {}
        overlays, metas, percepts = [], {}, []
        for schema, channel, message in reader.iter_messages():
            seen[schema.name] = seen.get(schema.name, 0) + 1
            if schema.name.startswith("foxglove."):
                body = _decode_foxglove(schema, channel, message.data)
            else:
                assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
                body = json.loads(message.data)
                _validate(body, json.loads(schema.data))
                MODELS[schema.name].model_validate_json(message.data)  # the typed model, strictly
            if channel.topic.endswith("/meta"):
                metas[channel.topic.removesuffix("/meta"), message.log_time] = body
            if channel.topic == "/respecd/percept":
                percepts.append(body)
                assert set(body) <= set(json.loads(schema.data)["properties"])  # every field declared
            if channel.topic == "/respecd/detections":
                overlays.append(body)
                assert channel.metadata == {"image_topic": "/sensors/cam"}
            if channel.topic == "/sensors/cam":
                image_stamps[metas["/sensors/cam", message.log_time]["seq"]] = _stamp(body.timestamp)
                image = cv2.imdecode(np.frombuffer(body.data, np.uint8), cv2.IMREAD_COLOR)
                assert body.format == "jpeg" and image.shape == (360, 640, 3) and body.frame_id == "cam"
            if channel.topic == "/sensors/radar":
                assert [f.name for f in body.fields] == ["x", "y", "z", "v", "snr"] and body.point_stride == 20
                points = np.frombuffer(body.data, "<f4").reshape(-1, 5)
                seq = metas["/sensors/radar", message.log_time]["seq"]
                np.testing.assert_array_equal(points, sent[seq]["radar"].data)
    assert seen["foxglove.CompressedImage"] == 4 * 45  # rgb jpeg, thermal and depth png, thermal display image
    assert "foxglove.RawImage" not in seen
    assert seen["foxglove.PointCloud"] == 45 and seen["respecd.RawBytes"] == 45
    assert seen["respecd.FrameMeta"] == 5 * 45
    assert seen["respecd.Decision"] == 3 and seen["respecd.SensorConfig"] == 3
    assert seen["foxglove.FrameTransforms"] >= 2 and seen["foxglove.CameraCalibration"] >= 1
    assert len(overlays) == 3  # detections drawn over the very RGB frame they came from
    # beside the contributions, what each sensor's detections depend on (null when not attributed)
    assert [p["dependence"] for p in percepts] == [None] + [{"rgb": 0.1, "thermal": 0.05}] * 2
    assert percepts[1]["sufficiency"] == {"rgb": 0.9, "thermal": 0.8} and percepts[0]["sufficiency"] is None
    assert _stamp(overlays[1].points[0].timestamp) == image_stamps[15] == _stamp(overlays[1].timestamp)
    assert [(p.x, p.y) for p in overlays[1].points[0].points][2] == (30.0, 40.0)
    assert [t.text for t in overlays[1].texts] == ["person 0.80"]


def _stamp(ts: Any) -> tuple[int, int]:
    return ts.seconds, ts.nanos


def _decode_foxglove(schema: Any, channel: Any, data: bytes) -> Any:
    """Decode with the schema foxglove-sdk publishes (byte-identical to the file's); every
    byte must belong to a field of that schema (re-encoding gives the same bytes)."""
    import foxglove.messages as fox
    from mcap_protobuf.decoder import DecoderFactory

    official = getattr(fox, schema.name.removeprefix("foxglove.")).get_schema()
    assert (schema.encoding, channel.message_encoding) == ("protobuf", "protobuf")
    assert schema.data == bytes(official.data)
    message = DecoderFactory().decoder_for("protobuf", schema)(data)
    assert message.SerializeToString() == data
    return message


async def test_frames_come_back_exact_where_lossless(tmp_path: Path) -> None:
    recorder, sent = await _record(tmp_path)
    log = open_log(recorder.paths[0])
    assert log.sensors == {"cam": "rgb", "ir": "thermal", "depth": "depth", "radar": "radar", "imu": "imu"}
    assert log.channels["/sensors/depth"].schema == "foxglove.CompressedImage"  # lossless 16-bit PNG
    for name in ("ir", "depth", "radar", "imu"):
        frames = list(log.frames(name))
        assert [f.seq for f in frames] == list(range(45))
        for f in frames:
            np.testing.assert_array_equal(f.data, sent[f.seq][name].data)
            assert f.t == sent[f.seq][name].t and f.modality == sent[f.seq][name].modality
    radar = list(log.frames("radar"))
    assert radar[3].meta["raw"] == bytes([3]) * 9  # the raw UART bytes rejoin their frame
    assert log.channels["/sensors/cam"].schema == "foxglove.CompressedImage"  # lossless PNG: the default
    rgb = list(log.frames("cam"))
    assert rgb[10].meta["gt"] == [[110.0, 80.0, 220.0 + 10, 300.0]]
    np.testing.assert_array_equal(rgb[10].data, sent[10]["cam"].data)


async def test_jpeg_rgb_is_close_and_raw_images_are_exact(tmp_path: Path) -> None:
    recorder, sent = await _record(tmp_path, rgb_format="jpeg", thermal_format="raw", depth_format="raw")
    log = open_log(recorder.paths[0])
    assert log.channels["/sensors/ir"].schema == log.channels["/sensors/depth"].schema == "foxglove.RawImage"
    for name in ("ir", "depth"):
        for f in log.frames(name):
            np.testing.assert_array_equal(f.data, sent[f.seq][name].data)
    rgb = list(log.frames("cam"))
    error = np.abs(rgb[10].data.astype(int) - sent[10]["cam"].data.astype(int)).mean()
    assert 0 < error < 3.0  # JPEG at quality 80 on a flat scene


async def test_cut_log_reads_up_to_the_last_complete_chunk(tmp_path: Path) -> None:
    recorder, _ = await _record(tmp_path)
    data = recorder.paths[0].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    log = open_log(cut)
    assert log.truncated
    frames = list(log.frames("cam"))
    assert 0 < len(frames) < 45
    assert [f.seq for f in frames] == list(range(len(frames)))  # a prefix, nothing garbled
    full = open_log(recorder.paths[0])
    assert not full.truncated and full.message_count > log.message_count


async def test_rotation_by_size_gives_complete_segments(tmp_path: Path) -> None:
    recorder, _ = await _record(tmp_path, rotate_mib=1, flush_s=0.1)  # 1 MiB: the smallest segment
    assert len(recorder.paths) >= 2
    assert recorder.paths[1].name.endswith("-001.mcap")
    total = 0
    for path in recorder.paths:
        log = open_log(path)
        assert not log.truncated and log.profile_dict() == PROFILE
        total += log.message_count
    assert total == recorder.written


async def test_queue_drops_oldest_and_counts(tmp_path: Path) -> None:
    config = RecordingConfig(enabled=True, path=str(tmp_path / "busy.mcap"), queue_size=8, rgb_format="jpeg")
    recorder = Recorder(config, PROFILE, ManualClock())
    recorder.start()
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8)  # slow to JPEG-encode
    for i in range(300):  # faster than any writer: the taps must not block
        recorder.on_frame("cam", Frame("rgb", i / 30, i, noise))
    await recorder.close()
    assert recorder.dropped > 0
    frames = list(open_log(recorder.paths[0]).frames("cam"))
    assert len(frames) + recorder.dropped == 300
    assert frames[-1].seq == 299  # the newest survive


async def test_writer_encodes_in_batches_but_never_waits_on_a_half_full_queue_or_at_close(tmp_path: Path) -> None:
    config = RecordingConfig(enabled=True, path=str(tmp_path / "batch.mcap"), queue_size=8, batch_s=5.0)
    recorder = Recorder(config, PROFILE, ManualClock())
    recorder.start()
    imu = _frames(0, np.random.default_rng(2))["imu"]
    recorder.on_frame("imu", imu)
    await asyncio.sleep(0.5)
    assert recorder.cpu_s == 0.0  # queued, not yet encoded: the writer sleeps out its 5 s batch
    for seq in range(1, 4):  # four queued: half of queue_size wakes the writer at once
        recorder.on_frame("imu", Frame("imu", seq / 30, seq, imu.data))
    for _ in range(300):
        if recorder.cpu_s > 0:
            break
        await asyncio.sleep(0.01)
    assert recorder.cpu_s > 0
    recorder.on_frame("imu", Frame("imu", 4 / 30, 4, imu.data))
    started = time.monotonic()
    await recorder.close()
    assert time.monotonic() - started < 4.0  # close drains now, it does not sleep out the batch
    assert [f.seq for f in open_log(recorder.paths[0]).frames("imu")] == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (None, "no such file"),
        (b"", "empty file"),
        (b"PK\x03\x04 a zip, not a log", "not an MCAP file"),
        (b"\x89MCAP0\r\n", "holds no messages"),  # the magic and nothing else
    ],
)
def test_bad_files_are_input_errors(tmp_path: Path, content: bytes | None, expected: str) -> None:
    path = tmp_path / "session.mcap"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=expected) as err:
        open_log(path)
    assert str(path) in str(err.value)


async def test_close_gives_up_queued_frames_to_finish_in_time(tmp_path: Path) -> None:
    """SIGTERM budget: frames still queued after the drain window are dropped, the file is finished."""
    config = RecordingConfig(enabled=True, path=str(tmp_path / "term.mcap"), queue_size=4096)
    recorder = Recorder(config, PROFILE, ManualClock())
    recorder.start()
    noise = np.random.default_rng(2).integers(0, 255, (720, 1280, 3), dtype=np.uint8)  # ~10 ms to encode
    for i in range(400):
        recorder.on_frame("cam", Frame("rgb", i / 30, i, noise))
    recorder.on_decision(Decision(14.0, (0,), 1, 0.0, 0.0, (0.0,)))
    await recorder.close()
    assert recorder.dropped > 0  # no queue overflow here: only the drain window drops
    log = open_log(recorder.paths[0])
    assert len(list(log.frames("cam"))) + 1 + recorder.dropped == 401
    assert not log.truncated and log.channels["/respecd/decision"].count == 1  # cheap messages always kept


async def test_an_undecodable_replayed_frame_is_left_out_with_one_warning_and_no_traceback(tmp_path: Path) -> None:
    """A replayed log's damaged image reaches the recorder as a LazyFrame that cannot decode: input, not a bug."""
    from structlog.testing import capture_logs

    from respecd.errors import UndecodableImageError
    from respecd.record.lazy import LazyFrame

    def cut() -> np.ndarray:
        raise UndecodableImageError("JPEG cut short")

    config = RecordingConfig(enabled=True, path=str(tmp_path / "log.mcap"), queue_size=64)
    recorder = Recorder(config, PROFILE, ManualClock())
    with capture_logs() as logs:
        recorder.start()
        for seq in range(3):
            recorder.on_frame("cam", LazyFrame("rgb", seq / 30, seq, decode=cut, shape=(360, 640, 3)))
        recorder.on_frame("cam", Frame("rgb", 0.1, 3, np.zeros((360, 640, 3), np.uint8)))
        await recorder.close()
    warned = [e for e in logs if e["event"] == "record.frame_undecodable"]
    assert len(warned) == 1 and "rgb frame 0" in warned[0]["error"] and "exc_info" not in warned[0]
    assert not [e for e in logs if e["event"] == "record.encode_failed"]
    assert recorder.undecodable == 3 and recorder.errors == 0
    assert [f.seq for f in open_log(recorder.paths[0]).frames("cam")] == [3]
