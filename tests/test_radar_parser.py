"""The data-port parser against real TI captures: whole, byte by byte, split, corrupted."""

from __future__ import annotations

import random
import struct
from pathlib import Path

import numpy as np
import pytest

from respecd.radar.parser import ForeignPacket, MmwParser, RadarPacket
from respecd.radar.tlv import MAGIC

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
SDK2 = REAL / "ti_awr1642_oob_piatek" / "xwr16xx_processed_stream_2023_10_30T09_00_44_253.dat"
SDK36 = REAL / "ti_awr1642_oob_piatek" / "AWR1642_test_data_SDK_3_6_0.dat"
SDK33 = REAL / "ti_iwr6843_oob_automated_doors" / "xwr68xx_processed_stream_2019_12_04T21_44_51_663.dat"
PPLCOUNT = REAL / "ti_iwr6843aop_pplcount_niek" / "data.bin"

# (capture, first frame, complete frames, leading partial bytes, SDK major) from the SOURCE.md files
CAPTURES = [(SDK2, 167, 99, 216, 2), (SDK36, 69, 100, 376, 3), (SDK33, 209, 101, 0, 3)]


def _read(path: Path) -> bytes:
    if not path.exists():
        pytest.skip(f"shared capture {path} absent (CI clones shared/ beside the repo)")
    return path.read_bytes()


def _reference_frames(data: bytes) -> list[tuple[int, int, bytes]]:
    """(offset, frame number, bytes) by the simplest walk: magic, totalPacketLen, next magic."""
    out = []
    i = data.find(MAGIC)
    while i >= 0 and i + 40 <= len(data):
        total, frame_number = struct.unpack_from("<I", data, i + 12)[0], struct.unpack_from("<I", data, i + 20)[0]
        if i + total <= len(data):
            out.append((i, frame_number, data[i:i + total]))
        i = data.find(MAGIC, i + total)
    return out


def _side_snr(raw: bytes) -> np.ndarray | None:
    """SNR column straight from TLV 7 of a packet (independent walk)."""
    num_tlvs, off = struct.unpack_from("<I", raw, 32)[0], 40
    for _ in range(num_tlvs):
        tlv_type, length = struct.unpack_from("<2I", raw, off)
        if tlv_type == 7:
            return np.frombuffer(raw, "<i2", length // 2, off + 8)[0::2] / 10.0
        off += 8 + length
    return None


def _feed_chunks(parser: MmwParser, data: bytes, sizes: list[int]) -> list:
    out, pos = [], 0
    for size in sizes:
        out += parser.feed(data[pos:pos + size])
        pos += size
    return out + parser.feed(data[pos:])


def _assert_accounting(parser: MmwParser, packets: list) -> None:
    """Every byte fed is in a packet, counted as skipped, or still pending."""
    used = sum(len(p.raw) for p in packets)
    assert used + parser.stats.bytes_skipped + parser.pending == parser.stats.bytes_in


@pytest.mark.parametrize(("path", "first", "count", "lead", "major"), CAPTURES, ids=["sdk2.1", "sdk3.6", "sdk3.3"])
def test_whole_capture_decodes_every_frame(path: Path, first: int, count: int, lead: int, major: int) -> None:
    data = _read(path)
    parser = MmwParser()
    packets = parser.feed(data)
    reference = _reference_frames(data)
    assert [p.frame_number for p in packets] == list(range(first, first + count))
    assert [(p.offset, p.raw) for p in packets] == [(off, raw) for off, _, raw in reference]
    assert parser.stats.bytes_skipped == lead and parser.stats.gaps == 0 and parser.stats.bad_packets == 0
    for p in packets:
        assert isinstance(p, RadarPacket) and p.version >> 24 == major
        assert p.points.dtype == np.float32 and p.points.shape == (struct.unpack_from("<I", p.raw, 28)[0], 5)
        assert len(p.raw) % 32 == 0 and p.stats is not None
        snr = _side_snr(p.raw)
        if snr is not None:
            np.testing.assert_allclose(p.points[:, 4], snr, rtol=1e-6)
            assert p.noise_db is not None and p.noise_db.shape == (len(p.points),)
    _assert_accounting(parser, packets)


@pytest.mark.parametrize("path", [SDK2, SDK36, SDK33], ids=["sdk2.1", "sdk3.6", "sdk3.3"])
def test_byte_by_byte_and_random_splits_give_the_same_frames(path: Path) -> None:
    data = _read(path)
    reference = MmwParser()
    whole = reference.feed(data)
    one = MmwParser()
    by_byte = [p for i in range(len(data)) for p in one.feed(data[i:i + 1])]
    rng = random.Random(5)
    split = MmwParser()
    by_split = _feed_chunks(split, data, [rng.randint(0, 900) for _ in range(200)])
    for packets in (by_byte, by_split):
        assert [p.raw for p in packets] == [p.raw for p in whole]
        assert all(np.array_equal(a.points, b.points, equal_nan=True) for a, b in zip(packets, whole, strict=True))
    assert one.stats.bytes_skipped == split.stats.bytes_skipped == reference.stats.bytes_skipped
    assert one.pending == split.pending == reference.pending


def _garbage(rng: random.Random) -> bytes:
    """Junk that contains magic-word prefixes and a fake header, but no valid packet."""
    pieces = [rng.randbytes(rng.randint(1, 60)), MAGIC[:rng.randint(1, 7)], MAGIC + rng.randbytes(rng.randint(0, 50))]
    rng.shuffle(pieces)
    return b"".join(pieces)


@pytest.mark.parametrize("path", [SDK2, SDK36, SDK33], ids=["sdk2.1", "sdk3.6", "sdk3.3"])
def test_garbage_between_frames_is_skipped_and_counted(path: Path) -> None:
    data = _read(path)
    rng = random.Random(7)
    reference = _reference_frames(data)
    stream, junk = bytearray(data[:reference[0][0]]), 0
    for _, _, raw in reference:
        stream += raw
        if rng.random() < 0.5:
            extra = _garbage(rng)
            stream += extra
            junk += len(extra)
    parser = MmwParser()
    packets = _feed_chunks(parser, bytes(stream), [rng.randint(1, 700) for _ in range(300)])
    assert [p.raw for p in packets] == [raw for _, _, raw in reference]
    assert parser.stats.gaps == 0
    assert parser.stats.bytes_skipped + parser.pending == reference[0][0] + junk  # trailing junk may wait
    _assert_accounting(parser, packets)


def test_lost_bytes_and_bad_lengths_cost_only_their_frame() -> None:
    data = _read(SDK33)
    frames = _reference_frames(data)
    broken = bytearray()
    for index, (_, _, raw) in enumerate(frames):
        if index == 10:
            raw = raw[:300] + raw[400:]  # UART lost 100 bytes: the next magic arrives early
        elif index == 20:
            raw = raw[:12] + struct.pack("<I", 70000) + raw[16:]  # corrupted totalPacketLen
        elif index == 30:
            raw = raw[:28] + struct.pack("<I", 99) + raw[32:]  # point count disagrees with TLV 1
        broken += raw
    parser = MmwParser()
    packets = parser.feed(bytes(broken))
    numbers = [p.frame_number for p in packets]
    expected = [n for i, (_, n, _) in enumerate(frames) if i not in (10, 20, 30)]
    assert numbers == expected
    assert parser.stats.gaps == 3 and parser.stats.missing_frames == 3 and parser.stats.bad_packets >= 3
    assert [p.gap for p in packets if p.gap] == [1, 1, 1]
    _assert_accounting(parser, packets)


def test_random_bytes_and_mutations_never_raise() -> None:
    data = _read(SDK36)
    rng = random.Random(11)
    parser = MmwParser()
    packets = parser.feed(rng.randbytes(50_000))
    mutated = bytearray(data)
    for _ in range(200):
        mutated[rng.randrange(len(mutated))] = rng.randrange(256)
    packets += _feed_chunks(parser, bytes(mutated), [rng.randint(1, 500) for _ in range(200)])
    assert parser.stats.packets == len(packets) > 0
    _assert_accounting(parser, packets)


def test_frame_numbers_going_back_count_as_restart() -> None:
    frames = _reference_frames(_read(SDK33))
    parser = MmwParser()
    packets = parser.feed(b"".join(raw for _, _, raw in frames[5:10] + frames[0:3]))
    assert len(packets) == 8 and parser.stats.restarts == 1 and parser.stats.gaps == 0


def test_sdk2_points_are_q_format_and_velocity_needs_the_cfg() -> None:
    data = _read(SDK2)
    packet = MmwParser().feed(data)[0]
    objects = packet.sdk2_objects()
    assert objects is not None and len(objects) == len(packet.points) == 5
    q_format = struct.unpack_from("<H", packet.raw, 48 + 2)[0]
    assert q_format == 9
    np.testing.assert_allclose(packet.points[:, :3], objects["xyz"] / 512.0)
    assert np.isnan(packet.points[:, 3:]).all()  # no Doppler resolution given, no SNR in SDK 2.x
    with_cfg = MmwParser(doppler_resolution=0.13).feed(data)[0]
    np.testing.assert_allclose(with_cfg.points[:, 3], objects["doppler_idx"] * 0.13, rtol=1e-6)
    assert packet.array(2) is not None and packet.array(2).shape == (256,)


def test_people_counting_dump_is_reported_not_misread() -> None:
    data = _read(PPLCOUNT)[:400_000]
    parser = MmwParser()
    packets = parser.feed(data)
    assert packets and all(isinstance(p, ForeignPacket) and p.kind == "pplcount" for p in packets)
    numbers = [p.frame_number for p in packets]
    assert numbers == list(range(1, len(numbers) + 1))
    assert parser.stats.packets == 0 and parser.stats.foreign_packets == len(packets)
    assert {t for p in packets for t in p.tlvs} <= {6, 7, 8}
    _assert_accounting(parser, packets)


def test_packet_becomes_a_radar_frame() -> None:
    packet = MmwParser().feed(_read(SDK36))[0]
    frame = packet.to_frame(t=1.5, seq=3)
    assert frame.modality == "radar" and frame.seq == 3 and frame.t == 1.5
    assert frame.data.dtype == np.float32 and frame.data.shape[1] == 5
    assert frame.meta["raw"] == packet.raw and frame.meta["frame_number"] == 69
    assert frame.meta["tlvs"] == (1, 7, 2, 6, 9) and frame.meta["version"] == "3.6.0.0"
    assert frame.meta["temperature"]["valid"] and frame.meta["stats"]["transmit_output_time_us"] > 0


@pytest.mark.parametrize("extra", range(1, 8))
def test_total_length_a_few_bytes_too_large_spares_the_next_frame(extra: int) -> None:
    frames = _reference_frames(_read(SDK33))
    stream = bytearray()
    hit = set()
    for index, (_, number, raw) in enumerate(frames):
        if index % 10 == 5:  # totalPacketLen overstated by 1-7 B: it reaches into the next magic word
            raw = raw[:12] + struct.pack("<I", len(raw) + extra) + raw[16:]
            hit.add(number)
        stream += raw
    parser = MmwParser()
    packets = _feed_chunks(parser, bytes(stream), [333] * (len(stream) // 333))
    lost = {n for _, n, _ in frames} - {p.frame_number for p in packets}
    assert not lost - hit  # the overstated frame may be lost, never the one after it
    assert parser.stats.missing_frames == len(lost)
    _assert_accounting(parser, packets)


def _numbered(raw: bytes, number: int) -> bytes:
    return raw[:20] + struct.pack("<I", number) + raw[24:]


@pytest.mark.parametrize("bit", [0, 3, 12, 31])
def test_one_flipped_bit_in_a_frame_number_adds_no_drops(bit: int) -> None:
    raws = [raw for _, _, raw in _reference_frames(_read(SDK33))]
    raws[40] = _numbered(raws[40], struct.unpack_from("<I", raws[40], 20)[0] ^ (1 << bit))
    parser = MmwParser()
    packets = parser.feed(b"".join(raws))
    assert len(packets) == len(raws)
    assert sum(p.gap for p in packets) == 0 and parser.stats.missing_frames == 0 and parser.stats.restarts == 0


def test_a_real_jump_is_counted_once_the_next_frame_confirms_it() -> None:
    raws = [raw for _, _, raw in _reference_frames(_read(SDK33))]
    kept = raws[:30] + raws[35:]  # 5 frames lost on the UART
    parser = MmwParser()
    packets = parser.feed(b"".join(kept))
    assert [p.gap for p in packets if p.gap] == [5] and parser.stats.missing_frames == 5
    # the frame right after the gap has a corrupted number: it still arrived, the gap stays 5
    kept[31] = _numbered(kept[31], 1 << 30)
    parser = MmwParser()
    packets = parser.feed(b"".join(kept))
    assert sum(p.gap for p in packets) == 5 and parser.stats.missing_frames == 5 and parser.stats.restarts == 0
