"""Profile section ``recording:``: where the MCAP log goes, how it is chunked, rotated and
compressed, and which channels it carries.

Small chunks bound what a power cut can lose (a log is readable up to its last complete
chunk); rotation bounds the size of any one file so a long run never becomes one huge log.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from respecd.sensors import StrictModel

Channel = Literal["frames", "radar_raw", "percepts", "decisions", "configs", "sync"]
ALL_CHANNELS: tuple[Channel, ...] = ("frames", "radar_raw", "percepts", "decisions", "configs", "sync")


class RecordingConfig(StrictModel):
    enabled: bool = Field(False, description="Record the session to MCAP.")
    path: str = Field(
        "respecd-{time}.mcap",
        description=(
            "Output path; {time} becomes the UTC start time (YYYYmmddTHHMMSS), {index} the rotation segment "
            "(without {index}, segments after the first get -001, -002, ... before the suffix)."
        ),
    )
    chunk_size_kib: int = Field(
        1024, ge=16, le=65536, description="MCAP chunk size (KiB of messages): a crash loses at most the chunk being "
        "filled (at the simulated rover's 11 MB/s about 0.1 s).",
    )
    flush_s: float = Field(
        2.0, gt=0, le=600, description="Close the open chunk at least this often (s of session time), bounding loss."
    )
    fsync: bool = Field(
        True, description="fsync at most every flush_s: a power cut (not just a crash) keeps what was fsynced."
    )
    compression: Literal["zstd", "lz4", "none"] = Field(
        "lz4", description="Chunk compression: lz4 (default) costs the writer about a third of zstd's CPU for "
        "files about 25 % larger (zstd at the mcap library's level 3).",
    )
    rotate_mib: float = Field(
        512.0, gt=0, le=1 << 20, description="Start a new file once the current one reaches this size (MiB)."
    )
    rotate_s: float = Field(
        0.0, ge=0, description="Start a new file after this many seconds of session time (0: no time rotation)."
    )
    channels: list[Channel] = Field(
        list(ALL_CHANNELS),
        description="What to record: sensor frames, raw radar UART bytes, percepts, decisions, applied configs, sync.",
    )
    jpeg_quality: int = Field(
        80, ge=10, le=100, description="JPEG quality for RGB frames (CompressedImage). 80: on the simulated rover "
        "about 0.8 points of a core less than 90, for files a quarter smaller (docs/PERFORMANCE.md).",
    )
    rgb_format: Literal["jpeg", "png"] = Field(
        "jpeg", description="RGB encoding: jpeg (small, lossy) or png (lossless, ~9x larger, ~11x slower to encode)."
    )
    depth_format: Literal["raw", "png"] = Field(
        "raw",
        description=(
            "16-bit thermal/depth encoding: raw (RawImage mono16/16UC1, chunk-compressed; ~3x cheaper to encode) "
            "or png (CompressedImage, lossless, ~15% smaller files)."
        ),
    )
    thermal_colormap: Literal["inferno", "none"] = Field(
        "inferno",
        description=(
            "Beside the exact thermal image, a display image (JPEG) colormapped over perception.thermal_range_k; "
            "the scale is in the channel metadata. none: only the exact image."
        ),
    )
    min_free_mib: float = Field(
        256.0, ge=0, description="Free space (MiB) recording leaves on the disk: below it the file is finished "
        "and recording pauses, resuming in a new file once there is room (0: write until the disk refuses).",
    )
    max_bytes: int = Field(
        0, ge=0, description="Most bytes of recordings (every session this path names) kept on disk; past it the "
        "oldest session's files are deleted first, never the file being written (0: no limit).",
    )
    delete_oldest: bool = Field(
        False, description="Below min_free_mib, delete the oldest recordings (oldest session first) before pausing.",
    )
    queue_size: int = Field(
        256, ge=8, le=65536, description="Messages waiting for the writer thread before the oldest is dropped."
    )
    batch_s: float = Field(
        0.5, ge=0, le=5, description="The writer thread wakes at most this often (s) and encodes what queued in one "
        "burst (sooner once half of queue_size waits; per message while the live view is on): on the simulated "
        "rover a wake per message costs 1.35-1.58x the CPU (cold caches). A crash, not a SIGTERM, loses up to "
        "this much more. 0: wake per message.",
    )

