"""Record a live session to MCAP (and serve it live) without ever blocking the event loop.

The daemon calls the ``on_*`` taps from the loop; each tap only appends the (immutable)
message to a bounded deque. A worker thread encodes each message once (PNG/JPEG, Foxglove
protobuf, JSON) and hands it to its sinks: the MCAP segment writer and/or the Foxglove
live view. When the worker falls behind, the oldest message is dropped and counted
(``dropped``, shown in the status line): a recorder must never slow the robot down.
The worker wakes once per ``batch_s`` and encodes what queued in one burst: woken per
message it would start every encode with cold caches, which costs more CPU on the
simulated rover (docs/PERFORMANCE.md "record and replay").
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import structlog

from respecd.clock import Clock
from respecd.errors import UndecodableImageError
from respecd.messages import Bundle, Decision, Frame, Percept, SensorConfig
from respecd.priority import lower_thread_priority
from respecd.record import codec, events, png
from respecd.record.codec import Message
from respecd.record.config import RecordingConfig
from respecd.record.scene import PERIOD_S, Scene
from respecd.record.topics import (  # noqa: F401 - re-exported: the recorder's topics
    TOPIC_CONFIG,
    TOPIC_DECISION,
    TOPIC_DETECTIONS,
    TOPIC_PERCEPT,
    TOPIC_SYNC,
    raw_topic,
    sensor_topic,
)
from respecd.record.writer import SegmentWriter, profile_document, session_metadata

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)

# SIGTERM: the daemon gives every tap 1.5 s to close, then the process ends with os._exit.
# Queued frames are encoded for at most DRAIN_S; those still waiting are dropped (counted)
# so that finish() -- summary and footer, a few ms -- always runs inside that budget.
DRAIN_S = 0.8
CLOSE_TIMEOUT_S = 5.0
SENSOR_KINDS = ("frame", "raw")  # the costly ones to encode; the rest is always written



class Sink(Protocol):
    """Where encoded messages go (the MCAP writer, the live view); called from the worker."""

    def wants(self, topic: str) -> bool: ...
    def put(self, message: Message, log_ns: int, t: float) -> None: ...
    def close(self) -> None: ...


def _formats(config: RecordingConfig, profile: Mapping[str, Any]) -> codec.ImageFormats:
    perception = profile.get("perception") or {}
    return codec.ImageFormats(
        rgb=config.rgb_format, jpeg_quality=config.jpeg_quality, thermal=config.thermal_format,
        depth=config.depth_format, thermal_colormap=config.thermal_colormap,
        thermal_range_k=tuple(perception.get("thermal_range_k", (273.0, 313.0))),
        thermal_counts_per_k=float(perception.get("thermal_counts_per_k", 100.0)),
    )


def _rgb_sensor(profile: Mapping[str, Any]) -> str | None:
    """Name of the profile's first RGB sensor."""
    for sensor in profile.get("sensors", []):
        if sensor.get("modality") == "rgb":
            return str(sensor.get("name"))
    return None


class Recorder:
    """Taps for the daemon; encoding and sink I/O in one worker thread.

    ``to_file`` writes the MCAP log; ``live`` (the Foxglove server) is another sink.
    ``drain_s``: how long ``close`` encodes queued frames before dropping the rest (the
    daemon's SIGTERM budget); None encodes them all, for a session on a simulated or
    lockstep clock, which can queue faster than real time and has no robot to let go.
    ``lossless``: a full queue also makes the tap wait for the worker instead of dropping
    (and ``close`` writes all that is queued); for a lockstep replay, whose clock is the log's
    and may run ahead of the encoder (never for a robot, whose loop must not wait).
    ``origin``: (session time, its log time in ns) instead of (now, the wall clock): a replay's
    log keeps the times of the log it replays. ``metadata``: more MCAP metadata records.
    """

    def __init__(
        self,
        config: RecordingConfig,
        profile: Profile | Mapping[str, Any],
        clock: Clock,
        live: Sink | None = None,
        to_file: bool = True,
        drain_s: float | None = DRAIN_S,
        *,
        lossless: bool = False,
        origin: tuple[float, int] | None = None,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
    ) -> None:
        """``profile``: the Profile, or its JSON form (what the log stores)."""
        self.config = config
        self.profile = profile_document(profile)
        self.clock = clock
        self.channels = frozenset(config.channels)
        self.dropped = 0
        self.errors = 0
        self.undecodable = 0  # replayed frames whose images did not decode (left out)
        self.cpu_s = 0.0  # worker thread CPU time, for the overhead benchmark
        self._formats = _formats(config, self.profile)
        self._scene = Scene(self.profile)
        self._live = live
        self._to_file = to_file
        self._sinks: list[Sink] = []
        self._calibrated: dict[str, tuple[int, int, float]] = {}  # sensor -> (width, height, session t)
        self._tf_t = -float("inf")
        self._queue: deque[tuple[str, str, Any]] = deque()
        # the live view wants every message now; a file only wants it eventually
        self._batch_s = 0.0 if live is not None else config.batch_s
        self._wake_at = max(1, config.queue_size // 2) if self._batch_s > 0 else 1
        self._cond = threading.Condition()
        self._closing = False
        self._drain_s = drain_s
        self._drain_until = float("inf")
        self._rgb_sensor = _rgb_sensor(self.profile)
        self._thread: threading.Thread | None = None
        self._segments: SegmentWriter | None = None
        self._epoch_ns = 0
        self._t0 = 0.0
        self._lossless = lossless
        if lossless:
            self._drain_s = None  # nothing queued is dropped at close either
        self._origin = origin
        self._metadata = {name: dict(fields) for name, fields in (metadata or {}).items()}

    @property
    def paths(self) -> list[Path]:
        return list(self._segments.paths) if self._segments else []

    @property
    def written(self) -> int:
        """Messages on disk in complete chunks (what a reader of the files gets)."""
        return self._segments.messages if self._segments else 0

    def recording_status(self) -> dict[str, Any]:
        """For the status line: recording or paused (and why), what is on disk, what was lost."""
        if self._segments is None:
            return {"state": "live" if self._live is not None else "off", "dropped": self.dropped}
        return {**self._segments.status(), "dropped": self.dropped}

    def start(self) -> Path | None:
        """Open the first segment (profile as metadata) and start the writer thread."""
        started = datetime.now(timezone.utc)
        self._t0, self._epoch_ns = self._origin or (self.clock.now(), time.time_ns())
        path = None
        if self._to_file:
            meta = {**session_metadata(self.profile, started, self._t0, self._epoch_ns), **self._metadata}
            self._segments = SegmentWriter(self.config, meta, started)
            path = self._segments.open(self._t0)
            self._sinks.append(self._segments)
        if self._live is not None:
            open_live = getattr(self._live, "open", None)
            if open_live is not None:
                open_live()
            self._sinks.append(self._live)
        # non-daemon: interpreter exit waits for finish(), so the summary is always written
        self._thread = threading.Thread(target=self._run, name="respecd-recorder")
        self._thread.start()
        log.info("record.start", path=str(path) if path else None, live=self._live is not None,
                 channels=sorted(self.channels), png_encoder=png.ENCODER)
        return path

    # -- taps, called on the event loop: O(1), never block ------------------------------
    def on_frame(self, sensor_name: str, frame: Frame) -> None:
        if "frames" in self.channels:
            self._put("frame", sensor_name, frame)
        raw = frame.meta.get("raw")
        if "radar_raw" in self.channels and isinstance(raw, (bytes, bytearray)):
            self._put("raw", sensor_name, frame)

    def on_bundle(self, bundle: Bundle) -> None:
        if "sync" in self.channels:
            self._put("sync", "", bundle)

    def on_percept(self, percept: Percept) -> None:
        if "percepts" in self.channels:
            self._put("percept", "", percept)

    def on_decision(self, decision: Decision) -> None:
        if "decisions" in self.channels:
            self._put("decision", "", decision)

    def on_config(self, sensor_name: str, applied: SensorConfig) -> None:
        if "configs" in self.channels:
            self._put("config", sensor_name, (self.clock.now(), applied))

    def _put(self, kind: str, name: str, item: Any) -> None:
        if self._thread is None or self._closing:
            return
        with self._cond:
            if self._lossless:
                while len(self._queue) >= self.config.queue_size and self._worker_alive():
                    self._cond.notify()  # the worker may be between batches: it has work now
                    self._cond.wait(0.1)
            if len(self._queue) >= self.config.queue_size:
                self._queue.popleft()
                self.dropped += 1
            self._queue.append((kind, name, item))
            if len(self._queue) >= self._wake_at:
                self._cond.notify()  # else the worker's batch_s timeout collects it

    def _worker_alive(self) -> bool:
        thread = self._thread
        return not self._closing and thread is not None and thread.is_alive()

    async def close(self) -> None:
        """Drain what is queued, finish the file (summary + footer); safe to call twice."""
        if self._thread is None:
            return
        with self._cond:
            self._closing = True
            if self._drain_s is not None:
                self._drain_until = time.monotonic() + self._drain_s
            self._cond.notify()
        thread, self._thread = self._thread, None
        await asyncio.to_thread(thread.join, CLOSE_TIMEOUT_S if self._drain_s is not None else None)
        if thread.is_alive():
            log.error("record.close_timeout", pending=len(self._queue))
        lost = self._segments.lost if self._segments else 0
        mib = round(self._segments.on_disk_bytes / 2**20, 1) if self._segments else 0.0
        log.info("record.closed", paths=[str(p) for p in self.paths], messages=self.written, mib=mib,
                 dropped=self.dropped, lost=lost, encode_errors=self.errors,
                 undecodable=self.undecodable)

    # -- worker thread -------------------------------------------------------------------
    def _run(self) -> None:
        lower_thread_priority()  # the loop keeps time, this only has to keep up
        cpu0 = time.thread_time()
        try:
            while True:
                with self._cond:
                    while not self._queue and not self._closing:
                        self._cond.wait(self._batch_s or None)
                    if not self._queue:
                        break
                    kind, name, item = self._queue.popleft()
                    if self._lossless:
                        self._cond.notify()  # a tap may be waiting for room
                if self._closing and kind in SENSOR_KINDS and time.monotonic() > self._drain_until:
                    self.dropped += 1  # shutting down and out of time: frames give way to finish()
                    continue
                try:
                    self._write(kind, name, item)
                except UndecodableImageError as err:  # a replayed log's damaged frame: input, not a bug here
                    self.undecodable += 1
                    if self.undecodable == 1:  # once: the perception stage names each sensor's first
                        log.warning("record.frame_undecodable", sensor=name or None, error=str(err))
                except Exception as err:  # noqa: BLE001 - thread boundary: one bad message must not end the log
                    self.errors += 1  # the disk's errors never get here (the file sink pauses): an encoding bug
                    if self.errors == 1:  # once, with the traceback; the count is in the closing line
                        log.warning("record.encode_failed", kind=kind, sensor=name or None, error=str(err),
                                    exc_info=True)
                self.cpu_s = time.thread_time() - cpu0
        finally:
            for sink in self._sinks:
                try:
                    sink.close()
                except Exception:  # noqa: BLE001 - thread boundary: the other sinks still close
                    log.exception("record.sink_close_failed", sink=type(sink).__name__)
            self.cpu_s = time.thread_time() - cpu0

    def _log_ns(self, t: float) -> int:
        return self._epoch_ns + max(0, round((t - self._t0) * 1e9))

    def _write(self, kind: str, name: str, item: Any) -> None:
        t = item[0] if kind == "config" else item.t
        self._scene_messages(t)
        if kind == "frame":
            self._write_frame(name, item)
        elif kind == "raw":
            ns = self._log_ns(item.t)
            self._emit(codec.encode_raw(item, name, ns), ns, item.t)
        else:
            if kind == "percept":
                self._write_annotations(item)
            payload, schema, topic = self._encode_own(kind, name, item)
            ns = self._log_ns(t)
            self._emit(Message(topic, schema, payload, {}), ns, t)

    def _emit(self, message: Message, log_ns: int, t: float) -> None:
        for sink in self._sinks:
            if sink.wants(message.topic):
                sink.put(message, log_ns, t)

    def _wanted(self, topic: str) -> bool:
        return any(sink.wants(topic) for sink in self._sinks)

    def _write_frame(self, name: str, frame: Frame) -> None:
        if not self._wanted(sensor_topic(name)):
            return  # live view only, nobody watching this sensor: no encoding at all
        ns = self._log_ns(frame.t)
        if frame.modality in ("rgb", "thermal", "depth") and frame.data.ndim >= 2:
            self._calibrate(name, frame, ns)
        for message in codec.encode_frame(frame, name, ns, self._formats):
            self._emit(message, ns, frame.t)

    def _calibrate(self, name: str, frame: Frame, log_ns: int) -> None:
        """A CameraCalibration at the first frame, at every size change and every PERIOD_S."""
        height, width = frame.data.shape[:2]
        last = self._calibrated.get(name)
        if last is not None and last[:2] == (width, height) and frame.t - last[2] < PERIOD_S:
            return
        self._calibrated[name] = (width, height, frame.t)
        message = self._scene.calibration(name, width, height, log_ns)
        if message is not None:
            self._emit(message, log_ns, frame.t)

    def _scene_messages(self, t: float) -> None:
        """The profile's frame transforms, every PERIOD_S of session time."""
        if t - self._tf_t >= PERIOD_S:
            self._tf_t = t
            ns = self._log_ns(t)
            self._emit(self._scene.transforms(ns), ns, t)

    def _write_annotations(self, percept: Percept) -> None:
        """Boxes over the RGB image they were detected in (same timestamp as that frame)."""
        rgb = percept.bundle.frames.get("rgb") if percept.bundle is not None else None
        if rgb is None:
            return
        ns = self._log_ns(rgb.t)
        meta = {"image_topic": sensor_topic(self._rgb_sensor)} if self._rgb_sensor else {}
        message = Message(TOPIC_DETECTIONS, "foxglove.ImageAnnotations", events.encode_annotations(percept, ns), meta)
        self._emit(message, ns, percept.t)

    @staticmethod
    def _encode_own(kind: str, name: str, item: Any) -> tuple[bytes, str, str]:
        if kind == "percept":
            return events.encode_percept(item), "respecd.Percept", TOPIC_PERCEPT
        if kind == "decision":
            return events.encode_decision(item), "respecd.Decision", TOPIC_DECISION
        if kind == "sync":
            return events.encode_bundle(item), "respecd.Sync", TOPIC_SYNC
        t, applied = item
        return events.encode_config(name, t, applied), "respecd.SensorConfig", TOPIC_CONFIG
