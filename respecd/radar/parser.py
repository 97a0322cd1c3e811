"""Incremental parser for the TI mmWave data port (UART bytes in, packets out).

Bytes may arrive split anywhere. The parser finds the magic word, reads the header,
waits for ``totalPacketLen`` bytes (header + TLVs + padding to 32 B), checks that no other
magic word starts inside that span (bytes were lost) and that every TLV fits and has the
size its header implies, then decodes. Anything else is skipped and counted; it never
raises on bad bytes. Frame-number gaps and restarts are counted too.

Besides the out-of-box demo (SDK 2.x and 3.x, told apart by the version field) it
recognises the people-counting lab's 52-byte header (same magic, checksummed) and reports
those packets as ``ForeignPacket`` rather than misreading them.
"""

from __future__ import annotations

import dataclasses
import struct
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from respecd.messages import Frame
from respecd.radar import tlv
from respecd.radar.sequence import FrameSequence, SequenceCounts
from respecd.radar.tlv import MAGIC, Header, TlvType

DEFAULT_MAX_PACKET = 256 * 1024  # largest packet accepted: a 256x128 range-Doppler map is 64 KiB
_PPL_HEADER = struct.Struct("<8s10I2H")  # people counting: ... totalPacketLen @20, numTLVs u16, checksum u16
_PPL_HEADER_LEN = _PPL_HEADER.size  # 52
_PROBE = 24  # bytes needed to tell the two header layouts apart


@dataclass(frozen=True, slots=True)
class RadarPacket:
    """One decoded out-of-box demo frame. Bulky TLVs (profiles, heatmaps) decode on demand."""

    frame_number: int
    version: int
    platform: int
    subframe: int
    time_cpu_cycles: int
    points: np.ndarray  # float32 (N, 5): x, y, z (m, y = boresight), v (m/s), snr (dB; NaN if not sent)
    tlvs: tuple[tuple[int, int, int], ...]  # (type, payload offset in raw, payload length), packet order
    raw: bytes  # the packet's bytes, padding included (what the recorder keeps)
    offset: int  # byte offset of the magic word in the stream
    gap: int = 0  # frames missing right before this one
    side_info: np.ndarray | None = None  # int16 (N, 2) snr, noise in 0.1 dB (TLV 7)
    stats: dict[str, int] | None = None
    temperature: dict[str, Any] | None = None

    @property
    def tlv_types(self) -> tuple[int, ...]:
        return tuple(t for t, _, _ in self.tlvs)

    @property
    def version_str(self) -> str:
        return Header(self.version, 0, 0, 0, 0, 0, 0, 0).version_str

    @property
    def noise_db(self) -> np.ndarray | None:
        """Per-point noise floor (dB) from TLV 7."""
        return None if self.side_info is None else self.side_info[:, 1] * np.float32(0.1)

    def array(self, tlv_type: int) -> np.ndarray | None:
        """uint16 bins of TLV 2 (range profile, Q9), 3 (noise profile) or 5 (range-Doppler), if sent."""
        for t, start, length in self.tlvs:
            if t == tlv_type:
                return np.frombuffer(self.raw, dtype="<u2", count=length // 2, offset=start)
        return None

    def sdk2_objects(self) -> np.ndarray | None:
        """SDK 2.x only: the raw objects (range_idx, doppler_idx, peak, xyz in Q format)."""
        for t, start, length in self.tlvs:
            if t == TlvType.DETECTED_POINTS and self.version >> 24 < 3:
                return np.frombuffer(self.raw, dtype=tlv.V2_POINT, offset=start + 4, count=(length - 4) // 12)
        return None

    def to_frame(self, t: float, seq: int) -> Frame:
        """The pipeline message: data = points, meta = raw bytes and frame facts."""
        meta: dict[str, Any] = {
            "raw": self.raw,
            "frame_number": self.frame_number,
            "version": self.version_str,
            "platform": f"{self.platform:#x}",
            "subframe": self.subframe,
            "tlvs": self.tlv_types,
            "gap": self.gap,
            "stats": self.stats,
            "temperature": self.temperature,
        }
        if self.side_info is not None:
            meta["noise_db"] = self.noise_db
        return Frame(modality="radar", t=t, seq=seq, data=self.points, meta=meta)


@dataclass(frozen=True, slots=True)
class ForeignPacket:
    """A well-framed packet that is not the out-of-box demo format (people-counting lab)."""

    kind: str
    frame_number: int
    version: int
    platform: int
    tlvs: tuple[int, ...]
    raw: bytes
    offset: int
    gap: int = 0


Packet = RadarPacket | ForeignPacket


@dataclass
class ParserStats(SequenceCounts):
    """Counters over everything fed so far (frame-number ones from ``SequenceCounts``)."""

    bytes_in: int = 0
    bytes_skipped: int = 0  # garbage, partial leading frames, rejected packets
    packets: int = 0  # out-of-box packets decoded
    foreign_packets: int = 0
    bad_packets: int = 0  # magic + header found but the packet was inconsistent
    damaged_runs: int = 0  # stretches of skipped bytes (a bad packet or garbage) between good packets
    overlong_packets: int = 0  # totalPacketLen reached into the next magic word; cut there
    tlv_counts: Counter[int] = field(default_factory=Counter)
    last_error: str | None = None

    def as_dict(self) -> dict[str, Any]:
        out = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "tlv_counts"}
        out["tlv_counts"] = {str(k): v for k, v in sorted(self.tlv_counts.items())}
        return out


class MmwParser:
    """Feed UART bytes with ``feed``; get complete packets back, in order."""

    def __init__(self, max_packet: int = DEFAULT_MAX_PACKET, doppler_resolution: float = float("nan")) -> None:
        self.max_packet = max_packet
        # SDK 2.x points carry a Doppler bin index, not m/s: v = index * resolution (from the cfg)
        self.doppler_resolution = doppler_resolution
        self.stats = ParserStats()
        self._buf = bytearray()
        self._base = 0  # stream offset of _buf[0]
        self._sequences: dict[str, FrameSequence] = {}
        self._wait_until = 0  # stream offset up to which a pending packet extends
        self._scanned = 0  # stream offset up to which the pending packet holds no other magic
        self._pending: tuple[int, Header] | None = None  # (stream offset, checked header) awaiting its tail
        self._skipping = False  # inside a stretch of skipped bytes (counted once in damaged_runs)

    @property
    def pending(self) -> int:
        """Bytes buffered that are not yet a complete packet."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Append ``data`` and return every packet it completed."""
        self.stats.bytes_in += len(data)
        buf = self._buf
        buf += data
        end = self._base + len(buf)
        if end < self._wait_until:
            # inside a packet whose header was checked: only look for a magic word in the new bytes
            if buf.find(MAGIC, self._scanned - self._base) < 0:
                self._scanned = end - (len(MAGIC) - 1)
                return []
        out: list[Packet] = []
        pos = 0
        while True:
            step, packet = self._step(pos)
            if step == 0:
                break
            pos += step
            if packet is not None:
                out.append(packet)
        if pos:
            del buf[:pos]
            self._base += pos
        return out

    def _step(self, pos: int) -> tuple[int, Packet | None]:
        """Consume from ``pos``: (bytes consumed, packet or None); (0, None) = need more bytes."""
        buf = self._buf
        if buf[pos:pos + 8] != MAGIC:
            found = buf.find(MAGIC, pos)
            keep = len(buf) - (len(MAGIC) - 1) if found < 0 else found  # a magic may straddle the end
            skip = max(0, keep - pos)
            self.stats.bytes_skipped += skip
            if skip:
                self._skip_run()
            return skip, None
        if len(buf) - pos < _PROBE:
            return 0, None
        platform_at_12, = struct.unpack_from("<I", buf, pos + 12)
        if platform_at_12 >> 16 == 0xA:  # people-counting layout: platform where totalPacketLen would be
            return self._foreign(pos)
        return self._oob(pos)

    def _reject(self, why: str) -> tuple[int, None]:
        """Drop the magic word we stood on; the next step searches for the next one."""
        self.stats.bad_packets += 1
        self.stats.last_error = why
        self.stats.bytes_skipped += 1
        self._skip_run()
        return 1, None

    def _skip_run(self) -> None:
        if not self._skipping:
            self._skipping = True
            self.stats.damaged_runs += 1

    def _span(self, pos: int, total: int) -> bytes | None | str:
        """The packet's bytes once all have arrived; a string if another magic starts inside."""
        buf = self._buf
        # a magic word inside the span means bytes were lost: give up now, not when
        # a (possibly corrupted, huge) totalPacketLen has finally arrived
        inner = buf.find(MAGIC, pos + 1, pos + total)
        if inner >= 0:
            return f"next magic word {inner - pos} B into a {total}-B packet (bytes lost)"
        if len(buf) - pos < total:
            self._wait_until = self._base + pos + total
            self._scanned = self._base + max(pos + 1, len(buf) - len(MAGIC) + 1)
            return None
        return bytes(buf[pos:pos + total])

    def _oob(self, pos: int) -> tuple[int, Packet | None]:
        if len(self._buf) - pos < tlv.HEADER.size:
            return 0, None
        at = self._base + pos
        if self._pending is not None and self._pending[0] == at:
            header = self._pending[1]  # checked when it arrived; now the whole packet is here
        else:
            header = Header.unpack(self._buf, pos)
            problem = header.problem(self.max_packet)
            if problem:
                return self._reject(problem)
            self._pending = (at, header)
        raw = self._span(pos, header.total_len)
        if raw is None:
            return 0, None
        if isinstance(raw, str):
            return self._reject(raw)
        packet = decode_oob(raw, header, self._base + pos, self.doppler_resolution)
        if isinstance(packet, str):
            return self._reject(packet)
        gap = self._track("oob", header.frame_number)
        self.stats.packets += 1
        self._skipping = False
        counts = self.stats.tlv_counts
        for tlv_type, _, _ in packet.tlvs:
            counts[tlv_type] += 1
        size = self._trim(raw, _tlv_end(packet.tlvs, tlv.HEADER.size))
        if size != len(raw) or gap:
            packet = dataclasses.replace(packet, raw=raw[:size], gap=gap)
        return size, packet

    def _foreign(self, pos: int) -> tuple[int, Packet | None]:
        buf = self._buf
        if len(buf) - pos < _PPL_HEADER_LEN:
            return 0, None
        fields = _PPL_HEADER.unpack_from(buf, pos)
        version, platform, total, frame_number, num_tlvs = fields[1], fields[2], fields[4], fields[5], fields[11]
        header_ok = tlv.ones_complement_ok(buf[pos:pos + _PPL_HEADER_LEN])
        if not header_ok or not _PPL_HEADER_LEN <= total <= self.max_packet:
            return self._reject("people-counting header with a bad checksum or length")
        raw = self._span(pos, total)
        if raw is None:
            return 0, None
        if isinstance(raw, str):
            return self._reject(raw)
        walked = tlv.walk_tlvs(raw, _PPL_HEADER_LEN, num_tlvs, total, length_includes_header=True)
        if isinstance(walked, str):
            return self._reject(walked)
        gap = self._track("pplcount", frame_number)
        self.stats.foreign_packets += 1
        self._skipping = False
        types = tuple(t for t, _, _ in walked)
        size = self._trim(raw, _tlv_end(walked, _PPL_HEADER_LEN))
        offset = self._base + pos
        return size, ForeignPacket("pplcount", frame_number, version, platform, types, raw[:size], offset, gap)

    def _trim(self, raw: bytes, tlv_end: int) -> int:
        """Bytes the packet really spans: an overstated totalPacketLen (1-7 B) ends inside the next
        magic word, whose first bytes then sit in the padding; give them back to the next packet."""
        for k in range(min(len(MAGIC) - 1, len(raw) - tlv_end), 0, -1):
            if raw.endswith(MAGIC[:k]):
                self.stats.overlong_packets += 1
                return len(raw) - k
        return len(raw)

    def _track(self, kind: str, frame_number: int) -> int:
        """Frames found missing as of this packet (see ``respecd.radar.sequence``)."""
        sequence = self._sequences.get(kind)
        if sequence is None:
            sequence = self._sequences[kind] = FrameSequence(self.stats)
        return sequence.advance(frame_number)


def _tlv_end(walked: tuple[tuple[int, int, int], ...] | list[tuple[int, int, int]], header_len: int) -> int:
    """Offset just past the last TLV's payload (where the padding begins)."""
    return walked[-1][1] + walked[-1][2] if walked else header_len


def decode_oob(
    raw: bytes, header: Header, offset: int = 0, doppler_resolution: float = float("nan")
) -> RadarPacket | str:
    """Decode one complete out-of-box packet, or say why it is inconsistent.

    This is the hot path (> 100x the 921600-baud budget): plain branches, few numpy calls.
    """
    walked = tlv.walk_tlvs(raw, tlv.HEADER.size, header.num_tlvs, header.total_len, length_includes_header=False)
    if isinstance(walked, str):
        return walked
    end = _tlv_end(walked, tlv.HEADER.size)
    if header.total_len - end >= tlv.SEGMENT:
        return f"{header.total_len - end} B after the last TLV (padding is < {tlv.SEGMENT})"
    view = memoryview(raw)
    n, v3 = header.num_points, header.sdk_major >= 3
    points: Any = None  # each a decoded TLV (an error string returns above)
    side: Any = None
    stats: Any = None
    temperature: Any = None
    for tlv_type, start, length in walked:  # plain branches: this loop runs for every packet
        payload = view[start:start + length]
        result: Any = None
        if tlv_type == _POINTS:
            result = points = tlv.decode_points_v3(payload, n) if v3 else tlv.decode_points_v2(payload, n)
        elif tlv_type == _SIDE_INFO:
            result = side = tlv.decode_side_info(payload, n)
        elif tlv_type == _STATS:
            result = stats = tlv.decode_stats(payload)
        elif tlv_type == _TEMPERATURE:
            result = temperature = tlv.decode_temperature(payload)
        elif tlv_type in _U16_ARRAYS and length % 2:
            result = f"uint16 array TLV {tlv_type} has odd length {length}"
        if isinstance(result, str):
            return result
        # types 4, 8, 10 and unknown ones: listed in ``tlvs``, payload skipped by length
    return RadarPacket(
        frame_number=header.frame_number,
        version=header.version,
        platform=header.platform,
        subframe=header.subframe,
        time_cpu_cycles=header.time_cpu_cycles,
        points=_points(points, side, n, v3, doppler_resolution),
        tlvs=tuple(walked),
        raw=raw,
        offset=offset,
        side_info=side,
        stats=stats,
        temperature=temperature,
    )


_POINTS, _SIDE_INFO = int(TlvType.DETECTED_POINTS), int(TlvType.DETECTED_POINTS_SIDE_INFO)
_STATS, _TEMPERATURE = int(TlvType.STATS), int(TlvType.TEMPERATURE_STATS)
_U16_ARRAYS = {int(TlvType.RANGE_PROFILE), int(TlvType.NOISE_PROFILE), int(TlvType.RANGE_DOPPLER_HEATMAP)}


def _points(decoded: Any, side: np.ndarray | None, n: int, v3: bool, doppler_resolution: float) -> np.ndarray:
    """Assemble float32 (N, 5) x, y, z, v, snr from whichever point TLVs the packet had."""
    points = np.empty((n if decoded is not None else 0, 5), dtype=np.float32)
    if decoded is None:
        return points  # header counted points but no points TLV was sent (guiMonitor off)
    if v3:
        points[:, :4] = decoded
    else:
        points[:, :3] = decoded["xyz"]
        points[:, 3] = decoded["doppler_idx"] * np.float32(doppler_resolution)  # bin index -> m/s
    if side is None:
        points[:, 4] = np.nan
    else:
        points[:, 4] = side[:, 0]
        points[:, 4] *= np.float32(0.1)  # 0.1 dB steps -> dB
    return points
