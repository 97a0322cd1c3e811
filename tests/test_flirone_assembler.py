"""FLIR One frame assembler on the real Gen-3 capture (109 EP 0x85 reads, 20 frames) and on
synthesized 160x120 frames, checked against the flirone-v4l2 pixel formula."""

from __future__ import annotations

import random
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from respecd.drivers.flirone_protocol import (
    HEADER_SIZE,
    MAX_FRAME_PADDING,
    FrameAssembler,
    FrameHeader,
    build_frame,
    encode_pro_thermal,
)
from respecd.drivers.flirone_usb import RecordedTransport

CAPTURE = "flirone_pro_gen3_usb_moezemara"


@pytest.fixture
def capture(shared_data: Path) -> Path:
    return shared_data / CAPTURE


@pytest.fixture
def chunks(capture: Path) -> list[bytes]:
    return RecordedTransport.from_path(capture / "test_chunks_hex").chunks


def feed_all(chunks: list[bytes]) -> tuple[list, FrameAssembler]:
    assembler = FrameAssembler()
    frames = []
    for chunk in chunks:
        frames.extend(assembler.feed(chunk))
    return frames, assembler


def headers_in(stream: bytes) -> list[tuple[int, ...]]:
    """Walk the concatenated capture by FrameSize, independently of the assembler."""
    out, at = [], 0
    while at < len(stream):
        fields = struct.unpack_from("<4s6I", stream, at)
        assert fields[0] == b"\xef\xbe\x00\x00"
        out.append(fields[2:6])
        at += HEADER_SIZE + fields[2]
    return out


def test_real_capture_gives_its_20_frames(chunks: list[bytes], capture: Path) -> None:
    assert len(chunks) == 108  # 109 reads, the first one empty
    frames, assembler = feed_all(chunks)
    stream = (capture / "usb_stream_concat.bin").read_bytes()
    expected = headers_in(stream)
    assert len(frames) == len(expected) == 20
    for frame, (size, thermal, jpeg, status) in zip(frames, expected, strict=True):
        h = frame.header
        assert (h.frame_size, h.thermal_size, h.jpeg_size, h.status_size) == (size, thermal, jpeg, status)
        assert frame.thermal.shape == (60, 80) and frame.thermal.dtype == np.uint16
        assert 3000 <= frame.thermal.min() and frame.thermal.max() < 1 << 14  # 14-bit Lepton counts
        assert 3500 <= np.median(frame.thermal) <= 4100  # a room-temperature scene, not telemetry words
        assert frame.status is not None and frame.status["shutterState"] == "ON"
        assert not frame.ffc
    s = assembler.stats
    assert (s.frames, s.resyncs, s.bytes_skipped, s.truncated, s.bad_line_ids) == (20, 0, 0, 0, 0)
    assert [i for i, f in enumerate(frames) if f.repeat] == [1, 11]  # the device resent frames 0 and 10
    assert s.layouts == {"80x60": 20}


def test_real_capture_jpegs_decode(chunks: list[bytes]) -> None:
    frames, _ = feed_all(chunks)
    for frame in frames[:4]:
        image = cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert image is not None and image.shape == (1080, 1440, 3)


def test_gen3_pixels_match_the_line_layout(chunks: list[bytes], capture: Path) -> None:
    frames, _ = feed_all(chunks)
    raw = (capture / "usb_stream_concat.bin").read_bytes()
    # SOURCE.md: 63 lines of 164 bytes = u16 id, u16 CRC, 80 x u16 LE; rows 0-59 are the image
    for y in (0, 17, 59):
        line = raw[HEADER_SIZE + 164 * y : HEADER_SIZE + 164 * (y + 1)]
        assert struct.unpack_from("<H", line)[0] & 0x0FFF == y
        assert list(frames[0].thermal[y]) == list(struct.unpack_from("<80H", line, 4))
    assert len(frames[0].telemetry) == 3 * 164


def test_whole_stream_and_random_splits_give_the_same_frames(chunks: list[bytes], capture: Path) -> None:
    reference, _ = feed_all(chunks)
    stream = (capture / "usb_stream_concat.bin").read_bytes()
    whole, _ = feed_all([stream])
    rng = random.Random(5)
    pieces, at = [], 0
    while at < len(stream):
        step = rng.choice((1, 3, 27, 29, 500, 4096, 40000))
        pieces.append(stream[at : at + step])
        at += step
    split, assembler = feed_all(pieces)
    for frames in (whole, split):
        assert len(frames) == 20
        for a, b in zip(frames, reference, strict=True):
            assert np.array_equal(a.thermal, b.thermal) and a.jpeg == b.jpeg and a.status == b.status
    assert assembler.stats.bytes_skipped == 0


def test_split_header_is_reassembled(chunks: list[bytes]) -> None:
    split: list[bytes] = []
    for i, chunk in enumerate(chunks):
        if len(chunk) == HEADER_SIZE:
            cut = 1 + i % 27  # every position inside the 28-byte header, the magic included
            split += [chunk[:cut], chunk[cut:]]
        else:
            split.append(chunk)
    frames, assembler = feed_all(split)
    assert len(frames) == 20
    assert assembler.stats.resyncs == 0


def test_bad_magic_loses_one_frame_and_resyncs(chunks: list[bytes]) -> None:
    headers = [i for i, c in enumerate(chunks) if len(c) == HEADER_SIZE]
    damaged = list(chunks)
    damaged[headers[5]] = b"\xde\xad\xbe\xef" + chunks[headers[5]][4:]
    frames, assembler = feed_all(damaged)
    reference, _ = feed_all(chunks)
    assert len(frames) == 19
    assert assembler.stats.resyncs >= 1 and assembler.stats.bytes_skipped > 0
    kept = reference[:5] + reference[6:]
    assert all(np.array_equal(a.thermal, b.thermal) for a, b in zip(frames, kept, strict=True))


def test_garbage_between_frames_is_skipped(chunks: list[bytes]) -> None:
    headers = [i for i, c in enumerate(chunks) if len(c) == HEADER_SIZE]
    garbage = bytes(range(256)) * 3 + b"\xef\xbe"  # ends in half a magic
    noisy = chunks[: headers[3]] + [garbage] + chunks[headers[3] :]
    frames, assembler = feed_all(noisy)
    assert len(frames) == 20
    assert assembler.stats.bytes_skipped == len(garbage)


def test_lost_read_drops_only_that_frame(chunks: list[bytes]) -> None:
    big = [i for i, c in enumerate(chunks) if len(c) == 32768]
    frames, assembler = feed_all(chunks[: big[4]] + chunks[big[4] + 1 :])
    assert len(frames) == 19
    assert assembler.stats.truncated == 1


def pro_image() -> np.ndarray:
    y, x = np.mgrid[0:120, 0:160]
    return (3000 + 7 * y + x + 500 * (x >= 80)).astype(np.uint16)


def test_pro_layout_decodes_from_a_synthesized_frame() -> None:
    image = pro_image()
    ok, jpeg = cv2.imencode(".jpg", np.full((480, 640, 3), 90, np.uint8))
    assert ok
    raw = build_frame(encode_pro_thermal(image), jpeg.tobytes(), {"shutterState": "FFC", "ffcState": "x"})
    (frame,) = FrameAssembler().feed(raw)
    assert frame.layout == (160, 120)
    assert np.array_equal(frame.thermal, image)
    assert frame.ffc
    # flirone-v4l2: pos = 2*(y*164 + x) + 32, 4 bytes further when x >= 80, over the whole buffer
    for y, x in ((0, 0), (5, 79), (5, 80), (119, 159), (60, 100)):
        pos = 2 * (y * 164 + x) + 32 + (4 if x >= 80 else 0)
        assert frame.thermal[y, x] == raw[pos] + 256 * raw[pos + 1]
    assert cv2.imdecode(np.frombuffer(frame.jpeg, np.uint8), cv2.IMREAD_COLOR).shape == (480, 640, 3)


def test_short_thermal_block_and_bad_status_are_counted() -> None:
    good = build_frame(encode_pro_thermal(pro_image()), b"\xff\xd8\xff\xd9", b"not json\x00")
    short = build_frame(b"\x00" * 1000, b"\xff\xd8\xff\xd9", {"shutterState": "ON"})
    assembler = FrameAssembler()
    frames = assembler.feed(short) + assembler.feed(good)
    assert len(frames) == 1 and frames[0].status is None
    assert assembler.stats.bad_thermal == 1 and assembler.stats.bad_status == 1


def test_oversized_header_is_rejected_not_buffered() -> None:
    bogus = struct.pack("<4s6I", b"\xef\xbe\x00\x00", 1, 50_000_000, 10, 10, 10, 0)
    good = build_frame(encode_pro_thermal(pro_image()), b"\xff\xd8", {"shutterState": "ON"})
    assembler = FrameAssembler()
    frames = assembler.feed(bogus + b"\x00" * 100) + assembler.feed(good)
    assert len(frames) == 1
    assert assembler.stats.resyncs >= 1


def test_every_real_line_carries_a_valid_vospi_crc(chunks: list[bytes]) -> None:
    """CRC-16/CCITT over the big-endian packet, ID nibble and CRC field zeroed: 63 x 20 packets match."""
    frames, assembler = feed_all(chunks)
    assert [f.crc_errors for f in frames] == [0] * 20 and assembler.stats.bad_crc_lines == 0
    header = next(i for i, c in enumerate(chunks) if len(c) == HEADER_SIZE)
    thermal = bytearray(chunks[header + 1])  # the read after a header is that frame's thermal block
    thermal[164 * 17 + 4 + 2 * 40] ^= 0x01  # one bit of one pixel of row 17
    damaged = chunks[: header + 1] + [bytes(thermal)] + chunks[header + 2 :]
    frames, assembler = feed_all(damaged)
    assert sum(f.crc_errors for f in frames) == 1 and assembler.stats.bad_crc_frames == 1


def test_synthesized_pro_frames_carry_valid_crcs_and_a_bad_one_is_caught() -> None:
    block = encode_pro_thermal(pro_image())
    (frame,) = FrameAssembler().feed(build_frame(block, b"\xff\xd8", {"shutterState": "ON"}))
    assert frame.layout == (160, 120) and frame.crc_errors == 0
    (frame,) = FrameAssembler().feed(build_frame(encode_pro_thermal(pro_image(), crc=False), b"\xff\xd8", {}))
    assert frame.crc_errors == 240  # every packet of a block whose CRC fields are empty


def test_geometry_comes_from_the_frame_not_a_constant(chunks: list[bytes]) -> None:
    gen3, _ = feed_all(chunks)
    (pro,) = FrameAssembler().feed(build_frame(encode_pro_thermal(pro_image()), b"\xff\xd8", {}))
    assert gen3[0].layout == (80, 60) and pro.layout == (160, 120)  # one assembler API, no sensor setting


def test_deeply_nested_status_json_is_a_bad_status_not_a_crash() -> None:
    """A status of 100,000 '[' raised RecursionError out of the assembler (issue 17, item 7)."""
    nested = build_frame(encode_pro_thermal(pro_image()), b"\xff\xd8", b"[" * 100_000 + b"\x00")
    assembler = FrameAssembler()
    (frame,) = assembler.feed(nested)
    assert frame.status is None and assembler.stats.bad_status == 1


def frame_starts(stream: bytes) -> list[int]:
    return [i for i in range(len(stream)) if stream.startswith(b"\xef\xbe\x00\x00", i)]


def split(stream: bytes, size: int) -> list[bytes]:
    return [stream[i : i + size] for i in range(0, len(stream), size)]


@pytest.mark.parametrize("read_size", [32768, 5000, 777])
def test_overstated_frame_size_costs_one_frame_with_misaligned_reads(capture: Path, read_size: int) -> None:
    # reads that do not line up with frames (as RecordedTransport.from_path cuts a .bin): a FrameSize of
    # 900000 in frame 5 used to swallow the frames after it until a read happened to begin with a header
    stream = bytearray((capture / "usb_stream_concat.bin").read_bytes())
    struct.pack_into("<I", stream, frame_starts(bytes(stream))[5] + 8, 900_000)
    frames, assembler = feed_all(split(bytes(stream), read_size))
    reference, _ = feed_all(split((capture / "usb_stream_concat.bin").read_bytes(), read_size))
    assert len(reference) == 20 and len(frames) == 19
    kept = reference[:5] + reference[6:]
    assert all(np.array_equal(a.thermal, b.thermal) for a, b in zip(frames, kept, strict=True))
    assert assembler.damage == 1 and assembler.stats.lost_sync == 1


@pytest.mark.parametrize("read_size", [32768, 5000])
def test_cut_frame_costs_one_frame_with_misaligned_reads(capture: Path, read_size: int) -> None:
    stream = (capture / "usb_stream_concat.bin").read_bytes()
    at = frame_starts(stream)[5]
    cut = stream[: at + 30_000] + stream[at + 50_000 :]  # 20 kB of frame 5's JPEG lost
    frames, assembler = feed_all(split(cut, read_size))
    assert len(frames) == 19
    assert assembler.stats.truncated == 1 and assembler.damage == 1 and assembler.stats.bytes_skipped == 0


def test_frame_size_must_match_its_parts() -> None:
    good = build_frame(encode_pro_thermal(pro_image()), b"\xff\xd8", {"shutterState": "ON"})
    assert FrameHeader.parse(good) is not None
    padded = bytearray(good)
    struct.pack_into("<I", padded, 8, len(good) - HEADER_SIZE + MAX_FRAME_PADDING)
    assert FrameHeader.parse(padded) is not None  # a little padding is tolerated
    struct.pack_into("<I", padded, 8, len(good) - HEADER_SIZE + MAX_FRAME_PADDING + 1)
    assert FrameHeader.parse(padded) is None


def test_real_frames_declare_exactly_their_parts(capture: Path) -> None:
    headers = headers_in((capture / "usb_stream_concat.bin").read_bytes())
    assert len(headers) == 20 and all(frame == thermal + jpeg + status for frame, thermal, jpeg, status in headers)


def test_garbage_before_the_first_frame_is_not_damage(chunks: list[bytes]) -> None:
    frames, assembler = feed_all([b"\x01" * 5000, *chunks])
    assert len(frames) == 20 and assembler.stats.bytes_skipped == 5000 and assembler.damage == 0
