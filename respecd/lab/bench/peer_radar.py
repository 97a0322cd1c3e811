"""Radar data-port parser against TI's reference parser and juhasch/xwr68xxisk, same capture.

Every parser decodes the whole real IWR6843 capture, ``repeat`` times per round, best round
reported as CPU µs per frame; the points (x, y, z, v as float32) and the side info (SNR,
noise) of every frame both decode are compared value for value (``identical``).

Neither peer is on PyPI, so each is loaded from a checkout (``--peers DIR``):

* TI: ``DIR/ti/parser_mmw_demo.py`` (mmWave SDK ``packages/ti/demo/parser_scripts``), driven
  the way TI's ``mmw_demo_example_script.py`` drives it (one packet per call on the rest of
  the stream, advance by ``headerStartIndex + totalPacketNumBytes``), with its per-frame
  ``print``s silenced: the parser, not the terminal.
  It decodes TLVs 1 and 7 only and fails a frame with no points.
* juhasch: ``DIR/xwr68xxisk`` (a checkout; ``xwr68xxisk.parse.RadarData``). Its serial reader
  frames packets with pyserial's ``read_until(MAGIC)``; here ``bytes.find`` does that, so only
  the TLV decoding is the peer's own code.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import logging
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from respecd.radar.tlv import MAGIC

CAPTURE = "ti_iwr6843_oob_automated_doors/xwr68xx_processed_stream_2019_12_04T21_44_51_663.dat"
Decoded = dict[int, tuple[np.ndarray, np.ndarray | None]]  # stream offset -> (x y z v float32, snr noise ints)
Parser = tuple[Callable[[bytes], list[Any]], Callable[[list[Any]], Decoded]]  # (timed parse, decode to compare)


def ours(data: bytes) -> list[Any]:
    from respecd.radar.parser import MmwParser

    return MmwParser().feed(data)


def decode_ours(packets: list[Any]) -> Decoded:
    from respecd.radar.parser import RadarPacket

    out: Decoded = {}
    for packet in packets:
        if isinstance(packet, RadarPacket):
            side = None if packet.side_info is None else packet.side_info.astype(np.int64)
            out[packet.offset] = (packet.points[:, :4], side)
    return out


def ti_parser(checkout: Path) -> Parser:
    """TI's ``parser_one_mmw_demo_output_packet`` over a whole capture."""
    path = checkout / "ti" / "parser_mmw_demo.py"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: TI's parser_mmw_demo.py is not there")
    spec = importlib.util.spec_from_file_location("_peer_parser_mmw_demo", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.print = lambda *args, **kwargs: None  # type: ignore[attr-defined]  # it prints every frame
    parse_one = module.parser_one_mmw_demo_output_packet

    def parse(data: bytes) -> list[Any]:
        out, pos = [], 0
        while pos < len(data):
            result = parse_one(data[pos:], len(data) - pos)
            start, total = result[1], result[2]
            if start < 0 or total <= 0:
                break
            if result[0] == 0:  # TC_PASS
                out.append((pos + start, result))
            pos += start + total
        return out

    def decode(frames: list[Any]) -> Decoded:
        out: Decoded = {}
        for offset, (_, _, _, _, _, _, x, y, z, v, _, _, _, snr, noise) in frames:
            out[offset] = (np.array([x, y, z, v], dtype=np.float32).T.reshape(-1, 4),
                           np.array([snr, noise], dtype=np.int64).T.reshape(-1, 2))
        return out

    return parse, decode


def juhasch_parser(checkout: Path) -> Parser:
    """juhasch's ``RadarData`` on each packet, fed the way its ``read_frame`` feeds it."""
    if not (checkout / "xwr68xxisk" / "xwr68xxisk" / "parse.py").is_file():
        raise FileNotFoundError(f"{checkout / 'xwr68xxisk'}: not a juhasch/xwr68xxisk checkout")
    with _on_path(checkout / "xwr68xxisk"):
        radar_data = importlib.import_module("xwr68xxisk.parse").RadarData

    def parse(data: bytes) -> list[Any]:
        with _quiet():  # it logs a warning per frame without points: the parser, not the terminal
            return [(offset, radar_data(connection)) for offset, connection in _packets(data)]

    def decode(frames: list[Any]) -> Decoded:
        out: Decoded = {}
        for offset, frame in frames:
            points = np.array(frame.pc, dtype=np.float32).T.reshape(-1, 4)
            side = None
            if frame.snr:  # dB floats, x 0.1 of the raw int16s
                side = np.rint(np.array([frame.snr, frame.noise]) * 10).astype(np.int64).T
            out[offset] = (points, side)
        return out

    return parse, decode


class _Packet:
    """One ``read_frame`` result for RadarData: the header after the magic word, the payload."""

    is_running = True

    def __init__(self, segment: bytes) -> None:
        self.segment = segment

    def is_connected(self) -> bool:
        return True

    def read_frame(self) -> tuple[dict[str, Any], np.ndarray]:
        packet = self.segment
        header = {"frame_number": int.from_bytes(packet[12:16], "little"),
                  "num_tlvs": int.from_bytes(packet[24:28], "little")}
        return header, np.frombuffer(packet[32:], dtype=np.uint8)


def _packets(data: bytes) -> Iterator[tuple[int, _Packet]]:
    """(magic offset, what ``read_until(MAGIC)`` returns after it) for every packet."""
    start = data.find(MAGIC)
    while start >= 0:
        following = data.find(MAGIC, start + len(MAGIC))
        end = len(data) if following < 0 else following + len(MAGIC)
        yield start, _Packet(data[start + len(MAGIC):end])
        start = following


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(logging.NOTSET)


@contextlib.contextmanager
def _on_path(folder: Path) -> Iterator[None]:
    sys.path.insert(0, str(folder))
    try:
        yield
    finally:
        sys.path.remove(str(folder))


def compare(mine: Decoded, theirs: Decoded) -> dict[str, Any]:
    """Frames both decoded, and whether every point and side-info value agrees."""
    common = sorted(set(mine) & set(theirs))
    same = 0
    for offset in common:
        (p1, s1), (p2, s2) = mine[offset], theirs[offset]
        points_ok = p1.shape == p2.shape and bool(np.array_equal(_bits(p1), _bits(p2)))  # NaN-safe, -0.0 != 0.0
        side_ok = s2 is None or (not s2.any() if s1 is None else np.array_equal(s1 & 0xFFFF, s2 & 0xFFFF))
        same += points_ok and side_ok
    return {"frames_compared": len(common), "frames_identical": same, "identical": bool(common) and same == len(common)}


def time_parser(parse: Callable[[bytes], list[Any]], data: bytes, repeat: int, rounds: int) -> dict[str, Any]:
    """Best-round CPU and wall µs per frame the parser returns."""
    best_cpu = best_wall = float("inf")
    frames = 0
    for _ in range(rounds):
        started, cpu_started = time.perf_counter(), time.process_time()
        for _ in range(repeat):
            frames = len(parse(data))
        best_cpu = min(best_cpu, time.process_time() - cpu_started)
        best_wall = min(best_wall, time.perf_counter() - started)
    per = max(frames * repeat, 1)
    return {"frames": frames, "cpu_us_per_frame": round(best_cpu / per * 1e6, 1),
            "wall_us_per_frame": round(best_wall / per * 1e6, 1)}


def _bits(points: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(points, dtype=np.float32).view(np.uint32)
