"""What a file looks like from its first bytes, for error messages: "garbage.pt looks like an
ONNX model", not the confusing complaint of whatever library was asked to read it.

``sniff`` reads at most ``HEAD`` bytes and never imports torch or numpy; it guesses, and a
guess only ever goes into a message.
"""

from __future__ import annotations

import struct
from pathlib import Path

HEAD = 64
ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; the end record of an empty archive
MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
NPY_MAGIC = b"\x93NUMPY"


def read_head(path: Path, size: int = HEAD) -> bytes:
    """The first ``size`` bytes (OSError as ``open`` raises it)."""
    with path.open("rb") as handle:
        return handle.read(size)


def first_zip_entry(head: bytes) -> str | None:
    """The name of a ZIP archive's first member, from its local header (readable even when the
    archive was cut before its central directory), or None."""
    if not head.startswith(b"PK\x03\x04") or len(head) < 30:
        return None
    name_len = struct.unpack_from("<H", head, 26)[0]
    return head[30 : 30 + name_len].decode("utf-8", "replace") if len(head) >= 30 + name_len else None


def is_pickle(head: bytes) -> bool:
    """A Python pickle (protocol 2-5): how torch.save wrote files before its zip format."""
    return len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5


def describe(head: bytes, path: Path | None = None) -> str:
    """A short guess of what the bytes are: 'an MCAP file', 'text (YAML, JSON, ...)', ..."""
    if not head:
        return "an empty file"
    if head.startswith(MCAP_MAGIC):
        return "an MCAP file (a respecd session log or a rosbag2 storage file)"
    if head.startswith(ROS1_MAGIC[:8]):
        return "a ROS 1 bag"
    if head.startswith(SQLITE_MAGIC):
        return "an SQLite database (a rosbag2 .db3 file?)"
    if head.startswith(NPY_MAGIC):
        return "a NumPy .npy array"
    if head.startswith(ZIP_MAGIC):
        entry = first_zip_entry(head)
        if entry is not None and entry.endswith(".npy"):
            return "a NumPy .npz archive (a respecd Q-table?)"
        if entry is not None and entry.endswith("data.pkl"):
            return "a torch zip archive"
        return "a ZIP archive" + (f" (first member {entry!r})" if entry else "")
    if is_pickle(head):
        return "a Python pickle"
    if head.startswith(b"\x1f\x8b"):
        return "gzip-compressed data"
    if head.startswith(b"\x7fELF"):
        return "an ELF executable"
    if _looks_like_onnx(head) or (path is not None and path.suffix.lower() == ".onnx"):
        return "an ONNX model (protobuf)"
    if _is_text(head):
        return "text (YAML, JSON or the like)"
    return "unrecognised binary data"


def _looks_like_onnx(head: bytes) -> bool:
    """ONNX ModelProto: field 1 (ir_version, varint) first, then usually field 2, producer_name."""
    return len(head) >= 4 and head[0] == 0x08 and head[1] < 0x80 and head[2] in (0x12, 0x1A, 0x3A, 0x42)


def _is_text(head: bytes) -> bool:
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        try:  # a multi-byte character cut by the head's end
            text = head[:-3].decode("utf-8")
        except UnicodeDecodeError:
            return False
    return all(c.isprintable() or c in "\t\r\n" for c in text)
