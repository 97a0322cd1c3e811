"""Disk space for recordings: the free-space floor and the retention cap.

A rover records for days onto a disk it shares with its OS, and at the rover's data rate
(docs/PERFORMANCE.md "recorder data rate") a card fills in hours. Recording therefore stops
short of a full disk (``min_free_mib``: the file is finished cleanly while there is still
room for its summary) and, when the profile allows it, makes room by deleting the oldest
recordings first: earlier sessions, oldest first, then this session's own finished
segments, never the segment being written.

Only what is provably an earlier, finished recording is deleted: a file of another session
last written before this session started (its modification time, not the time in its name:
a name dated 2099 once sorted after the live session and took 21 of its 22 segments). A
file matching the template that was written since this session started is somebody else's
(another daemon, a copy in progress): counted, never deleted.

Recordings are the files the ``recording.path`` template names: ``{time}`` is the session
(its UTC start), ``{index}`` or the ``-NNN`` suffix the segment.
"""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import structlog

log = structlog.get_logger(__name__)

MIB = 1 << 20


@dataclass(frozen=True, order=True)
class Recording:
    session: str  # the {time} stamp ("" for a template without one)
    index: int
    path: Path
    size: int
    mtime: float = 0.0  # last written (epoch s)


def pattern(template: str) -> tuple[Path, re.Pattern[str]]:
    """The directory of the template and a regex matching its file names (session, index)."""
    path = Path(template)

    def escaped(text: str) -> str:
        return re.escape(text).replace(re.escape("{time}"), r"(?P<time>\d{8}T\d{6})")

    if "{index}" in path.name:
        name = escaped(path.name).replace(re.escape("{index}"), r"(?P<index>\d{3,})")
    else:  # segments after the first get -001, -002, ... before the suffix (writer.segment_path)
        name = escaped(path.stem) + r"(?:-(?P<index>\d{3,}))?" + re.escape(path.suffix)
    return path.parent, re.compile(name)


def recordings(template: str) -> list[Recording]:
    """This template's recordings on disk, oldest session first, segments in order."""
    directory, regex = pattern(template)
    found = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return []
    for entry in entries:
        match = regex.fullmatch(entry.name)
        if match is None or not entry.is_file(follow_symlinks=False):
            continue
        try:
            stat = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        groups = match.groupdict()
        found.append(Recording(groups.get("time") or "", int(groups.get("index") or 0), Path(entry.path),
                               stat.st_size, stat.st_mtime))
    return sorted(found)


def free_bytes(directory: Path) -> int | None:
    """Free bytes for an unprivileged writer on ``directory``'s file system (None: unknown)."""
    try:
        return shutil.disk_usage(directory).free
    except OSError:
        return None


class Retention:
    """Deletes the oldest recordings to keep under ``max_bytes`` and, if allowed, above the floor."""

    def __init__(self, template: str, max_bytes: int, floor_bytes: int, delete_for_floor: bool,
                 started: float = float("inf")) -> None:
        """``started``: when this session began (epoch s); files last written since are not deleted."""
        self.template = template
        self.max_bytes = max_bytes
        self.floor_bytes = floor_bytes
        self.delete_for_floor = delete_for_floor
        self.started = started
        self.directory = pattern(template)[0]
        self.over_cap_logged = False

    def enforce(self, own: list[Path], open_path: Path | None, open_size: int = 0) -> list[Recording]:
        """Delete until both limits hold or nothing deletable is left; what was deleted. ``own``: this
        session's segments, ``open_path`` among them the one being written (never deleted)."""
        deleted: list[Recording] = []
        if not self.max_bytes and not self.delete_for_floor:
            return deleted
        found = [r for r in recordings(self.template) if r.path != open_path]
        total = sum(r.size for r in found) + open_size
        for recording in self.deletable(found, own):
            over_cap = self.max_bytes and total > self.max_bytes
            free = free_bytes(self.directory)
            low = self.delete_for_floor and free is not None and free < self.floor_bytes
            if not over_cap and not low:
                break
            try:
                recording.path.unlink()
            except OSError as err:
                log.warning("record.prune_failed", path=str(recording.path), error=err.strerror or str(err))
                break
            total -= recording.size
            deleted.append(recording)
            log.info("record.pruned", path=str(recording.path), mib=round(recording.size / MIB, 1),
                     reason="max_bytes" if over_cap else "min_free_mib", kept_mib=round(total / MIB, 1))
        if self.max_bytes and total > self.max_bytes and not self.over_cap_logged:
            self.over_cap_logged = True  # once: nothing older is left that may be deleted
            log.warning("record.over_max_bytes", kept_mib=round(total / MIB, 1), max_mib=round(self.max_bytes / MIB, 1),
                        reason="the rest is the segment being written or files written since this session started")
        return deleted

    def deletable(self, found: list[Recording], own: list[Path]) -> list[Recording]:
        """Earlier sessions' files, oldest written first, then this session's finished segments in order."""
        mine = set(own)
        earlier = sorted((r for r in found if r.path not in mine and r.mtime < self.started),
                         key=lambda r: (r.mtime, r.path))
        return earlier + [r for r in found if r.path in mine]
