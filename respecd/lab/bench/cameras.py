"""Camera section of ``respecd bench drivers``: the FLIR One frame assembler on the real Gen-3
capture (EP 0x85 reads as recorded, and re-split into ``--chunk`` pieces).

The camera sends ~88 KB frames at ~8.7 Hz, about 0.77 MB/s; the figures say by how much the
assembler (which runs in the driver's worker thread) outpaces that.
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

from respecd.errors import InputError

FLIR_CAPTURE = "flirone_pro_gen3_usb_moezemara/test_chunks_hex"
CAMERA_RATE_HZ = 8.7  # FLIR One frames per second


def flirone_assembler(args: argparse.Namespace) -> dict[str, Any]:
    """MB/s and frames/s of FrameAssembler over the recorded reads and over ``--chunk`` pieces."""
    from respecd.drivers.flirone_usb import RecordedTransport

    path = args.data / FLIR_CAPTURE
    if not path.is_dir():
        raise InputError(f"{path}: FLIR capture not found; pass --data shared/data/real")
    reads = RecordedTransport.from_path(path).chunks
    stream = b"".join(reads)
    small = [stream[i : i + args.chunk] for i in range(0, len(stream), args.chunk)]
    out: dict[str, Any] = {"bytes_per_pass": len(stream), "reads_per_pass": len(reads), "chunk_bytes": args.chunk}
    camera_b_per_s = len(stream) / 20 * CAMERA_RATE_HZ  # the capture holds 20 frames
    for label, pieces in (("usb_reads", reads), ("chunked", small)):
        rounds = [_time_round(pieces, args.repeat) for _ in range(args.rounds)]
        wall = min(r[0] for r in rounds)
        cpu = min(r[2] for r in rounds)  # CPU seconds: robust when other processes share the cores
        frames = rounds[0][1]
        out[f"{label}_frames_per_round"] = frames
        out[f"{label}_mb_per_s"] = round(len(stream) * args.repeat / wall / 1e6, 1)
        out[f"{label}_frames_per_s"] = round(frames / wall)
        out[f"{label}_x_camera_rate"] = round(len(stream) * args.repeat / wall / camera_b_per_s, 1)
        out[f"{label}_mb_per_cpu_s"] = round(len(stream) * args.repeat / cpu / 1e6, 1)
    out["camera_mb_per_s"] = round(camera_b_per_s / 1e6, 2)
    out["load_average_1min"] = round(os.getloadavg()[0], 2)  # > cores: wall-clock figures are pessimistic
    return out


def _time_round(pieces: list[bytes], repeat: int) -> tuple[float, int, float]:
    """(wall s, frames, CPU s) to assemble the capture ``repeat`` times, a fresh assembler per pass."""
    from respecd.drivers.flirone_protocol import FrameAssembler

    frames = 0
    started, cpu_started = time.perf_counter(), time.process_time()
    for _ in range(repeat):
        assembler = FrameAssembler()
        for piece in pieces:
            frames += len(assembler.feed(piece))
    return time.perf_counter() - started, frames, time.process_time() - cpu_started


def uvc_file(args: argparse.Namespace) -> dict[str, Any]:
    """Frames/s the uvc driver delivers from a 1280x720 MJPG file played as fast as consumed:
    native size, resized to 640x360, and decimated to 10 Hz (skipped frames are grabbed, not retrieved)."""
    import asyncio
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "clip.avi"
        frames = _write_clip(path, count=150)
        out: dict[str, Any] = {"clip": "1280x720 MJPG, 30 fps", "clip_frames": frames}
        cases = (("native", (1280, 720), 30.0), ("resized_640x360", (640, 360), 30.0), ("decimated_10hz", None, 10.0))
        for label, size, rate in cases:
            runs = [asyncio.run(_play(path, size, rate)) for _ in range(args.rounds)]
            wall, cpu, delivered = min(runs)
            out[f"{label}_frames"] = delivered
            out[f"{label}_file_frames_per_s"] = round(frames / wall, 1)  # file frames consumed per second
            out[f"{label}_cpu_ms_per_file_frame"] = round(cpu / frames * 1000, 2)
    return out


def _write_clip(path: Any, count: int) -> int:
    import cv2
    import numpy as np

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 30, (1280, 720))
    rng = np.random.default_rng(0)
    base = rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8)  # textured, so MJPG has work to do
    for i in range(count):
        writer.write(np.roll(base, 8 * i, axis=1))
    writer.release()
    return count


async def _play(path: Any, size: tuple[int, int] | None, rate: float) -> tuple[float, float, int]:
    """(wall s, CPU s, frames delivered) for one pass through the file."""
    from respecd.clock import MonotonicClock
    from respecd.drivers.uvc import UVCConfig, UVCDriver

    config = UVCConfig(name="bench", device=str(path), realtime=False, rate_hz=rate, resolution=size,
                       resolutions=[(1280, 720), (640, 360)])
    driver = UVCDriver(config, MonotonicClock())
    started, cpu_started = time.perf_counter(), time.process_time()
    await driver.start()
    delivered = 0
    try:
        async for _ in driver.frames():
            delivered += 1
    finally:
        await driver.stop()
    return time.perf_counter() - started, time.process_time() - cpu_started, delivered
