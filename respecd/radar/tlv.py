"""TI mmWave out-of-box demo packet layout: header, TLV types and payload decoders.

Pure functions over ``bytes``; the framing (magic search, lengths, resync) lives in
``parser.py``. Layouts follow TI ``mmw_output.h`` (SDK 3.x) and the SDK 2.x demo, checked
against the real captures in ``shared/data/real/ti_*`` (SENSORS.md §2.2). Little-endian.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Any, NamedTuple

import numpy as np

MAGIC = b"\x02\x01\x04\x03\x06\x05\x08\x07"  # uint16 {0x0102, 0x0304, 0x0506, 0x0708}
HEADER = struct.Struct("<8s8I")  # magic + version..subFrameNumber = 40 B
_HEADER_FIELDS = struct.Struct("<8I")
TLV_HEADER = struct.Struct("<2I")  # type, length (payload bytes only, SDK 2.x and 3.x)
SEGMENT = 32  # MMWDEMO_OUTPUT_MSG_SEGMENT_LEN: packets are padded to a multiple of this
MAX_TLVS = 32
MAX_SUBFRAME = 3  # the TI parser rejects subFrameNumber > 3

_STATS = struct.Struct("<6I")
_TEMPERATURE = struct.Struct("<iI10h")
_V2_DESCRIPTOR = struct.Struct("<2H")  # numObj, xyzQFormat
V2_POINT = np.dtype([("range_idx", "<u2"), ("doppler_idx", "<i2"), ("peak", "<u2"), ("xyz", "<i2", 3)])

STATS_FIELDS = (
    "inter_frame_processing_time_us",
    "transmit_output_time_us",  # time the UART send of the previous frame took
    "inter_frame_processing_margin_us",
    "inter_chirp_processing_margin_us",
    "active_frame_cpu_load_pct",
    "inter_frame_cpu_load_pct",
)
TEMPERATURE_SENSORS = ("rx0", "rx1", "rx2", "rx3", "tx0", "tx1", "tx2", "pm", "dig0", "dig1")


class TlvType(IntEnum):
    """``MmwDemo_output_message_type``."""

    DETECTED_POINTS = 1
    RANGE_PROFILE = 2
    NOISE_PROFILE = 3
    AZIMUTH_STATIC_HEATMAP = 4
    RANGE_DOPPLER_HEATMAP = 5
    STATS = 6
    DETECTED_POINTS_SIDE_INFO = 7
    AZIMUTH_ELEVATION_STATIC_HEATMAP = 8
    TEMPERATURE_STATS = 9
    RANGE_PROFILE_COMPLEX = 10


class Header(NamedTuple):
    """The 40-byte frame header after the magic word (a tuple: built for every packet)."""

    version: int
    total_len: int  # includes header, TLVs and padding
    platform: int
    frame_number: int
    time_cpu_cycles: int
    num_points: int
    num_tlvs: int
    subframe: int

    @classmethod
    def unpack(cls, buf: bytes | bytearray | memoryview, offset: int = 0) -> Header:
        return cls._make(_HEADER_FIELDS.unpack_from(buf, offset + 8))

    @property
    def sdk_major(self) -> int:
        return self.version >> 24

    @property
    def version_str(self) -> str:
        v = self.version
        return f"{v >> 24}.{(v >> 16) & 0xFF}.{(v >> 8) & 0xFF}.{v & 0xFF}"

    def problem(self, max_len: int) -> str | None:
        """Why this header cannot start an out-of-box packet, or None if it is plausible."""
        if self.platform >> 16 != 0xA:
            return "platform field is not 0x000Axxxx"
        if not 2 <= self.sdk_major <= 3:
            return f"unsupported SDK major version {self.sdk_major}"
        if not HEADER.size + TLV_HEADER.size * self.num_tlvs <= self.total_len <= max_len:
            return f"totalPacketLen {self.total_len} out of range"
        if self.num_tlvs > MAX_TLVS or self.subframe > MAX_SUBFRAME:
            return "numTLVs or subFrameNumber out of range"
        return None


def decode_points_v3(payload: memoryview, num_points: int) -> np.ndarray | str:
    """SDK 3.x ``DPIF_PointCloudCartesian``: float32 x, y, z (m), v (m/s) = 16 B/point."""
    if len(payload) != 16 * num_points:
        return f"points TLV is {len(payload)} B, header says {num_points} points x 16 B"
    return np.frombuffer(payload, dtype="<f4").reshape(num_points, 4)


def decode_points_v2(payload: memoryview, num_points: int) -> dict[str, np.ndarray] | str:
    """SDK 1.x/2.x detected objects: descriptor {numObj, xyzQFormat} + 12 B/object in Q format."""
    if len(payload) < _V2_DESCRIPTOR.size:
        return "points TLV shorter than its 4-byte descriptor"
    count, q_format = _V2_DESCRIPTOR.unpack_from(payload)
    if count != num_points or len(payload) != _V2_DESCRIPTOR.size + V2_POINT.itemsize * count:
        return f"SDK 2.x points TLV is {len(payload)} B for {count} objects (header says {num_points})"
    if q_format > 15:
        return f"xyzQFormat {q_format} out of range"
    objects = np.frombuffer(payload, dtype=V2_POINT, offset=_V2_DESCRIPTOR.size)
    xyz = objects["xyz"].astype(np.float32) / np.float32(1 << q_format)  # Q-format fixed point -> m
    return {"xyz": xyz, "doppler_idx": objects["doppler_idx"]}


def decode_side_info(payload: memoryview, num_points: int) -> np.ndarray | str:
    """TLV 7: int16 (N, 2) snr, noise per point, both in 0.1 dB steps (left unscaled: hot path)."""
    if len(payload) != 4 * num_points:
        return f"side-info TLV is {len(payload)} B, header says {num_points} points x 4 B"
    return np.frombuffer(payload, dtype="<i2").reshape(num_points, 2)


def decode_stats(payload: memoryview) -> dict[str, int] | str:
    """TLV 6: processing times (us) and CPU loads (%)."""
    if len(payload) != _STATS.size:
        return f"stats TLV is {len(payload)} B, expected {_STATS.size}"
    return dict(zip(STATS_FIELDS, _STATS.unpack_from(payload), strict=True))


def decode_temperature(payload: memoryview) -> dict[str, Any] | str:
    """TLV 9: tempReportValid (0 = valid) + rlRfTempData_t {time ms, 10 sensors in degC}."""
    if len(payload) != _TEMPERATURE.size:
        return f"temperature TLV is {len(payload)} B, expected {_TEMPERATURE.size}"
    valid, time_ms, *sensors = _TEMPERATURE.unpack_from(payload)
    return {"valid": valid == 0, "time_ms": time_ms, "sensors_c": dict(zip(TEMPERATURE_SENSORS, sensors, strict=True))}


def walk_tlvs(
    raw: bytes, start: int, count: int, end: int, length_includes_header: bool
) -> list[tuple[int, int, int]] | str:
    """(type, payload offset, payload length) of each TLV, or why they do not fit in ``end``."""
    out: list[tuple[int, int, int]] = []
    offset = start
    for _ in range(count):
        if offset + TLV_HEADER.size > end:
            return "TLV header runs past totalPacketLen"
        tlv_type, length = TLV_HEADER.unpack_from(raw, offset)
        if length_includes_header:
            if length < TLV_HEADER.size:
                return f"TLV {tlv_type} length {length} shorter than its header"
            length -= TLV_HEADER.size
        offset += TLV_HEADER.size
        if offset + length > end:
            return f"TLV {tlv_type} length {length} runs past totalPacketLen"
        out.append((tlv_type, offset, length))
        offset += length
    return out


def ones_complement_ok(header: bytes | bytearray | memoryview) -> bool:
    """People-counting header checksum: the 16-bit one's complement sum of the header is 0xFFFF."""
    if len(header) % 2:
        return False
    total = sum(struct.unpack(f"<{len(header) // 2}H", header))
    while total > 0xFFFF:
        total = (total & 0xFFFF) + (total >> 16)
    return total == 0xFFFF
