"""What a bag must look like before rosbags reads it: a ROS 1 bag's header, a rosbag2's
metadata.yaml field by field and the storage files it lists — said in respecd's words (the
file, the field or byte offset, what was expected), where rosbags would trip over with its
own ("'int' object is not subscriptable"), or block (a FIFO listed as a storage file).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path, PurePath
from typing import Any

from respecd import filekind, pathkind
from respecd.errors import InputError
from respecd.filekind import ROS1_MAGIC

TIME_SLACK_NS = 1_000_000  # metadata.yaml times within 1 ms of the storage's are the same times


def lone_storage(path: Path) -> bool:
    """A ROS 2 .mcap without the metadata.yaml of a rosbag2 folder beside it."""
    return path.suffix == ".mcap" and not (path.parent / "metadata.yaml").exists()


def bag_root(path: Path) -> Path:
    """What rosbags opens: the bag's folder, or a lone .mcap itself (rosbags reads it raw)."""
    if lone_storage(path):
        return path
    return path.parent if path.suffix in (".mcap", ".db3") else path


ROS2_LAYOUT = "a rosbag2 is a folder with metadata.yaml and its .mcap or .db3 files"
ROS1_EXPECTED = f"expected a ROS 1 bag, which starts with {ROS1_MAGIC!r} ({ROS2_LAYOUT})"
METADATA_MAX_BYTES = 16 * 2**20


def check_layout(p: Path) -> dict[str, Any] | None:
    """What rosbags would trip over with a message of its own (a UnicodeDecodeError for a
    binary header, "'int' object is not subscriptable" for a metadata.yaml of the wrong
    shape), said in our words: the file, the field or byte offset, and what was expected.
    A rosbag2's ``rosbag2_bagfile_information`` (checked); None for a ROS 1 bag or a lone .mcap."""
    if lone_storage(p):
        return None  # no metadata.yaml to check: rosbags reads the MCAP's own summary
    if p.is_dir() or p.suffix in (".mcap", ".db3"):
        return _check_metadata(bag_root(p) / "metadata.yaml")
    _check_ros1(p)
    return None


def storage_sources(p: Path, info: dict[str, Any] | None) -> tuple[list[Path], list[str]]:
    """What rosbags is to read, and what metadata.yaml claimed wrongly about it. A rosbag2's
    storage files are read each once and on their own, so that counts and times come from the
    storage's own indexes: metadata.yaml's numbers are only a claim (a huge duration made a
    replay run forever, a count of 7 replayed 7 of 30 frames, a file listed twice replayed
    every message twice). A compressed rosbag2 (rare) is read through its folder."""
    if info is None:
        return [p], []
    root = bag_root(p)
    if str(info.get("compression_mode") or "").lower() not in ("", "none"):
        return [root], []
    files: list[Path] = []
    notes = []
    for name in info["relative_file_paths"]:
        path = root / PurePath(name).name
        if path in files:
            notes.append(f"relative_file_paths lists {PurePath(name).name} more than once (read once)")
        else:
            files.append(path)
    return files, notes


def metadata_mismatches(info: dict[str, Any], start_ns: int, end_ns: int, total: int,
                        counts: dict[str, int]) -> list[str]:
    """Where metadata.yaml's numbers disagree with the storage's (``end_ns`` as rosbags gives it:
    one past the last message)."""
    span = end_ns - 1 - start_ns if total else 0
    claims = []
    duration = info["duration"]["nanoseconds"]
    if abs(duration - span) > TIME_SLACK_NS:
        claims.append(f"duration {duration / 1e9:.3f} s, the storage's messages span {span / 1e9:.3f} s")
    started = info["starting_time"]["nanoseconds_since_epoch"]
    if total and abs(started - start_ns) > TIME_SLACK_NS:
        claims.append(f"starting_time {started} ns, the storage's first message is at {start_ns} ns")
    if info["message_count"] != total:
        claims.append(f"message_count {info['message_count']}, the storage holds {total}")
    for entry in info["topics_with_message_count"]:
        topic, claimed = entry["topic_metadata"]["name"], entry["message_count"]
        if claimed != counts.get(topic, 0):
            claims.append(f"{topic}: message_count {claimed}, the storage holds {counts.get(topic, 0)}")
    return claims


def _check_ros1(p: Path) -> None:
    try:
        with pathkind.open_regular(p, "a ROS 1 bag") as handle:
            head = handle.read(filekind.HEAD)
            size = os.fstat(handle.fileno()).st_size
            header = _ros1_bag_header(handle) if head.startswith(ROS1_MAGIC) else None
    except OSError as err:
        raise InputError(f"{p}: cannot read bag: {err.strerror or err}") from err
    if not head:
        raise InputError(f"{p}: empty file (0 bytes), {ROS1_EXPECTED}")
    if not head.startswith(ROS1_MAGIC):
        pairs = zip(head, ROS1_MAGIC, strict=False)
        at = next((i for i, (a, b) in enumerate(pairs) if a != b), min(len(head), len(ROS1_MAGIC)))
        raise InputError(f"{p}: not a ROS 1 bag: byte {at} is {head[at:at + 1]!r} "
                         f"(the file looks like {filekind.describe(head, p)}); {ROS1_EXPECTED}")
    if header is None:
        raise InputError(f"{p}: ROS 1 bag cut inside its bag header record (byte {len(ROS1_MAGIC)}; the file "
                         f"is {size} bytes)")
    index_pos = header.get(b"index_pos")
    if index_pos is not None and len(index_pos) == 8:
        pos = struct.unpack("<Q", index_pos)[0]
        if pos > size:
            raise InputError(f"{p}: ROS 1 bag is cut: its index is at byte {pos}, past the end of the file "
                             f"({size} bytes); `rosbag reindex` can rebuild it from the messages")


def _ros1_bag_header(handle: Any) -> dict[bytes, bytes] | None:
    """The fields of the bag header record right after the magic line (None: the file ends inside it)."""
    handle.seek(len(ROS1_MAGIC))
    raw = handle.read(4)
    if len(raw) < 4:
        return None
    length = struct.unpack("<I", raw)[0]
    if length > 2**20:
        return {}  # not a plausible header: rosbags names what is wrong with it
    body = handle.read(length)
    if len(body) < length:
        return None
    fields, pos = {}, 0
    while pos + 4 <= len(body):
        n = struct.unpack_from("<I", body, pos)[0]
        name, _, value = body[pos + 4 : pos + 4 + n].partition(b"=")
        fields[name] = value
        pos += 4 + n
    return fields


_R2_FIELDS: dict[str, type] = {  # what rosbags reads from rosbag2_bagfile_information
    "version": int, "storage_identifier": str, "relative_file_paths": list, "duration": dict,
    "starting_time": dict, "message_count": int, "topics_with_message_count": list,
}
_R2_NESTED: dict[str, dict[str, type]] = {"duration": {"nanoseconds": int},
                                          "starting_time": {"nanoseconds_since_epoch": int}}
_R2_TOPIC: dict[str, type] = {"message_count": int, "topic_metadata": dict}
_R2_TOPIC_META: dict[str, type] = {"name": str, "type": str, "serialization_format": str}
_KIND = {int: "an integer", str: "a text", list: "a list", dict: "a mapping"}
_TAGS = {int: "tag:yaml.org,2002:int", str: "tag:yaml.org,2002:str"}


def _check_metadata(meta: Path) -> dict[str, Any] | None:
    """A rosbag2's metadata.yaml, field by field: FILE:LINE: field: expected ..., got ..."""
    import yaml

    if not meta.exists():
        return None  # rosbags says which file is missing
    try:
        with pathkind.open_regular(meta, "a rosbag2 metadata.yaml") as handle:
            data = handle.read(METADATA_MAX_BYTES + 1)
        if len(data) > METADATA_MAX_BYTES:
            raise InputError(f"{meta}: more than {METADATA_MAX_BYTES} bytes, expected a rosbag2 metadata.yaml")
        root = yaml.compose(data.decode("utf-8"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    except OSError as err:
        raise InputError(f"{meta}: cannot read: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raise InputError(f"{meta}: not UTF-8 text at byte {err.start}; expected a rosbag2 metadata.yaml") from err
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        at = f":{mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err).splitlines()[0]
        raise InputError(f"{meta}{at}: not valid YAML: {problem}") from err
    info = _field(meta, root, (), {"rosbag2_bagfile_information": dict})["rosbag2_bagfile_information"]
    fields = _field(meta, info, ("rosbag2_bagfile_information",), _R2_FIELDS)
    for name, nested in _R2_NESTED.items():
        _field(meta, fields[name], ("rosbag2_bagfile_information", name), nested)
    for i, path_node in enumerate(fields["relative_file_paths"].value):
        _expect(meta, path_node, ("rosbag2_bagfile_information", "relative_file_paths", i), str)
        _check_storage_file(meta, path_node, i)
    for i, topic in enumerate(fields["topics_with_message_count"].value):
        where = ("rosbag2_bagfile_information", "topics_with_message_count", i)
        _expect(meta, topic, where, dict)
        entry = _field(meta, topic, where, _R2_TOPIC)
        _field(meta, entry["topic_metadata"], (*where, "topic_metadata"), _R2_TOPIC_META)
    loaded = yaml.load(data, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))  # noqa: S506 - a safe loader
    return dict(loaded["rosbag2_bagfile_information"])


def _check_storage_file(meta: Path, node: Any, i: int) -> None:
    """A storage file metadata.yaml lists is a regular file inside the bag (rosbags opens it: a FIFO
    there would block the open, and SIGTERM with it); a missing one rosbags names itself."""
    where = f"{meta}:{node.start_mark.line + 1}: rosbag2_bagfile_information.relative_file_paths.{i}"
    name = PurePath(node.value).name  # as rosbags reads it: the name, in the bag's folder
    problem = pathkind.problem(meta.parent / name, "a rosbag2 storage file (.mcap or .db3)")
    if problem:
        raise InputError(f"{where}: {problem}")


def _field(meta: Path, node: Any, where: tuple[Any, ...], wanted: dict[str, type]) -> dict[str, Any]:
    """The children ``wanted`` of a mapping node, each of the type it must have."""
    import yaml

    if not isinstance(node, yaml.MappingNode):
        keys = ", ".join(wanted)
        _expect(meta, node, where, dict, f" (with {keys})")
    found: dict[str, Any] = {}
    for key, value in node.value:
        if isinstance(key, yaml.ScalarNode) and key.value in wanted:
            found[key.value] = value
    for name, kind in wanted.items():
        if name not in found:
            line = node.start_mark.line + 1
            raise InputError(f"{meta}:{line}: {_dotted((*where, name))}: missing; expected {_KIND[kind]} here")
        _expect(meta, found[name], (*where, name), kind)
    return found


def _expect(meta: Path, node: Any, where: tuple[Any, ...], kind: type, extra: str = "") -> None:
    import yaml

    if kind is dict:
        ok = isinstance(node, yaml.MappingNode)
    elif kind is list:
        ok = isinstance(node, yaml.SequenceNode)
    else:
        ok = isinstance(node, yaml.ScalarNode) and node.tag == _TAGS.get(kind)
    if ok:
        return
    if isinstance(node, yaml.ScalarNode):
        tag = node.tag.rsplit(":", 1)[-1]
        got = f"{node.value} ({'a text' if tag == 'str' else 'an integer' if tag == 'int' else tag})" \
            if node.value else "nothing"
    else:
        got = "a mapping" if isinstance(node, yaml.MappingNode) else "a list"
    raise InputError(f"{meta}:{node.start_mark.line + 1}: {_dotted(where)}: expected {_KIND[kind]}{extra}, "
                     f"got {got}")


def _dotted(where: tuple[Any, ...]) -> str:
    return ".".join(map(str, where)) or "(top level)"
