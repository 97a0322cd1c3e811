"""``respecd radar-dump CAPTURE``: decode a recorded TI mmWave data-port capture.

Takes the TI visualizer's ``.dat`` recordings or any raw UART byte dump (they are the same
bytes). Prints one line per complete frame (``--json``: one object per line) and a summary
on stderr: frames, bytes skipped, frame-number gaps.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from respecd.errors import InputError

CHUNK = 64 * 1024  # read size: the parser is incremental, the file may be large
# a capture starts with a frame within one frame period's bytes; this much without one is not a capture
# (and /dev/zero or /dev/urandom given by mistake would otherwise be read forever)
NO_FRAME_LIMIT = 16 * 1024 * 1024


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="CAPTURE", help="recorded data-port bytes (.dat, .bin)")
    parser.add_argument("--json", action="store_true", help="one JSON object per frame")
    parser.add_argument("--points", action="store_true", help="with --json: include the points [x, y, z, v, snr]")
    parser.add_argument("--cfg", metavar="CFG", help="chirp cfg of the recording (SDK 2.x Doppler bins -> m/s)")


def main(args: argparse.Namespace) -> int:
    from respecd.radar.parser import MmwParser

    doppler_resolution = _doppler_resolution(args.cfg) if args.cfg else float("nan")
    parser = MmwParser(doppler_resolution=doppler_resolution)
    path = Path(args.capture)
    versions: set[str] = set()
    try:
        for chunk in _chunks(path):
            for packet in parser.feed(chunk):
                record = _record(packet, args.points and args.json)
                versions.add(record["version"])
                print(json.dumps(record) if args.json else _text(record))
            if parser.stats.bytes_in >= NO_FRAME_LIMIT and not _frames_seen(parser):
                raise _no_frames(path, parser, "in its first")
    except BrokenPipeError:  # `respecd radar-dump X | head`: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    if not _frames_seen(parser):
        raise _no_frames(path, parser, "in")
    print(_summary(parser, versions), file=sys.stderr)
    return 0


def _frames_seen(parser: Any) -> bool:
    return bool(parser.stats.packets or parser.stats.foreign_packets)


def _no_frames(path: Path, parser: Any, where: str) -> InputError:
    return InputError(f"{path}: no TI mmWave data-port frames {where} {parser.stats.bytes_in} bytes "
                      "(expected magic word 02 01 04 03 06 05 08 07 and a valid header)")


def _chunks(path: Path) -> Iterator[bytes]:
    try:
        with path.open("rb") as handle:
            while chunk := handle.read(CHUNK):
                yield chunk
    except FileNotFoundError as err:
        raise InputError(f"{path}: no such capture file") from err
    except IsADirectoryError as err:
        raise InputError(f"{path}: is a directory, expected a capture file") from err
    except OSError as err:
        raise InputError(f"{path}: cannot read capture: {err.strerror}") from err


def _doppler_resolution(cfg_path: str) -> float:
    from respecd.radar.cfg import profile_from_lines, read_cfg

    return profile_from_lines(read_cfg(cfg_path)).velocity_resolution_mps


def _record(packet: Any, with_points: bool) -> dict[str, Any]:
    from respecd.radar.parser import RadarPacket

    if not isinstance(packet, RadarPacket):
        return {"frame": packet.frame_number, "format": packet.kind, "version": _version(packet.version),
                "platform": f"{packet.platform:#x}", "points": None, "tlvs": list(packet.tlvs),
                "bytes": len(packet.raw), "offset": packet.offset, "gap": packet.gap}
    record: dict[str, Any] = {
        "frame": packet.frame_number, "format": "oob", "version": packet.version_str,
        "platform": f"{packet.platform:#x}", "subframe": packet.subframe, "points": len(packet.points),
        "tlvs": list(packet.tlv_types), "bytes": len(packet.raw), "offset": packet.offset, "gap": packet.gap,
        "stats": packet.stats, "temperature": packet.temperature,
    }
    if with_points:
        record["xyzv_snr"] = [[None if v != v else round(float(v), 4) for v in row] for row in packet.points]
    return record


def _version(value: int) -> str:
    return f"{value >> 24}.{(value >> 16) & 0xFF}.{(value >> 8) & 0xFF}.{value & 0xFF}"


def _text(record: dict[str, Any]) -> str:
    tlvs = ",".join(str(t) for t in record["tlvs"]) or "-"
    # a jump is confirmed by the frame after it (respecd.radar.sequence): the lost frames came before the previous one
    gap = f" GAP {record['gap']} missing before the previous frame" if record["gap"] else ""
    if record["format"] != "oob":
        return (f"frame {record['frame']:>7} {record['format']} v{record['version']} tlvs {tlvs} "
                f"bytes {record['bytes']} (not the out-of-box format: points not decoded){gap}")
    return (f"frame {record['frame']:>7} v{record['version']} {record['platform']} points {record['points']:>3} "
            f"tlvs {tlvs} bytes {record['bytes']}{gap}")


def _summary(parser: Any, versions: set[str]) -> str:
    s = parser.stats
    text = (f"radar-dump: {s.packets} frames (SDK {', '.join(sorted(versions)) or '-'}), "
            f"{s.bytes_skipped} bytes skipped, {s.gaps} gaps ({s.missing_frames} frames missing), "
            f"{s.restarts} restarts, {s.bad_packets} bad packets, {parser.pending} bytes incomplete at end")
    if s.foreign_packets:
        text += (f"; {s.foreign_packets} people-counting frames (52-byte header, not the out-of-box demo "
                 "format: points not decoded)")
    return text
