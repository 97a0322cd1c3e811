"""The MCAP file side of recording: segments, channels, chunk flushing and rotation.

Used only from the recorder's writer thread. Every segment is a complete MCAP file with
the profile and session metadata, so each one replays on its own. ``flush_s`` closes the
open chunk regularly: a file cut by a power loss keeps everything up to the last chunk.
A full disk pauses recording instead of failing every write (``SegmentWriter``).
"""

from __future__ import annotations

import errno
import json
import os
import time
from collections.abc import Callable, Mapping
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel

from respecd.record.codec import Message
from respecd.record.config import RecordingConfig
from respecd.record.schemas import schema_def
from respecd.record.storage import MIB, Retention, free_bytes

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)

MCAP_PROFILE = ""  # no ROS profile: Foxglove protobuf types and respecd JSON channels
LIBRARY = "respecd"
# 1: JSON messages, base64 payloads (respecd 0.1.0); 2: Foxglove protobuf types + FrameMeta channels
LOG_FORMAT = "2"
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
RETRY_S = 5.0  # first wait (wall s) before a paused recording checks for room again; doubles
MAX_RETRY_S = 300.0
RESUME_MARGIN = 1.25  # resume above floor x this (+ a chunk): no pause/resume flapping at the floor


def session_stamp(started: datetime) -> str:
    """What ``{time}`` becomes in a session's file names: its UTC start to the second."""
    return started.astimezone(timezone.utc).strftime("%Y%m%dT%H%M%S")


def segment_path(template: str, started: datetime, index: int) -> Path:
    """The file name of segment ``index`` (0 first) of a session that started at ``started``."""
    path = Path(template.replace("{time}", session_stamp(started)).replace("{index}", f"{index:03d}"))
    if index > 0 and "{index}" not in template:
        path = path.with_name(f"{path.stem}-{index:03d}{path.suffix}")
    return path


class _WholeWrites:
    """An unbuffered segment file whose ``write`` writes everything or raises.

    Unbuffered, so that after a failed write nothing is left in a buffer to be written
    later, past the point the file is cut back to; looping, because near a full disk
    write(2) writes part and the error comes only with the next call.
    """

    def __init__(self, path: Path) -> None:
        # "x": never over an existing file, a session must not destroy an earlier one (FileExistsError pauses)
        self._raw = open(path, "xb", buffering=0)  # noqa: SIM115 - lives as long as the segment

    def write(self, data: bytes | memoryview) -> int:
        view = memoryview(data)
        while view:
            done = self._raw.write(view)
            if not done:
                raise OSError(errno.ENOSPC, "short write")
            view = view[done:]
        return len(data)

    def tell(self) -> int:
        return self._raw.tell()

    def fileno(self) -> int:
        return self._raw.fileno()

    def flush(self) -> None:
        pass

    def cut(self, size: int) -> None:
        """Drop everything after ``size`` (a chunk the disk refused half-way) and close."""
        try:
            os.ftruncate(self._raw.fileno(), size)
        finally:
            self._raw.close()

    def close(self) -> None:
        self._raw.close()


class SegmentWriter:
    """Writes messages to the current segment; starts a new one past the size or time limit.

    Chunks are closed here (by ``chunk_size_kib`` and ``flush_s``), not inside the mcap
    writer, so that ``messages`` counts exactly what is on disk in complete chunks. The disk
    refusing a write (ENOSPC, EIO, ...) or free space falling under ``min_free_mib`` pauses
    recording with one log line; the segment keeps what was written (finished cleanly when
    there is still room, else cut back to its last complete chunk: readable either way);
    recording resumes in a new segment once there is room again. ``put`` never raises for
    the disk: the robot goes on whatever the recorder's storage does.
    """

    def __init__(
        self, config: RecordingConfig, metadata: dict[str, dict[str, str]], started: datetime,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.metadata = metadata
        self.started = started
        self.monotonic = monotonic  # wall time between retries while paused
        self.paths: list[Path] = []
        self.messages = 0  # in complete chunks on disk: what a reader of the files gets
        self.lost = 0  # offered while paused, or in a chunk the disk refused
        self.state = "recording"  # or "paused"
        self.reason: str | None = None
        self._file: _WholeWrites | None = None
        self._writer: Writer | None = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._segment_t0 = 0.0
        self._last_flush = 0.0
        self._last_sync = -float("inf")  # session time of the last fsync
        self._pending = self._pending_bytes = 0  # in the open chunk
        self._good = 0  # offset just past the segment's last complete chunk
        self._finished_bytes = 0  # sizes of the finished segments
        self._floor = int(config.min_free_mib * MIB)
        self._resume_at = int(self._floor * RESUME_MARGIN) + config.chunk_size_kib * 1024 + MIB
        self._directory = segment_path(config.path, started, 0).parent
        self._retention = Retention(config.path, int(config.max_bytes), self._floor, config.delete_oldest,
                                    started=started.timestamp())
        self._retry_s = RETRY_S
        self._next_retry = 0.0

    @property
    def on_disk_bytes(self) -> int:
        """Bytes of this session on disk (finished segments + the open one's complete chunks)."""
        return self._finished_bytes + self._good

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "messages": self.messages, "lost": self.lost,
                "mib": round(self.on_disk_bytes / MIB, 1), "reason": self.reason}

    def open(self, t: float) -> Path | None:
        """Start the next segment at session time ``t`` (s); None (paused) without room for it."""
        self._prune(None, 0)
        free = free_bytes(self._directory)
        if free is not None and free < self._floor:
            self._pause(f"free space {free / MIB:.1f} MiB is below recording.min_free_mib "
                        f"({self.config.min_free_mib:g} MiB)", error=False)
            return None
        try:
            return self._open(t)
        except OSError as err:
            self._refused(err)
            return None

    def _open(self, t: float) -> Path:
        path = segment_path(self.config.path, self.started, len(self.paths))
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = _WholeWrites(path)
        self.paths.append(path)
        self._good = 0
        self._writer = Writer(
            self._file,  # type: ignore[arg-type]
            chunk_size=1 << 62,  # never closes a chunk itself: _flush does
            compression=_COMPRESSION[self.config.compression],
            enable_data_crcs=True,  # DataEnd's CRC covers what chunk CRCs do not: header, metadata, indexes
        )
        self._writer.start(profile=MCAP_PROFILE, library=LIBRARY)
        for name, data in self.metadata.items():
            segment = {**data, "segment": str(len(self.paths) - 1)} if name == "respecd.session" else data
            self._writer.add_metadata(name, segment)
        self._writer.flush()  # header + metadata reach the disk before any frame
        self._good = self._file.tell()
        self._schemas.clear()
        self._channels.clear()
        self._segment_t0 = self._last_flush = t
        self.state, self.reason, self._retry_s = "recording", None, RETRY_S
        log.info("record.segment", path=str(path), index=len(self.paths) - 1)
        return path

    def write(
        self, topic: str, schema: str, channel_meta: dict[str, str], log_ns: int, payload: bytes, t: float
    ) -> None:
        """Append one message; close the chunk, rotate, by size and session time (OSError: the disk)."""
        if self._writer is None and self.open(t) is None:
            self.lost += 1
            return
        assert self._writer is not None
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
        self._pending += 1
        self._pending_bytes += len(payload)
        if self._pending_bytes >= self.config.chunk_size_kib * 1024 or t - self._last_flush >= self.config.flush_s:
            self._flush(t)
        too_big = self._good >= self.config.rotate_mib * MIB
        too_old = self.config.rotate_s > 0 and t - self._segment_t0 >= self.config.rotate_s
        if self._writer is not None and (too_big or too_old):
            self.finish()
            self.open(t)

    def _flush(self, t: float) -> None:
        """Close the open chunk: readable after a crash from here on. With ``fsync``, also on
        the disk (a power cut keeps it) once per ``flush_s``: a chunk closed by size in between
        reaches the disk with the next fsync (at 10 MB/s of frames a 1 MiB chunk closes every
        0.1 s, and an fsync per chunk cost more CPU than compressing it)."""
        assert self._writer is not None and self._file is not None
        self._writer.flush()
        if self.config.fsync and t - self._last_sync >= self.config.flush_s:
            os.fsync(self._file.fileno())
            self._last_sync = t
        self.messages += self._pending
        self._pending = self._pending_bytes = 0
        self._good = self._file.tell()
        self._last_flush = t
        self._prune(self.paths[-1], self._good)
        free = free_bytes(self._directory)
        if free is not None and free < self._floor:
            self.finish()  # summary and footer while there is still room for them
            self._pause(f"free space {free / MIB:.1f} MiB is below recording.min_free_mib "
                        f"({self.config.min_free_mib:g} MiB)", error=False)

    # -- the recorder's sink interface --------------------------------------------------
    def wants(self, topic: str) -> bool:
        return True  # a log keeps every channel it was asked to record

    def put(self, message: Message, log_ns: int, t: float) -> None:
        if self.state == "paused":
            self.lost += 1
            self._maybe_resume(t)
            return
        try:
            self.write(message.topic, message.schema, message.channel_meta, log_ns, message.payload, t)
        except OSError as err:
            self._refused(err)

    def close(self) -> None:
        try:
            self.finish()
        except OSError as err:
            self._refused(err)

    def finish(self) -> None:
        """Write the summary and footer of the current segment and close it (idempotent)."""
        if self._writer is None or self._file is None:
            return
        writer, file, self._writer = self._writer, self._file, None
        writer.finish()
        self.messages += self._pending
        self._pending = self._pending_bytes = 0
        self._finished_bytes += file.tell()
        self._good = 0
        self._file = None
        file.close()

    # -- when the disk says no ----------------------------------------------------------
    def _refused(self, err: OSError) -> None:
        """The disk refused a write: keep the complete chunks, count the rest as lost, pause."""
        self.lost += self._pending
        self._pending = self._pending_bytes = 0
        file, self._file, self._writer = self._file, None, None
        if file is not None:
            try:
                file.cut(self._good)  # the refused chunk's first half would only confuse readers
                if self._good == 0:  # not even the header made it: no file at all
                    self.paths.pop().unlink()
            except OSError:
                pass
            self._finished_bytes += self._good
            self._good = 0
        self._pause(f"{err.strerror or err} ({type(err).__name__})", error=True,
                    space=err.errno in (errno.ENOSPC, errno.EDQUOT))

    def _pause(self, reason: str, error: bool, space: bool = True) -> None:
        """One line per change of reason; retries back off while the same reason persists."""
        self._next_retry = self.monotonic() + self._retry_s
        if self.state == "paused" and self.reason == reason:
            self._retry_s = min(self._retry_s * 2, MAX_RETRY_S)
            return
        self.state, self.reason = "paused", reason
        fields = {"path": str(self.paths[-1]) if self.paths else None, "reason": reason, "written": self.messages,
                  "written_mib": round(self.on_disk_bytes / MIB, 1), "lost": self.lost,
                  "resumes": f"when {self._resume_at / MIB:.0f} MiB are free (checked every {self._retry_s:g}+ s)"
                  if space else f"if a retry succeeds (every {self._retry_s:g}+ s)"}
        if error:
            log.error("record.paused", **fields)
        else:
            log.warning("record.paused", **fields)

    def _prune(self, open_path: Path | None, open_size: int) -> None:
        for gone in self._retention.enforce(self.paths, open_path, open_size):
            if gone.path in self.paths:  # an earlier segment of this session
                self._finished_bytes -= gone.size

    def _maybe_resume(self, t: float) -> None:
        if self.monotonic() < self._next_retry:
            return
        self._prune(None, 0)
        free = free_bytes(self._directory)
        if free is not None and free < self._resume_at:
            self._next_retry = self.monotonic() + self._retry_s
            return
        reason = self.reason
        path = self.open(t)
        if path is not None:
            log.info("record.resumed", path=str(path), after=reason, lost=self.lost)


def _version() -> str:
    try:
        return metadata.version("respecd")
    except metadata.PackageNotFoundError:
        return "unknown"


def profile_document(profile: Profile | Mapping[str, Any]) -> dict[str, Any]:
    """The profile as the log stores it: its JSON form (a test rig may give that form directly)."""
    return profile.model_dump(mode="json") if isinstance(profile, BaseModel) else dict(profile)


def session_metadata(dump: Mapping[str, Any], started: datetime, t0: float, epoch_ns: int) -> dict[str, dict[str, str]]:
    """MCAP metadata records: the profile used (its JSON form) and the session's time origin."""
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
