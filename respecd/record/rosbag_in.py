"""A robot's bag as a replay source: rosbag2 (MCAP or sqlite3 storage) or ROS 1, read with
``rosbags``, presenting the same interface as a respecd log (``SessionLog``), so ``--replay``
feeds it through the same pipeline with the same counterfactual replay drivers.

Which topic is which sensor comes from a topic map (``--topics rgb=/cam/image_raw,imu=...``);
without one it is guessed from message types and topic names (``guess_topics``). Sensors are
named after the map's keys. Frames are converted to respecd's conventions:

* ``sensor_msgs/Image`` / ``CompressedImage``: colour to BGR uint8 (mono RGB cameras are
  replicated to 3 channels); 16-bit kept exact; float depth (REP 118, metres) to uint16 mm;
  ``compressedDepth`` PNGs (image_transport's 12-byte header) decoded;
* ``sensor_msgs/PointCloud2``: x, y, z (REP 103: x forward, y left, z up) to TI's radar frame
  (x right, y forward, z up); radial velocity from a ``v``/``velocity``/``doppler`` field and
  SNR from ``snr``/``intensity`` when present, else 0;
* ``sensor_msgs/Imu``: linear acceleration and angular velocity.

Times are bag receive times, in seconds from the start of the bag.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import structlog

from respecd import filekind, pathkind
from respecd.errors import InputError, UndecodableImageError
from respecd.messages import Frame, Modality
from respecd.record.bag_layout import bag_root, check_layout, metadata_mismatches, storage_sources
from respecd.record.reader import ChannelInfo, Demux
from respecd.record.ros_image import image_pixels

log = structlog.get_logger(__name__)

MODALITIES: tuple[Modality, ...] = ("rgb", "thermal", "radar", "depth", "imu")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
POINTS_TYPE = "sensor_msgs/msg/PointCloud2"
IMU_TYPE = "sensor_msgs/msg/Imu"
_VELOCITY = ("v", "velocity", "doppler", "radial_velocity")
_SNR = ("snr", "intensity", "power")
_PC2_DTYPES = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}
SKIPPED_LISTED = 5  # bad messages named per topic in the report (the rest are counted)
_DESERIALIZE = threading.Lock()  # every replay driver reads its topic in a read-ahead thread of its own


def is_bag(path: str | Path) -> bool:
    """A rosbag2 directory (or one of its storage files), a ROS 2 ``.mcap`` on its own (what
    ``ros2 bag record -s mcap`` writes, copied without its metadata.yaml) or a ROS 1 ``.bag``."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").exists()  # whatever it is: the layout check says what is wrong with it
    if p.suffix == ".bag":
        return True
    return p.suffix in (".mcap", ".db3") and (p.parent / "metadata.yaml").exists() or is_ros2_mcap(p)


def is_ros2_mcap(path: Path) -> bool:
    """An MCAP file whose header names the ``ros2`` profile (rosbag2's storage plugin and
    rosbags write it; respecd's own logs name none)."""
    if pathkind.problem(path, "an MCAP file"):
        return False  # a FIFO or a device is read by nobody here (open_log refuses it, naming it)
    try:
        head = filekind.read_head(path)
    except OSError:
        return False
    # magic, then the Header record: opcode 0x01, u64 length, profile as u32 length + bytes
    if not head.startswith(filekind.MCAP_MAGIC) or head[8:9] != b"\x01" or len(head) < 25:
        return False
    size = struct.unpack_from("<I", head, 17)[0]
    return head[21 : 21 + size] == b"ros2"


def parse_topics(text: str | None, modalities: Iterable[str] = MODALITIES) -> dict[str, str]:
    """``rgb=/cam/image_raw,imu=/imu/data`` -> {"rgb": "/cam/image_raw", ...} (InputError if malformed)."""
    if not text:
        return {}
    mapping: dict[str, str] = {}
    for item in text.split(","):
        name, sep, topic = item.strip().partition("=")
        if not sep or not name or not topic.startswith("/"):
            raise InputError(f"--topics: {item.strip()!r}: expected NAME=/topic, e.g. rgb=/camera/image_raw")
        if name not in modalities:
            raise InputError(f"--topics: {name!r}: expected one of {', '.join(modalities)}")
        if name in mapping:
            raise InputError(f"--topics: {name} is given twice ({name}={mapping[name]} and {name}={topic}); "
                             "expected one topic per sensor")
        mapping[name] = topic
    return mapping


@dataclass
class BagLog:
    """A foreign bag, described like a ``SessionLog`` (no profile, no percepts, no truth)."""

    path: Path
    topic_map: dict[str, str]  # sensor name (= modality) -> topic
    channels: dict[str, ChannelInfo] = field(default_factory=dict)  # every topic in the bag
    start_ns: int = 0
    end_ns: int = 0
    message_count: int = 0
    size: int = 0
    truncated: bool = False
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    skipped: dict[str, dict[int, str]] = field(default_factory=dict)  # topic -> index in the topic -> why
    sources: list[Path] = field(default_factory=list)  # what rosbags reads (storage_sources)
    metadata_notes: list[str] = field(default_factory=list)  # metadata.yaml's claims the storage disproved
    _demux: Demux | None = field(default=None, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def duration_s(self) -> float:
        return max(0.0, (self.end_ns - self.start_ns) / 1e9)

    @property
    def sensors(self) -> dict[str, Modality]:
        return {name: name for name in self.topic_map}  # type: ignore[misc]

    def profile_dict(self) -> None:
        return None  # a robot's bag carries no respecd profile

    def frame_count(self, sensor: str) -> int:
        return self.channels[self.topic_map[sensor]].count

    def side_data(self, rgb_sensor: str | None) -> tuple[list[tuple[float, Any]], list[dict[str, Any]]]:
        return [], []  # no ground truth, no recorded percepts

    def json_messages(self, topic: str) -> Iterator[dict[str, Any]]:
        return iter(())

    def messages(self, topics: Iterable[str]) -> Iterator[tuple[str, Any, int, bytes]]:
        """(topic, (deserialize, connection), receive time ns, raw cdr/ros1 bytes) in bag order.

        ``deserialize`` is bound to the bag's typestore: a message parked in a ``Demux`` may
        be decoded after the reader has closed, and a closed ``AnyReader`` has swapped its
        typestore for an empty one (KeyError on the message type)."""
        from rosbags.highlevel import AnyReader

        wanted = set(topics)
        with AnyReader(self.sources or [bag_root(self.path)]) as reader:
            store = reader.typestore
            deserialize = store.deserialize_cdr if reader.is2 else store.deserialize_ros1
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, ns, raw in reader.messages(connections=connections):
                yield connection.topic, (deserialize, connection), ns, raw

    def shared_demux(self) -> Demux:
        if self._demux is None:
            owner = {topic: name for name, topic in self.topic_map.items()}
            self._demux = Demux(self.messages(owner), owner)
        return self._demux

    def frames(self, sensor: str, demux: Demux | None = None, lazy: bool = False) -> Iterator[Frame]:
        """A topic's messages as Frames (``lazy`` is accepted for the SessionLog interface; a
        bag's images are converted as they are read)."""
        topic = self.topic_map[sensor]
        messages = demux.messages_for(sensor) if demux is not None else self.messages([topic])
        for seq, (_, (deserialize, connection), ns, raw) in enumerate(messages):
            try:
                with _DESERIALIZE:  # rosbags builds its deserializers on first use: not thread-safe
                    msg = deserialize(raw, connection.msgtype)
                data = to_array(msg, connection.msgtype, sensor)  # type: ignore[arg-type]
                frame_id = msg.header.frame_id
            except Exception as err:  # noqa: BLE001 - a robot's bag is foreign data: whatever one message is,
                self._skip(topic, seq, err)  # it costs that message, never the rest of the sensor's replay
                continue
            yield Frame(modality=sensor, t=(ns - self.start_ns) / 1e9, seq=seq, data=data,  # type: ignore[arg-type]
                        meta={"topic": topic, "frame_id": frame_id})

    def _skip(self, topic: str, index: int, err: Exception) -> None:
        """A message that does not deserialize or convert: counted per topic, the first one logged."""
        why = f"{type(err).__name__}: {err}"[:300]
        with self._lock:
            entries = self.skipped.setdefault(topic, {})
            if index in entries:
                return  # met again by another pass over the bag (the first frames, then the replay)
            entries[index] = why
        if len(entries) == 1:
            log.warning("bag.message_skipped", path=str(self.path), topic=topic, index=index, why=why,
                        note="further bad messages of this topic are counted and reported at the end")

    def skipped_report(self) -> dict[str, dict[str, Any]]:
        """Per topic: how many messages were skipped, and the first few (index in the topic, why)."""
        with self._lock:
            return {topic: {"count": len(entries),
                            "first": [{"index": i, "why": w} for i, w in sorted(entries.items())[:SKIPPED_LISTED]]}
                    for topic, entries in self.skipped.items()}


def open_bag(path: str | Path, topics: dict[str, str] | None, warn: bool = True) -> BagLog:
    """Describe a bag; check the topic map against it (InputError naming what is wrong). What
    metadata.yaml claimed wrongly is in ``metadata_notes`` (logged unless ``warn`` is off)."""
    from rosbags.highlevel import AnyReader

    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or directory (expected a rosbag2 directory or a ROS 1 .bag)")
    metadata = check_layout(p)
    sources, notes = storage_sources(p, metadata)
    bag = BagLog(path=p, topic_map={}, sources=sources)
    try:
        with AnyReader(sources) as reader:
            for c in reader.connections:
                info = bag.channels.setdefault(c.topic, ChannelInfo(c.topic, c.msgtype, {}, 0, c.msgtype))
                info.count += c.msgcount
            bag.start_ns, bag.end_ns = reader.start_time, reader.end_time
            bag.message_count = reader.message_count
            guessed = guess_topics(bag.channels)
    except InputError:
        raise
    except Exception as err:  # rosbags' own errors: unreadable metadata, unknown storage, bad chunk
        raise InputError(f"{p}: cannot read as a ROS bag: {err}") from err
    if metadata is not None and sources != [bag_root(p)]:
        counts = {topic: c.count for topic, c in bag.channels.items()}
        notes += metadata_mismatches(metadata, bag.start_ns, bag.end_ns, bag.message_count, counts)
    bag.metadata_notes = notes
    for note in notes if warn else ():
        log.warning("bag.metadata_mismatch", path=str(bag_root(p) / "metadata.yaml"), claim=note,
                    used="the storage's own numbers")
    bag.size = sum(f.stat().st_size for f in ([p] if p.is_file() else p.iterdir()) if f.is_file())
    bag.topic_map = dict(topics) if topics else guessed
    _check_topics(bag)
    return bag


def _check_topics(bag: BagLog) -> None:
    kinds = {"imu": (IMU_TYPE,), "radar": (POINTS_TYPE,)}
    for name, topic in bag.topic_map.items():
        info = bag.channels.get(topic)
        if info is None:
            raise InputError(f"{bag.path}: --topics {name}={topic}: no such topic (the bag has: "
                             f"{', '.join(sorted(bag.channels)) or 'none'})")
        allowed = kinds.get(name, IMAGE_TYPES)
        if info.schema not in allowed:
            raise InputError(f"{bag.path}: --topics {name}={topic}: {info.schema} cannot be a {name} sensor "
                             f"(expected {' or '.join(allowed)})")


def guess_topics(channels: dict[str, ChannelInfo]) -> dict[str, str]:
    """One topic per modality from message types and names: images named like depth or
    thermal are those, any other image is RGB (a colour-named topic preferred); the first
    PointCloud2 is the radar, the first Imu the IMU."""
    guess: dict[str, str] = {}
    for topic in sorted(channels):
        msgtype, lower = channels[topic].schema, topic.lower()
        if msgtype in IMAGE_TYPES:
            kind = _image_kind(lower)
            if kind == "rgb" and "rgb" in guess and _colour_named(lower) and not _colour_named(guess["rgb"].lower()):
                guess["rgb"] = topic
            guess.setdefault(kind, topic)
        elif msgtype == POINTS_TYPE:
            guess.setdefault("radar", topic)
        elif msgtype == IMU_TYPE:
            guess.setdefault("imu", topic)
    return guess


def _image_kind(lower: str) -> Modality:
    if any(k in lower for k in ("depth", "disparity")):
        return "depth"
    if any(k in lower for k in ("thermal", "flir", "lwir", "boson", "lepton")):
        return "thermal"
    return "rgb"


def _colour_named(lower: str) -> bool:
    return any(k in lower for k in ("color", "colour", "rgb"))


# -- message conversion ---------------------------------------------------------------------
def to_array(msg: Any, msgtype: str, modality: Modality) -> np.ndarray:
    if msgtype == "sensor_msgs/msg/Image":
        return _image(msg, modality)
    if msgtype == "sensor_msgs/msg/CompressedImage":
        return _compressed(msg, modality)
    if msgtype == POINTS_TYPE:
        return _points(msg)
    if msgtype == IMU_TYPE:
        a, g = msg.linear_acceleration, msg.angular_velocity
        return np.array([a.x, a.y, a.z, g.x, g.y, g.z], dtype=np.float32)
    raise ValueError(f"cannot convert {msgtype}")


def _image(msg: Any, modality: Modality) -> np.ndarray:
    pixels = image_pixels(msg)  # colour as BGR, grey as it is (rosbags-image)
    return _to_modality(pixels, "bgr8" if pixels.ndim == 3 else "mono", modality)


def _compressed(msg: Any, modality: Modality) -> np.ndarray:
    raw = np.asarray(msg.data, dtype=np.uint8)
    if "compresseddepth" in msg.format.lower().replace(" ", ""):
        raw = raw[12:]  # image_transport's compressedDepth config header
    data = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
    if data is None:
        raise UndecodableImageError(f"undecodable {msg.format!r} image")
    return _to_modality(data, "bgr8" if data.ndim == 3 else "mono", modality)


def _to_modality(pixels: np.ndarray, enc: str, modality: Modality) -> np.ndarray:
    if pixels.ndim == 3 and pixels.shape[2] == 4:  # a decoded PNG with alpha
        pixels = cv2.cvtColor(pixels, cv2.COLOR_BGRA2BGR)
    if modality == "rgb" and pixels.ndim == 3 and pixels.dtype == np.uint16:  # 16-bit colour
        pixels = (pixels >> 8).astype(np.uint8)
    if modality == "rgb" and pixels.ndim == 2:
        if pixels.dtype != np.uint8:
            pixels = cv2.normalize(pixels, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)  # type: ignore[call-overload]
        pixels = cv2.cvtColor(pixels, cv2.COLOR_GRAY2BGR)  # the detector wants 3 channels
    if modality == "depth" and pixels.dtype == np.float32:
        pixels = np.nan_to_num(pixels * 1000.0, nan=0.0, posinf=0.0).clip(0, 65535).astype(np.uint16)  # m -> mm
    if modality in ("thermal", "depth") and pixels.ndim == 3:
        pixels = cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY)
    return pixels


def _points(msg: Any) -> np.ndarray:
    n = int(msg.width) * int(msg.height)
    fields = {f.name: f for f in msg.fields}
    if n == 0 or not {"x", "y", "z"} <= set(fields):
        return np.zeros((0, 5), np.float32)
    raw = np.asarray(msg.data, dtype=np.uint8)[: n * msg.point_step].reshape(n, msg.point_step)
    order = ">" if msg.is_bigendian else "<"

    def column(name: str) -> np.ndarray:
        f = fields[name]
        dtype = np.dtype(_PC2_DTYPES[f.datatype]).newbyteorder(order)  # type: ignore[arg-type]  # '<' or '>'
        cells = np.ascontiguousarray(raw[:, f.offset : f.offset + dtype.itemsize])
        return cells.view(dtype).reshape(n).astype(np.float32)

    def first(names: tuple[str, ...]) -> np.ndarray:
        name = next((k for k in names if k in fields), None)
        return column(name) if name else np.zeros(n, np.float32)

    x, y, z = column("x"), column("y"), column("z")
    points = np.stack([-y, x, z, first(_VELOCITY), first(_SNR)], axis=1)  # REP 103 -> TI (x right, y ahead)
    return points[np.isfinite(points[:, :3]).all(axis=1)].astype(np.float32)
