"""FLIR One USB frame protocol: reassemble EP 0x85 bulk reads into frames.

The camera streams frames on bulk endpoint 0x85, each a 28-byte little-endian header
(magic ``EF BE 00 00``, a type word, FrameSize, ThermalSize, JpgSize, StatusSize, and a
word that repeats when the device resends a frame) followed by the raw thermal block, the
visible-camera JPEG and a NUL-terminated JSON status. USB reads split a frame anywhere, so
``FrameAssembler.feed`` buffers bytes and frames by the header's sizes. A header whose
FrameSize its parts do not account for is refused; after a refused header or a bad magic it
scans forward to the next magic (flirone-v4l2 only reset and waited, which loses more), and a
valid header inside a pending frame's span restarts assembly there (bytes were lost), so one
damaged frame costs one frame however the reads are cut. ``damage`` counts the frames lost.

Thermal layouts, told apart by how many 164-byte VoSPI packets the camera put in the block
(SENSORS.md §3); the geometry comes from the frame, never from the profile:
  * 160x120 (One Pro / Gen 2): per image row two packets, each a 4-byte id+CRC then 80
    little-endian uint16 pixels; the right half sits 4 bytes later (flirone-v4l2);
  * 80x60 (Gen 3 / Pro LT): one packet per row; packets after row 59 are Lepton telemetry.
Every packet carries the Lepton VoSPI CRC: CRC-16/CCITT (x^16+x^12+x^5+1, init 0) over the
packet as the Lepton sends it (big-endian words) with the ID's top nibble and the CRC field
zeroed. All 63 x 20 packets of the real Gen-3 capture match it; a packet that does not is a
corrupted line (``crc_errors``), and the driver drops the frame by default.

No I/O and no numpy copies beyond the decoded images: the assembler runs in the driver's
worker thread and in ``respecd bench drivers``.
"""

from __future__ import annotations

import binascii
import json
import struct
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MAGIC = b"\xef\xbe\x00\x00"
HEADER = struct.Struct("<4s6I")  # magic, type, frame, thermal, jpeg, status, repeat-word
HEADER_SIZE = HEADER.size  # 28 bytes
MAX_FRAME_SIZE = 1 << 20  # flirone-v4l2's BUF85SIZE, "size got from android app"
# FrameSize beyond the sum of the three parts (0 in every real frame; a little room for a firmware
# that pads): a header claiming more is a damaged one, not a frame to wait for
MAX_FRAME_PADDING = 4096

LINE_BYTES = 164  # one VoSPI line: u16 id, u16 CRC, 80 x u16 pixels
LINE_WORDS = LINE_BYTES // 2
PRO_SIZE = (160, 120)  # (width, height)
GEN3_SIZE = (80, 60)
PRO_MIN_BYTES = PRO_SIZE[1] * 2 * LINE_BYTES  # 39360: two lines per 160-pixel row
GEN3_MIN_BYTES = GEN3_SIZE[1] * LINE_BYTES  # 9840
FFC_SHUTTER_STATE = "FFC"  # flirone-v4l2 checks "FFC" at status offset 17, i.e. shutterState


class ThermalLayoutError(ValueError):
    """The thermal block is too short for either known layout."""


@dataclass(frozen=True, slots=True)
class FrameHeader:
    frame_size: int
    thermal_size: int
    jpeg_size: int
    status_size: int
    kind: int
    repeat_word: int

    @classmethod
    def parse(cls, raw: bytes | bytearray | memoryview, offset: int = 0) -> FrameHeader | None:
        """The header at ``offset`` in ``raw``, or None when the magic or the sizes are wrong.

        The parts must account for the frame: FrameSize is ThermalSize + JpgSize + StatusSize
        (all 20 frames of the real capture, exactly), give or take ``MAX_FRAME_PADDING``. A
        FrameSize beyond that is refused at once instead of being waited for.
        """
        magic, kind, frame, thermal, jpeg, status, word = HEADER.unpack_from(raw, offset)
        parts = thermal + jpeg + status
        if magic != MAGIC or frame > MAX_FRAME_SIZE or not parts <= frame <= parts + MAX_FRAME_PADDING:
            return None
        return cls(frame, thermal, jpeg, status, kind, word)


@dataclass(frozen=True, slots=True)
class FlirFrame:
    """One decoded FLIR One frame."""

    header: FrameHeader
    thermal: np.ndarray  # uint16 (H, W) raw counts, little-endian decoded
    jpeg: bytes  # visible-camera JPEG as sent (may end in zero padding instead of FF D9)
    status: dict[str, Any] | None  # the JSON status, None when it did not parse
    telemetry: bytes  # thermal lines after the image (Lepton telemetry), raw
    ffc: bool  # shutter closed for a flat-field correction: the image is not the scene
    repeat: bool  # same content as the frame before (the device resends frames)
    crc_errors: int = 0  # VoSPI packets of the thermal block whose CRC failed

    @property
    def layout(self) -> tuple[int, int]:
        return (self.thermal.shape[1], self.thermal.shape[0])


@dataclass
class AssemblerStats:
    frames: int = 0
    bytes_in: int = 0
    bytes_skipped: int = 0  # discarded while hunting for a magic
    resyncs: int = 0  # times the buffer did not start with a valid header
    lost_sync: int = 0  # stretches of bytes skipped once frames were flowing (a damaged header or frame)
    truncated: int = 0  # partial frames abandoned because a new frame began inside their declared span
    bad_thermal: int = 0  # frames dropped because the thermal block fit no layout
    bad_status: int = 0  # status blocks that were not JSON
    bad_line_ids: int = 0  # 80x60 frames whose VoSPI line numbers were out of order
    bad_crc_frames: int = 0  # frames with at least one VoSPI packet whose CRC failed
    bad_crc_lines: int = 0
    repeats: int = 0
    ffc: int = 0
    layouts: dict[str, int] = field(default_factory=dict)


def crc_errors(block: bytes | memoryview, packets: int) -> int:
    """VoSPI packets among the first ``packets`` of ``block`` whose CRC does not match."""
    words = np.frombuffer(block, dtype="<u2", count=packets * LINE_WORDS).reshape(packets, LINE_WORDS)
    wire = words.astype(">u2")  # the Lepton sends big-endian words; the camera stores them little-endian
    expected = wire[:, 1].astype(np.uint16)
    wire[:, 0] &= 0x0FFF  # the ID's top nibble (segment / discard flags) is outside the CRC
    wire[:, 1] = 0
    raw = wire.tobytes()
    return sum(
        binascii.crc_hqx(raw[i * LINE_BYTES : (i + 1) * LINE_BYTES], 0) != int(expected[i]) for i in range(packets)
    )


def decode_thermal(block: bytes | memoryview) -> tuple[np.ndarray, bytes, bool, int]:
    """(image uint16 (H, W), telemetry bytes, line ids in order, CRC failures) for either layout."""
    size = len(block)
    if size >= PRO_MIN_BYTES:
        rows = np.frombuffer(block, dtype="<u2", count=PRO_MIN_BYTES // 2).reshape(PRO_SIZE[1], 2 * LINE_WORDS)
        # each row: [id, crc, 80 px | id, crc, 80 px] -> pixels x<80 at word 2+x, x>=80 at word 4+x
        image = np.hstack((rows[:, 2:LINE_WORDS], rows[:, LINE_WORDS + 2 :])).astype(np.uint16)
        return image, bytes(block[PRO_MIN_BYTES:]), True, crc_errors(block, size // LINE_BYTES)
    if size >= GEN3_MIN_BYTES:
        lines = np.frombuffer(block, dtype="<u2", count=GEN3_MIN_BYTES // 2).reshape(GEN3_SIZE[1], LINE_WORDS)
        # the low 12 bits of a VoSPI id are the line number; the top bits vary (segment/ttt)
        ordered = bool(np.array_equal(lines[:, 0] & 0x0FFF, np.arange(GEN3_SIZE[1])))
        bad = crc_errors(block, size // LINE_BYTES)
        return lines[:, 2:].astype(np.uint16), bytes(block[GEN3_MIN_BYTES:]), ordered, bad
    raise ThermalLayoutError(f"thermal block of {size} bytes fits neither 160x120 nor 80x60")


def parse_status(block: bytes | memoryview) -> dict[str, Any] | None:
    """The status JSON (NUL-terminated ASCII), or None when it is not a JSON object."""
    text = bytes(block).split(b"\x00", 1)[0]
    try:
        status = json.loads(text.decode("ascii", errors="replace"))
    except (ValueError, RecursionError):  # a deeply nested document exhausts the parser's stack
        return None
    return status if isinstance(status, dict) else None


class FrameAssembler:
    """Turns bulk reads (any split) into ``FlirFrame``s; never raises on bad bytes."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._header: FrameHeader | None = None  # checked header of the frame at the buffer's start
        self._scanned = 1  # buffer index up to which that frame's bytes hold no other valid header
        self._synced = False  # a valid header was seen: bytes skipped from now on are damage
        self._skipping = False  # inside a stretch of skipped bytes (counted once in ``lost_sync``)
        self._last: tuple[FrameHeader, bytes] | None = None
        self.stats = AssemblerStats()

    @property
    def damage(self) -> int:
        """Frames lost to bad bytes so far: cut short, skipped over, or with an unreadable thermal block."""
        s = self.stats
        return s.truncated + s.lost_sync + s.bad_thermal

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[FlirFrame]:
        """Add one USB read; return the frames it completed (usually zero or one)."""
        self.stats.bytes_in += len(chunk)
        self._buf += chunk
        frames: list[FlirFrame] = []
        while True:
            header = self._header
            if header is None:
                header = self._sync()
                if header is None:
                    return frames
                self._header, self._scanned = header, 1
            end = HEADER_SIZE + header.frame_size
            inner = self._inner_header(end)
            if inner > 0:
                # a frame starts inside this one's declared span: bytes were lost (a cut frame, or a
                # FrameSize too large); give the partial frame up now and assemble from there
                self.stats.truncated += 1
                del self._buf[:inner]
                self._header = None
                continue
            if len(self._buf) < end:
                return frames
            body = bytes(self._buf[HEADER_SIZE:end])
            del self._buf[:end]
            self._header = None
            frame = self._decode(header, body)
            if frame is not None:
                frames.append(frame)

    def _inner_header(self, end: int) -> int:
        """Where a valid header starts inside the pending frame's span (-1: none yet); scans new bytes only."""
        buf = self._buf
        complete = len(buf) >= end
        limit = min(end, len(buf))
        at = self._scanned
        while True:
            at = buf.find(MAGIC, at, limit)
            if at < 0:
                self._scanned = max(self._scanned, limit - (len(MAGIC) - 1))  # a magic may straddle the end
                return -1
            if at + HEADER_SIZE > len(buf):
                if not complete:
                    self._scanned = at  # check it once its header has arrived
                    return -1
            elif FrameHeader.parse(buf, at) is not None:
                return at
            at += 1

    def _sync(self) -> FrameHeader | None:
        """Drop bytes until the buffer starts with a valid header; None if more bytes are needed."""
        while len(self._buf) >= HEADER_SIZE:
            header = FrameHeader.parse(self._buf)
            if header is not None:
                self._synced, self._skipping = True, False
                return header
            self.stats.resyncs += 1
            at = self._buf.find(MAGIC, 1)
            skip = at if at > 0 else len(self._buf) - (len(MAGIC) - 1)  # keep a possibly split magic
            self._skip(skip)
        if self._buf and not MAGIC.startswith(bytes(self._buf[: len(MAGIC)])):
            at = self._buf.find(MAGIC, 1)
            self._skip(at if at > 0 else max(1, len(self._buf) - (len(MAGIC) - 1)))
        return None

    def _skip(self, count: int) -> None:
        self.stats.bytes_skipped += count
        if self._synced and not self._skipping:
            self.stats.lost_sync += 1  # the stream was in frames and lost them: at least one frame is gone
        self._skipping = True
        del self._buf[:count]

    def _decode(self, header: FrameHeader, body: bytes) -> FlirFrame | None:
        view = memoryview(body)
        thermal_end = header.thermal_size
        jpeg_end = thermal_end + header.jpeg_size
        try:
            image, telemetry, ordered, bad_crc = decode_thermal(view[:thermal_end])
        except ThermalLayoutError:
            self.stats.bad_thermal += 1
            return None
        status = parse_status(view[jpeg_end : jpeg_end + header.status_size])
        content = body[:jpeg_end]
        repeat = self._last is not None and self._last[0].repeat_word == header.repeat_word and self._last[1] == content
        self._last = (header, content)
        frame = FlirFrame(
            header=header,
            thermal=image,
            jpeg=body[thermal_end:jpeg_end],
            status=status,
            telemetry=telemetry,
            ffc=bool(status and status.get("shutterState") == FFC_SHUTTER_STATE),
            repeat=repeat,
            crc_errors=bad_crc,
        )
        self._count(frame, ordered, status is None)
        return frame

    def _count(self, frame: FlirFrame, ordered: bool, bad_status: bool) -> None:
        s = self.stats
        s.frames += 1
        s.bad_status += bad_status
        s.bad_line_ids += not ordered
        s.bad_crc_frames += frame.crc_errors > 0
        s.bad_crc_lines += frame.crc_errors
        s.repeats += frame.repeat
        s.ffc += frame.ffc
        key = f"{frame.layout[0]}x{frame.layout[1]}"
        s.layouts[key] = s.layouts.get(key, 0) + 1


def build_frame(
    thermal_block: bytes, jpeg: bytes, status: dict[str, Any] | bytes, *, kind: int = 1, repeat_word: int = 0
) -> bytes:
    """Encode one frame as the device sends it (for synthesized fixtures and benchmarks)."""
    status_bytes = status if isinstance(status, bytes) else json.dumps(status).encode("ascii") + b"\x00"
    size = len(thermal_block) + len(jpeg) + len(status_bytes)
    header = HEADER.pack(MAGIC, kind, size, len(thermal_block), len(jpeg), len(status_bytes), repeat_word)
    return header + thermal_block + jpeg + status_bytes


def encode_pro_thermal(image: np.ndarray, line_ids: bool = True, crc: bool = True) -> bytes:
    """The 160x120 layout of ``image`` (uint16 (120, 160)): two VoSPI packets per row.

    Packet numbers follow Lepton 3 segments (0-59 in each of 4 segments, the segment number
    in packet 20's top nibble); each packet gets its VoSPI CRC unless ``crc`` is False.
    """
    if image.shape != (PRO_SIZE[1], PRO_SIZE[0]):
        raise ValueError(f"expected a (120, 160) image, got {image.shape}")
    packets = np.zeros((2 * PRO_SIZE[1], LINE_WORDS), dtype="<u2")
    if line_ids:
        packets[:, 0] = np.arange(2 * PRO_SIZE[1]) % 60
        packets[20::60, 0] |= (np.arange(1, 5) << 12).astype(np.uint16)
    packets[0::2, 2:] = image[:, :80]
    packets[1::2, 2:] = image[:, 80:]
    if crc:
        for packet in packets:
            wire = packet.astype(">u2")
            wire[0] &= 0x0FFF
            packet[1] = binascii.crc_hqx(wire.tobytes(), 0)
    return packets.tobytes()
