"""Walk an MCAP file record by record, trusting nothing: every chunk's CRC is checked, a
damaged chunk is skipped and reported with its byte range, and after a damaged record
header the walk finds the next intact chunk instead of stopping.

The ``mcap`` library's stream reader stops at the first bad byte (ZstdError,
OverflowError...) and by default never checks chunk CRCs, so one flipped byte either ended
a replay with a traceback or silently altered a message. Here a chunk is only believed
when it decompresses to its recorded size and CRC-32; everything the format does not
protect by a CRC (record headers, metadata) is checked for consistency instead.
"""

from __future__ import annotations

import io
import mmap
import struct
import zlib
from collections.abc import Generator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lz4.frame
import zstandard
from mcap import records as rec
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Chunk, DataEnd, Footer, McapRecord, Message

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")  # opcode, length
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_FOOTER_LEN = 1 + 8 + 20
MAX_INFLATION = 1024  # a chunk claiming more than this x its compressed size is damaged
_COMPRESSIONS = ("", "zstd", "lz4")
_READERS: dict[int, Any] = {
    Opcode.HEADER: rec.Header, Opcode.FOOTER: Footer, Opcode.SCHEMA: rec.Schema, Opcode.CHANNEL: rec.Channel,
    Opcode.MESSAGE: Message, Opcode.CHUNK: Chunk, Opcode.MESSAGE_INDEX: rec.MessageIndex,
    Opcode.CHUNK_INDEX: rec.ChunkIndex,
    Opcode.ATTACHMENT: rec.Attachment, Opcode.ATTACHMENT_INDEX: rec.AttachmentIndex,
    Opcode.STATISTICS: rec.Statistics, Opcode.METADATA: rec.Metadata, Opcode.METADATA_INDEX: rec.MetadataIndex,
    Opcode.SUMMARY_OFFSET: rec.SummaryOffset, Opcode.DATA_END: DataEnd,
}
# what bytes that are not a record raise while being parsed as one
BAD_BYTES = (McapError, struct.error, UnicodeDecodeError, ValueError, EOFError, OverflowError, MemoryError,
              zstandard.ZstdError, RuntimeError, IndexError, KeyError)


@dataclass(frozen=True)
class Damage:
    """Bytes ``start``..``end`` (end exclusive) of the file could not be read."""

    start: int
    end: int
    reason: str

    def describe(self) -> str:
        return f"bytes {self.start}-{self.end} ({self.end - self.start} B): {self.reason}"


@dataclass(frozen=True)
class Cut:
    """The file ends inside a record that starts at ``offset`` (a power cut, a full disk)."""

    offset: int


class _Bad(Exception):
    """Bytes that are not what they claim to be; the message says why."""


class _Strict(io.BytesIO):
    def read(self, n: int | None = -1) -> bytes:
        data = super().read(n)
        if n is not None and n > 0 and len(data) < n:
            raise _Bad(f"a field runs {n - len(data)} B past its record")
        return data


def walk(path: Path, stop_at_data_end: bool = True, verify: bool = False) -> Iterator[McapRecord | Damage | Cut]:
    """Records in file order (a chunk's records in place of the chunk), ``Damage`` for each
    unreadable stretch and a final ``Cut`` if the file ends inside a record. ``verify`` also
    checks the data section's CRC (damage outside the chunks: header, metadata, indexes)."""
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        yield from _Walk(mm, verify).records(stop_at_data_end)


class _Walk:
    def __init__(self, mm: mmap.mmap, verify: bool) -> None:
        self.mm = mm
        self.verify = verify
        self.damaged = False
        self.finished = bytes(mm[-len(MAGIC):]) == MAGIC  # a footer's magic: the file was not cut

    def records(self, stop_at_data_end: bool) -> Iterator[McapRecord | Damage | Cut]:
        mm, size, pos = self.mm, len(self.mm), len(MAGIC)
        while pos < size:
            if size - pos < _RECORD_HEAD.size:
                yield from self._cut_or_damage(pos, "the file ends inside a record header")
                return
            opcode, length = _RECORD_HEAD.unpack_from(mm, pos)
            end = pos + _RECORD_HEAD.size + length
            try:
                if end > size:
                    raise _Bad(f"record of {length} B runs past the end of the file")
                records = _read_at(mm, opcode, pos, end)
            except (_Bad, *BAD_BYTES) as err:
                resume = yield from self._damaged(pos, end, opcode, err)
                if resume is None:
                    return
                pos = resume
                continue
            if isinstance(records[-1], DataEnd) and self.verify:
                yield from self._check_data_section(pos, records[-1])
            yield from records
            if isinstance(records[-1], Footer) or (stop_at_data_end and isinstance(records[-1], DataEnd)):
                return
            pos = end
        yield from self._cut_or_damage(pos, "the file ends without a data-end record")  # cut between records

    def _damaged(self, pos: int, end: int, opcode: int,
                 err: BaseException) -> Generator[Damage | Cut, None, int | None]:
        """Report the bad stretch; return where reading goes on (None: nowhere)."""
        self.damaged = True
        if opcode == Opcode.CHUNK and _plausible_chunk(self.mm, pos, len(self.mm)):
            yield Damage(pos, end, f"chunk skipped: {err}")  # its framing is intact: skip just this chunk
            return end
        if opcode in _READERS and _record_follows(self.mm, end):  # a bad body in an intact frame
            yield Damage(pos, end, f"record skipped ({err})")
            return end
        resume = _next_chunk(self.mm, pos + 1)
        if resume is None and end > len(self.mm):
            yield from self._cut_or_damage(pos, str(err))
            return None
        yield Damage(pos, resume or len(self.mm), f"not a valid record ({err})")
        return resume

    def _cut_or_damage(self, pos: int, reason: str) -> Iterator[Damage | Cut]:
        if self.finished:  # the footer is there, so the file was not cut short: a length is wrong
            self.damaged = True
            yield Damage(pos, len(self.mm), reason)
        else:
            yield Cut(pos)

    def _check_data_section(self, pos: int, data_end: DataEnd) -> Iterator[Damage]:
        crc = data_end.data_section_crc
        if crc and not self.damaged and zlib.crc32(self.mm[:pos]) != crc:
            self.damaged = True
            yield Damage(0, pos, "data section CRC mismatch: damage outside the chunks (header, metadata or index)")


def _read_at(mm: mmap.mmap, opcode: int, pos: int, end: int) -> list[McapRecord]:
    """The record at ``pos`` (a chunk: its records). A chunk is parsed in place, without
    copying its compressed bytes; only bytes objects leave (the mmap can then be closed)."""
    if opcode != Opcode.CHUNK:
        return [_read(opcode, mm[pos + _RECORD_HEAD.size:end])]
    with memoryview(mm) as view, view[pos + _RECORD_HEAD.size:end] as body:
        return chunk_records(_chunk(body))


def _read(opcode: int, body: bytes) -> McapRecord:
    reader = _READERS.get(opcode)
    if reader is None:
        raise _Bad(f"unknown record type {opcode:#04x}")  # respecd writes none: it is a flipped opcode
    stream = ReadDataStream(_Strict(body))
    return reader.read(stream, len(body)) if reader is Message else reader.read(stream)


def _chunk(body: memoryview) -> Chunk:
    start, end, uncompressed_size, crc, name_len = _CHUNK_HEAD.unpack_from(body, 0)
    at = _CHUNK_HEAD.size + name_len
    compression = bytes(body[_CHUNK_HEAD.size:at]).decode()
    data_len, = struct.unpack_from("<Q", body, at)
    if at + 8 + data_len != len(body):
        raise _Bad(f"chunk data of {data_len} B does not fill its {len(body)}-B record")
    return Chunk(compression=compression, data=body[at + 8:], message_end_time=end,  # type: ignore[arg-type]
                 message_start_time=start, uncompressed_crc=crc, uncompressed_size=uncompressed_size)


def chunk_records(chunk: Chunk) -> list[McapRecord]:
    """The schema, channel and message records of a chunk whose size and CRC check out."""
    if chunk.compression not in _COMPRESSIONS:
        raise _Bad(f"unknown compression {chunk.compression!r}")
    if chunk.uncompressed_size > MAX_INFLATION * len(chunk.data) + (1 << 20):
        raise _Bad(f"claims {chunk.uncompressed_size} B uncompressed from {len(chunk.data)} B")
    data = _decompress(chunk)
    if len(data) != chunk.uncompressed_size:
        raise _Bad(f"decompressed to {len(data)} B, expected {chunk.uncompressed_size}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise _Bad("CRC mismatch")
    out: list[McapRecord] = []
    pos, size = 0, len(data)
    while pos < size:
        opcode, length = _RECORD_HEAD.unpack_from(data, pos)
        start, pos = pos + _RECORD_HEAD.size, pos + _RECORD_HEAD.size + length
        if pos > size:
            raise _Bad("a record runs past the end of its chunk")
        if opcode == Opcode.MESSAGE:  # the hot path: parsed here, one copy of the payload
            if length < _MESSAGE_HEAD.size:
                raise _Bad(f"message record of {length} B")
            channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(data, start)
            out.append(Message(channel_id=channel_id, log_time=log_time, publish_time=publish_time,
                               sequence=sequence, data=bytes(data[start + _MESSAGE_HEAD.size:pos])))
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
            out.append(_read(opcode, bytes(data[start:pos])))
    return out


def _decompress(chunk: Chunk) -> bytes | memoryview:
    if chunk.compression == "zstd":
        # a decompressor per chunk: one object may not be shared by the replay's reader threads
        return zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    if chunk.compression == "lz4":
        return lz4.frame.decompress(chunk.data)
    return chunk.data


def _next_chunk(mm: mmap.mmap, start: int) -> int | None:
    """Offset of the next chunk record at or after ``start`` whose contents check out."""
    size, at = len(mm), start
    while (at := mm.find(bytes([Opcode.CHUNK]), at)) >= 0:
        if _plausible_chunk(mm, at, size):
            try:
                _read_at(mm, Opcode.CHUNK, at, at + _RECORD_HEAD.size + _length(mm, at))
                return at
            except (_Bad, *BAD_BYTES):
                pass
        at += 1
    return None


def _record_follows(mm: mmap.mmap, at: int) -> bool:
    """A known record header at ``at`` whose length fits the file: the frame before it was intact."""
    if at + _RECORD_HEAD.size > len(mm):
        return False
    opcode, length = _RECORD_HEAD.unpack_from(mm, at)
    return opcode in _READERS and at + _RECORD_HEAD.size + length <= len(mm)


def _length(mm: mmap.mmap, at: int) -> int:
    return int(_RECORD_HEAD.unpack_from(mm, at)[1])


def _plausible_chunk(mm: mmap.mmap, at: int, size: int) -> bool:
    """A cheap filter before a full parse: the chunk header's lengths agree with each other."""
    head = at + _RECORD_HEAD.size
    if head + _CHUNK_HEAD.size > size:
        return False
    length = _length(mm, at)
    *_, compression_len = _CHUNK_HEAD.unpack_from(mm, head)
    if compression_len > 4 or head + _CHUNK_HEAD.size + compression_len + 8 > size:
        return False
    name_at = head + _CHUNK_HEAD.size
    if bytes(mm[name_at:name_at + compression_len]).decode("ascii", "replace") not in _COMPRESSIONS:
        return False
    data_len, = struct.unpack_from("<Q", mm, name_at + compression_len)
    if data_len != length - (_CHUNK_HEAD.size + compression_len + 8):
        return False
    return head + length <= size


def check_summary(mm: mmap.mmap | bytes) -> tuple[bool | None, int, int]:
    """The summary section against the footer's CRC: (True intact / False damaged / None not
    checkable, its start, its end)."""
    size = len(mm)
    footer_at = size - len(MAGIC) - _FOOTER_LEN
    if footer_at < len(MAGIC) or bytes(mm[size - len(MAGIC):]) != MAGIC or mm[footer_at] != Opcode.FOOTER:
        return None, 0, 0
    summary_start, _, crc = struct.unpack_from("<QQI", mm, footer_at + _RECORD_HEAD.size)
    if crc == 0 or summary_start == 0:
        return None, 0, 0
    if not len(MAGIC) <= summary_start <= footer_at:
        return False, footer_at, size
    return zlib.crc32(mm[summary_start:footer_at + _RECORD_HEAD.size + 16]) == crc, summary_start, size
