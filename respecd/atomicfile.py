"""Replacing a file whole: a reader, or the file system after a crash or power cut, sees the old
file or the new one, never a part of the new one.

The Q-table (saved on SIGTERM and every few minutes), a replay's report and its saved table are
written this way. The temporary file is made by ``mkstemp``, which gives it mode 0600; the result
gets the mode an ordinary ``open`` would have given it under the process's umask, so a report
written for the user is readable as any other file of theirs.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

DEFAULT_UMASK = 0o022


def write_atomically(path: Path, data: bytes | memoryview, durable: bool = True) -> None:
    """Write ``data`` to ``path`` (folders made) through a temporary file beside it and a rename.
    ``durable``: the data and the rename reach the disk before this returns (fsync of the file
    and of its folder). On any failure the temporary file is removed and ``path`` is untouched."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~process_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if durable:
        folder = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)


def process_umask() -> int:
    """This process's umask, read without setting it: ``os.umask`` can only be read by changing it,
    which would let a file another thread creates meanwhile come out world-writable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return DEFAULT_UMASK
