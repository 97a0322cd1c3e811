"""Profile section ``recording:``: where the MCAP log goes, how it is chunked, rotated and
compressed, and which channels it carries.

Small chunks bound what a power cut can lose (a log is readable up to its last complete
chunk); rotation bounds the size of any one file so a long run never becomes one huge log.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from respecd.sensors import StrictModel

MIB = 1 << 20

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
        "lz4", description="MCAP chunk compression. Images are compressed per message (png, jpeg), so the chunk's "
        "compression matters for raw images and respecd's JSON channels: lz4 (default) is the cheaper, zstd (the "
        "mcap library's level 3) the smaller.",
    )
    rotate_mib: float = Field(
        512.0, ge=1, le=1 << 20, description="Start a new file once the current one reaches this size (MiB, "
        "at least 1: a segment is a whole MCAP file with the profile and its own summary).",
    )
    rotate_s: float = Field(
        0.0, ge=0, description="Start a new file after this many seconds of session time (0: no time rotation)."
    )
    channels: list[Channel] = Field(
        list(ALL_CHANNELS),
        description="What to record: sensor frames, raw radar UART bytes, percepts, decisions, applied configs, sync.",
    )
    rgb_format: Literal["png", "jpeg", "raw"] = Field(
        "png",
        description=(
            "RGB frames: png (CompressedImage, lossless), jpeg (CompressedImage at jpeg_quality: lossy, an order "
            "of magnitude smaller and cheaper to encode; docs/RECORDING.md \"Image encodings\") or raw (RawImage "
            "bgr8, compressed only by the chunk)."
        ),
    )
    jpeg_quality: int = Field(
        80, ge=10, le=100, description="JPEG quality of RGB frames when rgb_format is jpeg, and of the thermal "
        "display image.",
    )
    thermal_format: Literal["png", "raw"] = Field(
        "png", description="Thermal frames: png (CompressedImage, lossless, 16-bit kept) or raw (RawImage mono16).",
    )
    depth_format: Literal["png", "raw"] = Field(
        "png", description="Depth frames: png (CompressedImage, lossless 16-bit millimetres) or raw (RawImage 16UC1).",
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
        0, ge=0, description="Most bytes of recordings (every session this path names) kept on disk; past it "
        "earlier sessions' files are deleted first (oldest written first, only files last written before this "
        "session started), then this session's finished segments, never the file being written (0: no limit; "
        "else at least two segments, 2 x rotate_mib MiB).",
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

    @model_validator(mode="after")
    def _room_for_two_segments(self) -> RecordingConfig:
        """A cap below two segments would delete every finished one at once, or hold nothing at all."""
        least = int(2 * self.rotate_mib * MIB)
        if self.max_bytes and self.max_bytes < least:
            raise ValueError(f"max_bytes {self.max_bytes} is less than two segments of rotate_mib {self.rotate_mib:g} "
                             f"MiB ({least} bytes): use 0 (no limit), at least {least}, or a smaller rotate_mib")
        return self
