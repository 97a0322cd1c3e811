"""The MCAP file side of recording: segments, channels, chunk flushing and rotation.

Used only from the recorder's writer thread. Every segment is a complete MCAP file with
the profile and session metadata, so each one replays on its own. ``flush_s`` closes the
open chunk regularly: a file cut by a power loss keeps everything up to the last chunk.
"""

from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import IO, Any

import structlog
from mcap.writer import CompressionType, Writer

from respecd.record.codec import Message
from respecd.record.config import RecordingConfig
from respecd.record.schemas import schema_def

log = structlog.get_logger(__name__)

MCAP_PROFILE = ""  # no ROS profile: Foxglove protobuf types and respecd JSON channels
LIBRARY = "respecd"
# 1: JSON messages, base64 payloads (respecd 0.1.0); 2: Foxglove protobuf types + FrameMeta channels
LOG_FORMAT = "2"
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def segment_path(template: str, started: datetime, index: int) -> Path:
    """The file name of segment ``index`` (0 first) of a session that started at ``started``."""
    stamp = started.astimezone(timezone.utc).strftime("%Y%m%dT%H%M%S")
    path = Path(template.replace("{time}", stamp).replace("{index}", f"{index:03d}"))
    if index > 0 and "{index}" not in template:
        path = path.with_name(f"{path.stem}-{index:03d}{path.suffix}")
    return path


class SegmentWriter:
    """Writes messages to the current segment; starts a new one past the size or time limit."""

    def __init__(self, config: RecordingConfig, metadata: dict[str, dict[str, str]], started: datetime) -> None:
        self.config = config
        self.metadata = metadata
        self.started = started
        self.paths: list[Path] = []
        self.messages = 0
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._segment_t0 = 0.0
        self._last_flush = 0.0

    def open(self, t: float) -> Path:
        """Start the next segment at session time ``t`` (s)."""
        path = segment_path(self.config.path, self.started, len(self.paths))
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(path, "wb")  # noqa: SIM115 - lives as long as the segment
        self._writer = Writer(
            self._file,
            chunk_size=self.config.chunk_size_kib * 1024,
            compression=_COMPRESSION[self.config.compression],
            enable_data_crcs=True,  # DataEnd's CRC covers what chunk CRCs do not: header, metadata, indexes
        )
        self._writer.start(profile=MCAP_PROFILE, library=LIBRARY)
        for name, data in self.metadata.items():
            segment = {**data, "segment": str(len(self.paths))} if name == "respecd.session" else data
            self._writer.add_metadata(name, segment)
        self._writer.flush()  # header + metadata reach the disk before any frame
        self._schemas.clear()
        self._channels.clear()
        self._segment_t0 = self._last_flush = t
        self.paths.append(path)
        log.info("record.segment", path=str(path), index=len(self.paths) - 1)
        return path

    def write(
        self, topic: str, schema: str, channel_meta: dict[str, str], log_ns: int, payload: bytes, t: float
    ) -> None:
        """Append one message; rotate or flush by size and session time."""
        if self._writer is None:
            self.open(t)
        assert self._writer is not None and self._file is not None
        channel_id = self._channels.get(topic)
        if channel_id is None:
            definition = schema_def(schema)
            schema_id = self._schemas.get(schema)
            if schema_id is None:
                schema_id = self._writer.register_schema(schema, definition.encoding, definition.data)
                self._schemas[schema] = schema_id
            channel_id = self._writer.register_channel(topic, definition.message_encoding, schema_id, channel_meta)
            self._channels[topic] = channel_id
        self._writer.add_message(channel_id, log_time=log_ns, data=payload, publish_time=log_ns)
        self.messages += 1
        if t - self._last_flush >= self.config.flush_s:
            self._writer.flush()  # closes the open chunk: readable after a crash from here on
            if self.config.fsync:
                os.fsync(self._file.fileno())  # ... and after a power cut (page cache on disk)
            self._last_flush = t
        too_big = self._file.tell() >= self.config.rotate_mib * 1024 * 1024
        too_old = self.config.rotate_s > 0 and t - self._segment_t0 >= self.config.rotate_s
        if too_big or too_old:
            self.finish()
            self.open(t)

    # -- the recorder's sink interface --------------------------------------------------
    def wants(self, topic: str) -> bool:
        return True  # a log keeps every channel it was asked to record

    def put(self, message: Message, log_ns: int, t: float) -> None:
        self.write(message.topic, message.schema, message.channel_meta, log_ns, message.payload, t)

    def close(self) -> None:
        self.finish()

    def finish(self) -> None:
        """Write the summary and footer of the current segment and close it (idempotent)."""
        if self._writer is None or self._file is None:
            return
        try:
            self._writer.finish()
        finally:
            self._file.close()
            self._writer = None
            self._file = None


def _version() -> str:
    try:
        return metadata.version("respecd")
    except metadata.PackageNotFoundError:
        return "unknown"


def session_metadata(profile: Any, started: datetime, t0: float, epoch_ns: int) -> dict[str, dict[str, str]]:
    """MCAP metadata records: the profile used (as JSON) and the session's time origin."""
    dump = profile.model_dump(mode="json") if hasattr(profile, "model_dump") else dict(profile)
    return {
        "respecd.profile": {"name": str(dump.get("name", "")), "json": json.dumps(dump, separators=(",", ":"))},
        "respecd.session": {
            "started_utc": started.astimezone(timezone.utc).isoformat(),
            "clock_t0": repr(t0),
            "epoch_ns_at_t0": str(epoch_ns),
            "respecd_version": _version(),
            "format": LOG_FORMAT,
        },
    }
