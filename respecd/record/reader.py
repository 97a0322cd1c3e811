"""Open a session log for replay and ``log info``: validate it, read its metadata, channels
and statistics, and stream its messages — also from a file cut short by a power loss.

A cleanly finished log has a summary at its end and is described from it without reading
the data. A cut log (no footer) is scanned sequentially up to its last complete record;
``truncated`` is then True and callers warn once. Records are read by ``walk``, which checks
every chunk's CRC: a damaged chunk is skipped, listed in ``damage`` and warned about once,
with its byte range, and reading goes on. ``open_log(verify=True)`` reads the whole file
first (``respecd log info``). Bad input raises ``InputError`` naming the file and what was
expected.
"""

from __future__ import annotations

import json
import mmap
import os
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema

from respecd import pathkind
from respecd.errors import InputError
from respecd.messages import Frame, Modality
from respecd.record import codec, legacy
from respecd.record.codec import LoggedSchema
from respecd.record.topics import meta_topic, raw_topic, sensor_topic
from respecd.record.walk import BAD_BYTES, MAGIC, Cut, Damage, check_summary, walk

log = structlog.get_logger(__name__)


@dataclass
class ChannelInfo:
    topic: str
    schema: str
    metadata: dict[str, str]
    count: int = 0
    encoding: str = "json"  # message encoding: "protobuf" for Foxglove types in format 2


@dataclass
class SessionLog:
    """What a log holds; messages are streamed on demand, never all loaded at once."""

    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    channels: dict[str, ChannelInfo] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    message_count: int = 0
    truncated: bool = False
    size: int = 0
    damage: list[Damage] = field(default_factory=list)  # unreadable stretches met so far
    warn: bool = True  # log a warning per damaged stretch (log info prints them itself)
    channel_ids: dict[int, tuple[str, LoggedSchema]] = field(default_factory=dict)  # from a CRC-checked summary
    _demux: Demux | None = field(default=None, repr=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def note_damage(self, damage: Damage) -> None:
        """Record a damaged stretch; warn once per stretch however many passes meet it."""
        with self._lock:
            if damage in self.damage:
                return
            self.damage.append(damage)
        if self.warn:
            log.warning("log.damaged", path=str(self.path), bytes=f"{damage.start}-{damage.end}",
                        size=damage.end - damage.start, reason=damage.reason, action="skipped")

    def shared_demux(self) -> Demux:
        """The one-pass reader all replay drivers of this log share (created on first use)."""
        if self._demux is None:
            owner = {topic(n): n for n in self.sensors for topic in (sensor_topic, raw_topic, meta_topic)}
            self._demux = Demux(self.messages(list(owner)), owner)
        return self._demux

    @property
    def duration_s(self) -> float:
        return max(0.0, (self.end_ns - self.start_ns) / 1e9)

    @property
    def sensors(self) -> dict[str, Modality]:
        """Sensor name -> modality, from the sensor channels' metadata."""
        return {
            c.metadata["sensor"]: c.metadata["modality"]  # type: ignore[misc]
            for c in self.channels.values()
            if c.topic == f"/sensors/{c.metadata.get('sensor')}"
        }

    def profile_dict(self) -> dict[str, Any] | None:
        """The profile the session ran with, as a plain dict (None when not recorded)."""
        entry = self.metadata.get("respecd.profile")
        if not entry or "json" not in entry:
            return None
        try:
            profile = json.loads(entry["json"])
        except ValueError as err:
            raise InputError(f"{self.path}: the recorded profile is damaged ({err}); "
                             "pass the profile the session ran with: --config FILE") from err
        if not isinstance(profile, dict):
            raise InputError(f"{self.path}: the recorded profile is damaged (not a mapping); pass --config FILE")
        return profile

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, LoggedSchema, int, bytes]]:
        """(topic, schema, log time ns, payload) in file order, up to a cut if any; damaged
        chunks are skipped (``note_damage``)."""
        wanted = set(topics) if topics is not None else None
        yield from _iter_messages(self.path, wanted, self.note_damage, self.channel_ids)

    def frames(self, sensor: str, demux: Demux | None = None, lazy: bool = False) -> Iterator[Frame]:
        """The sensor's logged frames in order; radar frames get their raw UART bytes back.

        With ``demux`` (shared by every sensor of a replay) the file is read once in all,
        instead of once per sensor. ``lazy``: JPEG and PNG frames are decoded when first read
        (``respecd.record.lazy``).
        """
        topics = [sensor_topic(sensor), raw_topic(sensor), meta_topic(sensor)]
        messages = demux.messages_for(sensor) if demux is not None else self.messages(topics)
        yield from _pair_frames(messages, sensor, self.sensors.get(sensor, "rgb"), lazy)

    def side_data(self, rgb_sensor: str | None) -> tuple[list[tuple[float, Any]], list[dict[str, Any]]]:
        """One pass for what a replay needs besides frames: the RGB frames' ground truth as
        (t, gt) — empty when the first RGB frame has none — and the recorded percepts."""
        rgb_topic = None
        if rgb_sensor:  # format 2 keeps time and truth in the FrameMeta channel, format 1 inline
            first_format = meta_topic(rgb_sensor) not in self.channels
            rgb_topic = sensor_topic(rgb_sensor) if first_format else meta_topic(rgb_sensor)
        truth: list[tuple[float, Any]] = []
        percepts: list[dict[str, Any]] = []
        want_truth = rgb_topic is not None
        for topic, schema, _, data in self.messages([t for t in (rgb_topic, "/respecd/percept") if t]):
            if topic == rgb_topic and want_truth:
                extra = legacy.frame_extra(data) if schema.name != "respecd.FrameMeta" else json.loads(data)
                meta = extra.get("meta") or {}
                if "gt" not in meta:
                    want_truth = False
                    truth.clear()
                    continue
                truth.append((float(extra["t"]), meta["gt"]))
            elif topic == "/respecd/percept":
                percepts.append(json.loads(data))
        return truth, percepts

    def frame_count(self, sensor: str) -> int:
        return self.channels[sensor_topic(sensor)].count

    def json_messages(self, topic: str) -> Iterator[dict[str, Any]]:
        for _, _, _, data in self.messages([topic]):
            yield json.loads(data)


def _pair_frames(
    messages: Iterable[tuple[str, LoggedSchema, int, bytes]], sensor: str, modality: Modality, lazy: bool = False
) -> Iterator[Frame]:
    """Decode one sensor's frame messages. Its FrameMeta (format 2) comes just before the
    frame with the same log time; a raw-bytes message right after it (same seq) joins it."""
    topic, meta = sensor_topic(sensor), meta_topic(sensor)
    pending: Frame | None = None
    stashed: tuple[int, dict[str, Any]] | None = None
    for t, schema, ns, data in messages:
        if t == meta:
            stashed = (ns, json.loads(data))
        elif t == topic:
            if pending is not None:
                yield pending
            frame_meta = stashed[1] if stashed is not None and stashed[0] == ns else None
            pending, stashed = codec.decode_frame(schema, data, modality, ns, frame_meta, lazy), None
        elif pending is not None:
            seq, raw = legacy.raw_bytes(data)
            if seq == pending.seq:
                pending.meta["raw"] = raw
                yield pending
                pending = None
    if pending is not None:
        yield pending


class Demux:
    """One pass over a log shared by several consumers (one per sensor, in worker threads).

    A consumer asking for its next message reads ahead under a lock, parking other sensors'
    messages in their own queues; the log interleaves sensors in time order and replay
    drivers consume at log pace, so the queues stay short. A queue that nobody drains is
    capped (oldest dropped) so a stopped driver cannot grow memory without bound.
    """

    MAX_PARKED = 4096

    def __init__(self, source: Iterator[tuple[str, Any, int, Any]], owner: dict[str, str]) -> None:
        """``source``: (topic, schema, log ns, data) in log order; ``owner``: topic -> sensor."""
        self._owner = owner
        self._source = source
        self._parked: dict[str, deque[tuple[str, Any, int, Any]]] = {n: deque() for n in set(owner.values())}
        self._lock = threading.Lock()
        self._done = False
        self.dropped = 0

    def next_for(self, sensor: str) -> tuple[str, Any, int, Any] | None:
        with self._lock:
            queue = self._parked[sensor]
            while not queue and not self._done:
                item = next(self._source, None)
                if item is None:
                    self._done = True
                    break
                owner = self._parked[self._owner[item[0]]]
                if len(owner) >= self.MAX_PARKED:
                    owner.popleft()
                    self.dropped += 1
                owner.append(item)
            return queue.popleft() if queue else None

    def messages_for(self, sensor: str) -> Iterator[tuple[str, Any, int, Any]]:
        while (item := self.next_for(sensor)) is not None:
            yield item


def _iter_messages(
    path: Path, wanted: set[str] | None, on_damage: Callable[[Damage], None],
    known: dict[int, tuple[str, LoggedSchema]],
) -> Iterator[tuple[str, LoggedSchema, int, bytes]]:
    """Messages of known channels. Channel and schema records outside chunks carry no CRC:
    those of an intact summary (``known``) win over the data section's, and a message whose
    channel was lost to damage is skipped (the damage is reported)."""
    schemas: dict[int, Schema] = {}
    topics: dict[int, tuple[str, LoggedSchema]] = dict(known)  # channel id -> (topic, schema)
    for record in walk(path):
        if isinstance(record, Message):
            channel = topics.get(record.channel_id)
            if channel is not None and (wanted is None or channel[0] in wanted):
                yield channel[0], channel[1], record.log_time, record.data
        elif isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            topics.setdefault(record.id, (record.topic, _logged_schema(record, schemas.get(record.schema_id))))
        elif isinstance(record, Damage):
            on_damage(record)


def _logged_schema(channel: Any, schema: Any) -> LoggedSchema:
    return LoggedSchema(schema.name if schema else "", channel.message_encoding, schema.data if schema else b"")


def open_log(path: str | Path, verify: bool = False, warn: bool = True) -> SessionLog:
    """Validate and describe a log; raise InputError for missing, empty or non-MCAP files.

    ``verify``: read every record and check every CRC now (``damage`` is then complete and
    the counts are what can really be read), instead of trusting an intact summary."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file (expected an MCAP session log written by respecd --record)")
    try:
        with pathkind.open_regular(p, "an MCAP session log") as f:  # a FIFO or a device: refused at once
            head = f.read(len(MAGIC))
            size = os.fstat(f.fileno()).st_size
    except OSError as err:  # a file we may not read (PermissionError), an I/O error
        raise InputError(f"{p}: cannot read session log: {err.strerror or err}") from err
    if size == 0:
        raise InputError(f"{p}: empty file (0 bytes), expected an MCAP session log")
    if head != MAGIC:
        raise InputError(f"{p}: not an MCAP file (byte 0: {head[:8]!r}, expected the MCAP magic {MAGIC!r})")
    session = SessionLog(path=p, size=size, warn=warn)
    summarized = _from_summary(session)  # also checks the summary's CRC
    if verify or not summarized:
        _scan(session, verify, into_summary=not session.damage)  # a damaged summary was reported already
    if session.message_count == 0 and not session.channels:
        cut = " (the file was cut before its first complete chunk)" if session.truncated else ""
        raise InputError(f"{p}: MCAP log holds no messages{cut}")
    return session


def _from_summary(session: SessionLog) -> bool:
    """Fill ``session`` from the summary section of a finished log; False if there is none
    or its CRC shows it damaged (the data are scanned instead)."""
    try:
        with open(session.path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            intact, start, end = check_summary(mm)
        if intact is False:
            session.note_damage(Damage(start, end, "summary section CRC mismatch: counts are read from the data"))
            return False
        with open(session.path, "rb") as f:
            reader = SeekingReader(f)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return False
            session.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    except (*BAD_BYTES, OSError):  # too short for a footer, or a cut file: scan it instead
        return False
    stats = summary.statistics
    for cid, ch in summary.channels.items():
        schema = summary.schemas.get(ch.schema_id)
        session.channels[ch.topic] = ChannelInfo(
            ch.topic, schema.name if schema else "", dict(ch.metadata), stats.channel_message_counts.get(cid, 0),
            ch.message_encoding,
        )
        if intact:  # CRC-checked: trusted over the data section's copies
            session.channel_ids[cid] = (ch.topic, _logged_schema(ch, schema))
    session.start_ns, session.end_ns = stats.message_start_time, stats.message_end_time
    session.message_count = stats.message_count
    return True


def _scan(session: SessionLog, verify: bool = False, into_summary: bool = True) -> None:
    """Read a log record by record, up to its cut: what can really be read. Past the data
    section too (``into_summary``), so that a file cut inside its summary counts as cut."""
    schemas: dict[int, str] = {}
    by_id: dict[int, ChannelInfo] = {}
    session.channels.clear()  # counted again from what is really there
    session.message_count = session.start_ns = session.end_ns = 0
    for record in walk(session.path, stop_at_data_end=not into_summary, verify=verify):
        if isinstance(record, Message):
            if record.channel_id in by_id:
                _count(session, by_id[record.channel_id], record.log_time)
        elif isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Channel) and record.id not in by_id:
            by_id[record.id] = ChannelInfo(record.topic, schemas.get(record.schema_id, ""), dict(record.metadata),
                                           encoding=record.message_encoding)
            session.channels[record.topic] = by_id[record.id]
        elif isinstance(record, Metadata):
            session.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Damage):
            session.note_damage(record)
        elif isinstance(record, Cut):
            session.truncated = True


def _count(session: SessionLog, channel: ChannelInfo, log_time: int) -> None:
    channel.count += 1
    session.message_count += 1
    if session.message_count == 1 or log_time < session.start_ns:
        session.start_ns = log_time
    session.end_ns = max(session.end_ns, log_time)
