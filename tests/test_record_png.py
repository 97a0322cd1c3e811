"""The recorder's own PNG encoder (ISA-L deflate): every frame comes back exactly through libpng
(``cv2.imdecode``, an independent decoder) and through the replay's reader, the file is a
well-formed PNG (chunk CRCs checked with the standard library's zlib), and OpenCV's encoder
takes over where isal is missing."""

from __future__ import annotations

import asyncio
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from structlog.testing import capture_logs

from respecd.clock import ManualClock
from respecd.drivers.flirone_usb import RecordedTransport
from respecd.messages import Frame
from respecd.record import png
from respecd.record.config import RecordingConfig
from respecd.record.reader import open_log
from respecd.record.recorder import Recorder
from respecd.sim.render import render_depth, render_thermal
from respecd.sim.world import SimulationConfig, World


def decoded(data: bytes) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None
    return image


def chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, data) of every chunk, each CRC checked with zlib.crc32 (not the encoder's own CRC)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    out, at = [], 8
    while at < len(data):
        (length,) = struct.unpack_from(">I", data, at)
        kind, body = data[at + 4:at + 8], data[at + 8:at + 8 + length]
        (crc,) = struct.unpack_from(">I", data, at + 8 + length)
        assert crc == zlib.crc32(kind + body), f"bad CRC on {kind!r}"
        out.append((kind, body))
        at += 12 + length
    assert at == len(data)
    return out


@pytest.fixture(scope="module")
def simulated() -> dict[str, list[np.ndarray]]:
    """Depth (640x480 millimetres) and thermal (160x120 centikelvin) frames of a scene with people."""
    world, rng = World(SimulationConfig(scenarios=["good-light-moving"]), 0), np.random.default_rng(0)
    states = [world.state_at(5.0 + k / 15) for k in range(3)]
    return {"depth": [render_depth(s, (640, 480), rng) for s in states],
            "thermal": [render_thermal(s, (160, 120), rng) for s in states]}


@pytest.mark.parametrize("modality", ["depth", "thermal"])
def test_simulated_frames_come_back_exactly_through_libpng(simulated: dict, modality: str) -> None:
    for frame in simulated[modality]:
        assert frame.dtype == np.uint16 and frame.ndim == 2 and len(np.unique(frame)) > 100
        data = png.encode(frame)
        assert np.array_equal(decoded(data), frame)
        assert [kind for kind, _ in chunks(data)] == [b"IHDR", b"IDAT", b"IEND"]
        assert len(data) < 0.6 * frame.nbytes  # it compresses: the filter and deflate did their work


def test_ihdr_says_what_the_image_is() -> None:
    header = dict(chunks(png.encode(np.zeros((3, 5), np.uint16))))[b"IHDR"]
    assert struct.unpack(">IIBBBBB", header) == (5, 3, 16, 0, 0, 0, 0)  # width, height, 16-bit grey
    header = dict(chunks(png.encode(np.zeros((3, 5, 4), np.uint8))))[b"IHDR"]
    assert struct.unpack(">IIBBBBB", header) == (5, 3, 8, 6, 0, 0, 0)  # 8-bit RGBA


def test_the_image_data_is_a_standard_zlib_stream() -> None:
    frame = np.arange(12, dtype=np.uint16).reshape(3, 4) * 4099
    raw = zlib.decompress(dict(chunks(png.encode(frame)))[b"IDAT"])
    rows = np.frombuffer(raw, np.uint8).reshape(3, 1 + 8)
    assert list(rows[:, 0]) == [1, 1, 1]  # Sub on every row
    # undo Sub by hand: each byte plus the same byte of the pixel to its left, then big-endian
    samples = np.cumsum(rows[:, 1:].reshape(3, 4, 2).astype(np.int64), axis=1) % 256
    assert np.array_equal(samples[..., 0] * 256 + samples[..., 1], frame)


@pytest.mark.parametrize("image", [
    np.array([[40_000]], np.uint16),  # 1x1
    np.array([[7]], np.uint8),
    np.random.default_rng(1).integers(0, 65536, (7, 13), dtype=np.uint16),  # odd width and height
    np.random.default_rng(2).integers(0, 256, (5, 3), dtype=np.uint8),
    np.zeros((480, 640), np.uint16),
    np.full((120, 160), 65535, np.uint16),
    np.full((9, 11), 255, np.uint8),
    np.random.default_rng(3).integers(0, 65536, (1, 33), dtype=np.uint16),  # one row: nothing above it
    np.random.default_rng(4).integers(0, 65536, (33, 1), dtype=np.uint16),  # one column: nothing to the left
    np.random.default_rng(5).integers(0, 256, (17, 23, 3), dtype=np.uint8),  # BGR
    np.random.default_rng(6).integers(0, 256, (17, 23, 4), dtype=np.uint8),  # BGRA
    np.random.default_rng(7).integers(0, 65536, (17, 23, 3), dtype=np.uint16),  # 16-bit BGR
    np.random.default_rng(8).integers(0, 65536, (17, 23, 4), dtype=np.uint16),  # 16-bit BGRA
], ids=lambda a: f"{'x'.join(map(str, a.shape))}-{a.dtype}")
def test_edge_cases_round_trip(image: np.ndarray) -> None:
    assert np.array_equal(decoded(png.encode(image)), image)


def test_non_contiguous_arrays_round_trip() -> None:
    rng = np.random.default_rng(9)
    depth = rng.integers(0, 65536, (48, 64), dtype=np.uint16)
    colour = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    views = [depth[::2, 1::3], depth.T, depth[::-1, ::-1], np.asfortranarray(depth),
             colour[:, ::2], colour[::-1, :, :], colour.transpose(1, 0, 2), colour[..., 0]]
    for view in views:
        assert np.array_equal(decoded(png.encode(view)), view)


def test_a_trailing_channel_of_one_is_grey() -> None:
    image = np.random.default_rng(10).integers(0, 65536, (6, 5, 1), dtype=np.uint16)
    assert np.array_equal(decoded(png.encode(image)), image[..., 0])


@pytest.mark.parametrize("image", [np.zeros((4, 4), np.float32), np.zeros((4, 4, 2), np.uint8),
                                   np.zeros((0, 4), np.uint16), np.zeros((4,), np.uint8),
                                   np.zeros((4, 4), np.int16)])
def test_what_png_cannot_hold_is_a_clear_error(image: np.ndarray) -> None:
    with pytest.raises(ValueError, match="png: cannot encode"):
        png.encode(image)


def test_real_thermal_frames_round_trip(shared_data: Path) -> None:
    from respecd.drivers.flirone_protocol import FrameAssembler

    assembler = FrameAssembler()
    reads = RecordedTransport.from_path(shared_data / "flirone_pro_gen3_usb_moezemara" / "test_chunks_hex").chunks
    frames = [frame for read in reads for frame in assembler.feed(read)]
    assert len(frames) == 20
    for frame in frames:  # Lepton 14-bit counts, 80x60
        assert np.array_equal(decoded(png.encode(frame.thermal)), frame.thermal)


def test_real_grey_thermal_images_round_trip(shared_data: Path) -> None:
    paths = sorted((shared_data / "thermal_dogs_people" / "gray" / "images" / "train").glob("*.png"))[:5]
    assert paths
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert np.array_equal(decoded(png.encode(image)), image)
        colour = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image
        colour[..., 0] //= 2  # channels that differ: a swapped B and R would show
        assert np.array_equal(decoded(png.encode(colour)), colour)


def test_without_isal_opencv_encodes(monkeypatch: pytest.MonkeyPatch, simulated: dict) -> None:
    monkeypatch.setattr(png, "isal_zlib", None)
    frame = simulated["depth"][0]
    assert np.array_equal(decoded(png.encode(frame)), frame)
    assert np.array_equal(decoded(png.encode(frame[::2, ::-1])), frame[::2, ::-1])
    with pytest.raises(ValueError, match="png: cannot encode"):
        png.encode(frame.astype(np.float32))


def test_recorded_frames_replay_exactly_and_the_log_names_the_encoder(tmp_path: Path, simulated: dict) -> None:
    sensors = [{"name": "depth", "modality": "depth"}, {"name": "thermal", "modality": "thermal"}]
    clock = ManualClock()
    recorder = Recorder(RecordingConfig(path=str(tmp_path / "log.mcap")), {"name": "rig", "sensors": sensors},
                        clock, drain_s=None)
    with capture_logs() as logs:
        recorder.start()
    assert [e["png_encoder"] for e in logs if e["event"] == "record.start"] == [png.ENCODER] == ["isal"]
    for i in range(3):
        clock.set(i / 10)
        for name in ("depth", "thermal"):
            recorder.on_frame(name, Frame(name, i / 10, i, simulated[name][i]))
    asyncio.run(recorder.close())
    log = open_log(recorder.paths[0])
    for name in ("depth", "thermal"):
        for lazy in (False, True):
            frames = list(log.frames(name, lazy=lazy))
            assert len(frames) == 3
            for frame, expected in zip(frames, simulated[name], strict=True):
                assert np.array_equal(np.asarray(frame.data), expected)
