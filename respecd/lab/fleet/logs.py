"""Which logs a fleet command means: files, folders and globs on this machine, or URLs of an
object store (``s3://``, ``gs://``, ``memory://``... as fsspec reads them).

Every log gets a *name*: its file name, or — where two logs share one — the shortest tail of
its path that tells them apart. Names, not paths, go into reports (a report compares equal
wherever its logs were), and results are always listed by name, whatever order the logs
were given in. A URL is opened where the work runs (a Ray worker on another machine reads the
object store itself); a local path must exist where the work runs too (the same mount).
"""

from __future__ import annotations

import glob
import os
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from respecd.errors import InputError

LOG_SUFFIXES = (".mcap", ".bag")  # in a folder: respecd logs and ROS 1 bags; rosbag2 folders by metadata.yaml


@dataclass(frozen=True, order=True)
class LogRef:
    """One log: its name in reports, and where it is (a local path or a URL)."""

    name: str
    location: str

    @property
    def remote(self) -> bool:
        return "://" in self.location and not self.location.startswith("file://")

    def size(self) -> int:
        """Bytes on this machine (a rosbag2 folder: its files); 0 when remote or unreadable."""
        if self.remote:
            return 0
        path = Path(self.location.removeprefix("file://"))
        try:
            return sum(p.stat().st_size for p in path.rglob("*")) if path.is_dir() else path.stat().st_size
        except OSError:
            return 0


def largest_first(refs: Sequence[LogRef]) -> list[int]:
    """The order to hand logs out in: the biggest first, so the last to finish is a small one
    (workers end together); by name among equals. Results do not depend on it."""
    return sorted(range(len(refs)), key=lambda i: (-refs[i].size(), refs[i].name))


def expand(specs: Sequence[str]) -> list[LogRef]:
    """Files, folders (their logs, recursively) and globs, each log once, sorted by name.
    InputError for a spec that names nothing (the user mistyped, not a log that failed)."""
    found: list[str] = []
    for spec in specs:
        matches = _matches(spec)
        if not matches:
            raise InputError(f"{spec}: no such file, folder or glob match (expected .mcap logs, .bag files or "
                             "rosbag2 folders)")
        found += matches
    unique = list(dict.fromkeys(found))
    names = _names(unique)
    return sorted(LogRef(names[loc], loc) for loc in unique)


def _matches(spec: str) -> list[str]:
    if "://" in spec and not spec.startswith("file://"):
        return _remote_matches(spec)
    path = spec.removeprefix("file://")
    if glob.has_magic(path):
        return sorted(loc for hit in glob.glob(path, recursive=True) for loc in _matches(hit))
    p = Path(path)
    if p.is_dir() and not (p / "metadata.yaml").is_file():
        return sorted(str(q) for q in p.rglob("*") if _is_log(q))
    return [str(p.resolve())] if p.exists() else []


def _is_log(p: Path) -> bool:
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix in LOG_SUFFIXES and not (p.parent / "metadata.yaml").is_file()


def _remote_matches(url: str) -> list[str]:
    fs, root = _filesystem(url)
    protocol = url.split("://", 1)[0]
    if glob.has_magic(root):
        paths = fs.glob(root)
    elif fs.isdir(root):
        paths = [p for p in fs.find(root) if p.endswith(LOG_SUFFIXES)]
    else:
        paths = [root] if fs.exists(root) else []
    return sorted(f"{protocol}://{p.removeprefix(protocol + '://')}" for p in paths)


def _filesystem(url: str) -> tuple[Any, str]:
    try:
        import fsspec
    except ImportError as err:
        raise InputError(f"{url}: reading logs from an object store needs fsspec (pip install fsspec, and the "
                         "store's own package, e.g. s3fs or gcsfs)") from err
    try:
        return fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as err:
        raise InputError(f"{url}: {err}") from err


def _names(locations: list[str]) -> dict[str, str]:
    """Each location's name: the file name, lengthened by parent folders until unique."""
    parts = {loc: loc.split("://", 1)[-1].rstrip("/").split("/") for loc in locations}
    depth = dict.fromkeys(locations, 1)
    while True:
        names = {loc: "/".join(parts[loc][-depth[loc]:]) for loc in locations}
        seen: dict[str, list[str]] = {}
        for loc, name in names.items():
            seen.setdefault(name, []).append(loc)
        clashes = [loc for group in seen.values() if len(group) > 1 for loc in group
                   if depth[loc] < len(parts[loc])]
        if not clashes:
            return names
        for loc in clashes:
            depth[loc] += 1


@contextmanager
def local_copy(ref: LogRef) -> Iterator[Path]:
    """A path to read ``ref`` from: the file itself, or an object store's log copied to a
    temporary file (the reader seeks) and deleted after."""
    if not ref.remote:
        yield Path(ref.location.removeprefix("file://"))
        return
    fs, path = _filesystem(ref.location)
    suffix = Path(path).suffix or ".mcap"
    fd, tmp = tempfile.mkstemp(prefix="respecd-fleet-", suffix=suffix)
    os.close(fd)
    try:
        try:
            fs.get(path, tmp)
        except (OSError, ValueError) as err:
            raise InputError(f"{ref.location}: cannot fetch: {err}") from err
        yield Path(tmp)
    finally:
        os.unlink(tmp)
