"""Driver throughput: the radar data-port parser on real TI captures (more sections may join).

Each section is a function in ``SECTIONS`` returning its own dict of figures, so a camera
section can be added beside the radar one. The radar parser must keep up with a saturated
921600-baud data port (92,160 B/s) by far more than 100x, so a slow edge CPU still has room
for everything else; the figures say by how much, fed whole and in small chunks.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from respecd.errors import InputError
from respecd.lab.bench.cameras import flirone_assembler, uvc_file

DEFAULT_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "real"
RADAR_CAPTURES = (  # TI out-of-box demo data-port recordings (SDK 2.1, 3.6, 3.3)
    "ti_awr1642_oob_piatek/xwr16xx_processed_stream_2023_10_30T09_00_44_253.dat",
    "ti_awr1642_oob_piatek/AWR1642_test_data_SDK_3_6_0.dat",
    "ti_iwr6843_oob_automated_doors/xwr68xx_processed_stream_2019_12_04T21_44_51_663.dat",
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of the real captures")
    parser.add_argument("--chunk", type=int, default=64, help="bytes per feed for the small-chunk run")
    parser.add_argument("--repeat", type=int, default=20, help="passes over the captures per timed round")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds; the best one is reported")


def run(args: argparse.Namespace) -> dict[str, Any]:
    if args.chunk < 1 or args.repeat < 1 or args.rounds < 1:
        raise InputError("--chunk, --repeat and --rounds must be at least 1")
    return {name: section(args) for name, section in SECTIONS.items()}


def radar_parser(args: argparse.Namespace) -> dict[str, Any]:
    """MB/s and frames/s of MmwParser over the real captures, whole and in ``--chunk`` pieces."""
    from respecd.radar.chirp import UART_BYTES_PER_S

    captures = [_load(args.data / name) for name in RADAR_CAPTURES]
    total_bytes = sum(len(c) for c in captures) * args.repeat
    out: dict[str, Any] = {"captures": len(captures), "bytes_per_round": total_bytes, "chunk_bytes": args.chunk}
    for label, chunk in (("whole", None), ("chunked", args.chunk)):
        rounds = [_time_round(captures, chunk, args.repeat) for _ in range(args.rounds)]
        wall = min(r[0] for r in rounds)
        cpu = min(r[1] for r in rounds)  # CPU seconds: robust when other processes share the cores
        frames = rounds[0][2]
        out[f"{label}_frames_per_round"] = frames
        out[f"{label}_mb_per_s"] = round(total_bytes / wall / 1e6, 2)
        out[f"{label}_frames_per_s"] = round(frames / wall)
        out[f"{label}_x_uart_budget"] = round(total_bytes / wall / UART_BYTES_PER_S, 1)  # vs 921600 baud 8N1
        out[f"{label}_mb_per_cpu_s"] = round(total_bytes / cpu / 1e6, 2)
        out[f"{label}_x_uart_budget_cpu"] = round(total_bytes / cpu / UART_BYTES_PER_S, 1)
    out["uart_budget_b_per_s"] = UART_BYTES_PER_S
    out["load_average_1min"] = round(os.getloadavg()[0], 2)  # > cores: wall-clock figures are pessimistic
    return out


def _load(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read radar capture ({err.strerror}); pass --data shared/data/real") from err


def _time_round(captures: list[bytes], chunk: int | None, repeat: int) -> tuple[float, float, int]:
    """(wall s, CPU s, frames) to parse every capture ``repeat`` times, a fresh parser per pass."""
    from respecd.radar.parser import MmwParser

    frames = 0
    started, cpu_started = time.perf_counter(), time.process_time()
    for _ in range(repeat):
        for data in captures:
            parser = MmwParser()
            if chunk is None:
                frames += len(parser.feed(data))
                continue
            view = memoryview(data)
            for offset in range(0, len(data), chunk):
                frames += len(parser.feed(view[offset:offset + chunk]))
    return time.perf_counter() - started, time.process_time() - cpu_started, frames


SECTIONS: dict[str, Callable[[argparse.Namespace], dict[str, Any]]] = {
    "radar_parser": radar_parser,
    "flirone_assembler": flirone_assembler,
    "uvc_file": uvc_file,
}
