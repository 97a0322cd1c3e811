"""The Q-table on disk: where it lives, how it is written, and what happens when it is bad.

Format (version 1): a compressed ``.npz`` holding ``q`` (float64, states × actions),
``visits`` (int64, same shape) and ``meta`` (UTF-8 JSON as uint8): format name, version,
the fingerprint of the state and action spaces, their readable layout (factor bins, action
names — enough for ``respecd policy show`` without the profile), update count, ε, profile.
Most cells keep their initial value, so a fresh 3645 × 15 table is 2 kB on disk instead of
875 kB, written every ``save_every`` updates.

Writes are atomic: a temp file in the same directory, fsync, rename over the old file,
fsync of the directory — a crash leaves the old table or the new one, never half of one.
A corrupt file (any field of the wrong type, out of range or not finite: every one is
checked), another version, or a table for a different state/action space is renamed aside
(``NAME.corrupt-YYYYmmddTHHMMSS`` / ``.mismatch-...``) with a warning naming why, and learning
starts fresh: a bad table must never stop the robot, nor crash it at every restart.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import structlog

from respecd import filekind, pathkind
from respecd.atomicfile import write_atomically
from respecd.control.qlearning import QTable
from respecd.errors import InputError

log = structlog.get_logger(__name__)

FORMAT = "respecd-qtable"
VERSION = 1


def resolve_state_dir(cli_value: str | None) -> Path:
    """``--state-dir``, else ``$STATE_DIRECTORY`` (systemd StateDirectory=), else
    ``$XDG_STATE_HOME/respecd``, else ``~/.local/state/respecd``."""
    if cli_value:
        return Path(cli_value).expanduser()
    systemd = os.environ.get("STATE_DIRECTORY")
    if systemd:
        return Path(systemd.split(":")[0])  # systemd lists several dirs separated by ':'
    xdg = os.environ.get("XDG_STATE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".local" / "state"
    return base / "respecd"


def table_path(state_dir: Path, file_name: str, profile_name: str) -> Path:
    if not file_name:
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in profile_name) or "default"
        file_name = f"qtable-{safe}.npz"
    return state_dir / file_name


def fingerprint(layout: dict[str, Any]) -> str:
    """Short hash of the state and action layout a table was learned for."""
    canonical = json.dumps(layout, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def table_meta(table: QTable, layout: dict[str, Any], info: dict[str, Any]) -> dict[str, Any]:
    """A table's ``meta``: format, the layout and its fingerprint, progress, and ``info``."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "fingerprint": fingerprint(layout),
        "layout": layout,
        "updates": table.updates,
        "epsilon": table.epsilon,
        **info,
    }


def save_table(path: Path, table: QTable, layout: dict[str, Any], info: dict[str, Any]) -> None:
    """Write atomically (temp + fsync + rename + directory fsync), stamped with the time."""
    write_arrays(path, {**table_meta(table, layout, info), "saved_unix": time.time()}, table.q, table.visits)


def write_arrays(path: Path, meta: dict[str, Any], q: np.ndarray, visits: np.ndarray) -> None:
    """Write ``meta`` and the arrays as a table file, atomically."""
    buffer = io.BytesIO()
    meta_bytes = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez_compressed(buffer, q=q, visits=visits, meta=meta_bytes)
    write_atomically(path, buffer.getbuffer())


EXPECTED_SHORT = "a respecd Q-table (.npz)"
EXPECTED = ("expected a respecd Q-table: an .npz of plain arrays q, visits and meta, as the daemon and "
            "`respecd train-policy` write it")


class TableAccessError(InputError):
    """The table could not be read as a file (not a regular file, no permission to read it): the
    operator's to fix, not damage to set aside — the daemon stops at start (exit 2) instead of
    forgetting what it learned."""


def read_table(path: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """(meta, q, visits) of a table file; InputError says what is wrong with it. Never numpy's own
    advice for a file of pickled objects (load it with allow_pickle): that would run its code."""
    try:
        # open the file ourselves: np.load leaks its handle when the zip directory is torn
        with _open(path) as f:
            head = f.read(filekind.HEAD)
            if not head:
                raise InputError(f"{path}: empty file (0 bytes), {EXPECTED}")
            if not head.startswith((*filekind.ZIP_MAGIC, filekind.NPY_MAGIC)):
                raise InputError(f"{path}: not a respecd Q-table: it looks like {filekind.describe(head, path)} "
                                 f"(first bytes {head[:8]!r}); {EXPECTED}")
            f.seek(0)
            q, visits, raw = _arrays(path, np.load(f, allow_pickle=False))
    except InputError:
        raise
    except (zipfile.BadZipFile, EOFError) as err:
        raise InputError(f"{path}: damaged or truncated .npz archive ({err}); {EXPECTED}") from err
    except OSError as err:
        raise InputError(f"{path}: cannot read Q-table: {err.strerror or err}") from err
    except ValueError as err:
        detail = "it holds pickled Python objects" if "pickle" in str(err) else str(err)
        raise InputError(f"{path}: not a respecd Q-table: {detail}; {EXPECTED}") from err
    except Exception as err:  # noqa: BLE001 - damage surfaces as zlib's or numpy's header parser's own errors
        # (zlib.error, SyntaxError, tokenize.TokenError): damage, whichever the library raises
        raise InputError(f"{path}: damaged .npz archive ({type(err).__name__}: {err}); {EXPECTED}") from err
    try:
        meta = json.loads(raw.tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"{path}: meta is not JSON ({err})") from err
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"{path}: meta.format is not {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise InputError(f"{path}: meta.version is {meta.get('version')!r}, expected {VERSION}")
    _check_meta(path, meta)
    _check_arrays(path, q, visits)
    return meta, q, visits


def _check_meta(path: Path, meta: dict[str, Any]) -> None:
    """Every field the daemon reads, of its type and in its range: a bad value is a damaged table
    (set aside), never a TypeError at load or a division by zero at the next update."""
    checks = (
        ("fingerprint", lambda v: isinstance(v, str) and v != "", "a non-empty text"),
        ("layout", lambda v: isinstance(v, dict), "a mapping (the state and action layout)"),
        ("updates", lambda v: _is_int(v) and v >= 0, "a whole number >= 0"),
        ("epsilon", lambda v: _is_number(v) and 0.0 <= v <= 1.0, "a number from 0 to 1"),
    )
    for name, valid, expected in checks:
        if name not in meta or not valid(meta[name]):
            got = f"{meta[name]!r}" if name in meta else "nothing"
            raise InputError(f"{path}: meta.{name}: expected {expected}, got {got[:80]}")


def _check_arrays(path: Path, q: np.ndarray, visits: np.ndarray) -> None:
    if q.ndim != 2 or q.dtype != np.float64 or q.size == 0:
        raise InputError(f"{path}: q: expected a non-empty float64 matrix (states x actions), got {q.dtype} {q.shape}")
    if not np.isfinite(q).all():
        bad = np.argwhere(~np.isfinite(q))[0]
        raise InputError(f"{path}: q: expected finite values, got {q[tuple(bad)]} at state {bad[0]}, action {bad[1]}")
    if visits.shape != q.shape or visits.dtype.kind not in "iu":
        raise InputError(f"{path}: visits: expected whole numbers of q's shape {q.shape}, got {visits.dtype} "
                         f"{visits.shape}")
    if (visits < 0).any():
        bad = np.argwhere(visits < 0)[0]
        raise InputError(f"{path}: visits: expected counts >= 0, got {visits[tuple(bad)]} at state {bad[0]}, "
                         f"action {bad[1]}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _open(path: Path) -> BinaryIO:
    """The table file for reading; TableAccessError when it is no file to read at all."""
    try:
        return pathkind.open_regular(path, EXPECTED_SHORT)  # a FIFO or a device: refused, never waited on
    except FileNotFoundError as err:
        raise InputError(f"{path}: no such file") from err
    except InputError as err:
        raise TableAccessError(str(err)) from err
    except OSError as err:  # not ours to read (EACCES), a file system gone: not damage to the table
        raise TableAccessError(f"{path}: cannot read the Q-table: {err.strerror or err} (as user "
                               f"{_user()}); fix its permissions or the state directory's") from err


def _user() -> str:
    import pwd

    try:
        return pwd.getpwuid(os.geteuid()).pw_name
    except KeyError:
        return str(os.geteuid())


def _arrays(path: Path, data: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: a single .npy array, not a respecd .npz Q-table")
    with data:
        if not {"q", "visits", "meta"} <= set(data.files):
            raise InputError(f"{path}: not a respecd Q-table (arrays q, visits, meta expected)")
        return _array(path, data, "q"), _array(path, data, "visits"), _array(path, data, "meta")


def _array(path: Path, data: Any, name: str) -> np.ndarray:
    try:
        return np.asarray(data[name])
    except ValueError as err:
        if "pickle" not in str(err):
            raise
        raise InputError(f"{path}: not a respecd Q-table: array {name!r} holds Python objects (a pickle), "
                         f"which respecd never loads; {EXPECTED}") from err


def mismatch(meta: dict[str, Any], layout: dict[str, Any], profile: str) -> str | None:
    """Why a table (its ``meta``) does not fit ``layout`` (of profile ``profile``); None when it fits.
    Names what differs: the profile each was made for, the state factors, the action slots."""
    if meta.get("fingerprint") == fingerprint(layout):
        return None
    theirs: dict[str, Any] = meta["layout"] if isinstance(meta.get("layout"), dict) else {}
    made_for = f"profile {meta.get('profile', '?')!r}" + (f", this run {profile!r}" if meta.get("profile") != profile
                                                         else "")
    return f"it was learned for {made_for}: " + "; ".join(_layout_differences(theirs, layout))


def _layout_differences(theirs: dict[str, Any], ours: dict[str, Any]) -> list[str]:
    """What differs between two layouts, most telling first (at least one line)."""
    found = []
    states_a, states_b = theirs.get("states") or {}, ours.get("states") or {}
    if states_a.get("factors") != states_b.get("factors"):
        found.append(f"state factors {states_a.get('factors')} here {states_b.get('factors')}")
    elif states_a.get("bins") != states_b.get("bins"):
        found.append(f"state bins {states_a.get('bins')} here {states_b.get('bins')}")
    space_a = (theirs.get("actions") or {}).get("space") or {}
    space_b = (ours.get("actions") or {}).get("space") or {}
    if space_a.get("mode") != space_b.get("mode"):
        found.append(f"action mode {space_a.get('mode')} here {space_b.get('mode')}")
    slots_a = {s.get("name"): s for s in space_a.get("slots") or []}
    slots_b = {s.get("name"): s for s in space_b.get("slots") or []}
    if list(slots_a) != list(slots_b):
        found.append(f"controlled sensors {list(slots_a)} here {list(slots_b)}")
    for name in [n for n in slots_b if n in slots_a]:
        for key in ("settings", "rates"):
            if slots_a[name].get(key) != slots_b[name].get(key):
                found.append(f"{name} {key} {slots_a[name].get(key)} here {slots_b[name].get(key)}")
    return found or ["its state/action layout differs (fingerprint "
                     f"{fingerprint(theirs) if theirs else '?'} here {fingerprint(ours)})"]


@dataclass(frozen=True)
class StoredTable:
    """A Q-table file's contents, read once: what a replay or a fleet's workers are given (not its
    path, which another machine may not have). ``name`` says where it came from, in messages."""

    meta: dict[str, Any]
    q: np.ndarray
    visits: np.ndarray
    name: str

    @classmethod
    def read(cls, path: Path) -> StoredTable:
        meta, q, visits = read_table(Path(path))
        return cls(meta, q, visits, Path(path).name)

    @property
    def updates(self) -> int:
        return int(self.meta.get("updates", 0))

    def write(self, path: Path) -> None:
        """Save as a table file (no time stamp in meta: the same table reads back the same)."""
        write_arrays(Path(path), self.meta, self.q, self.visits)

    def restore_into(self, table: QTable, layout: dict[str, Any], profile: str) -> None:
        """Load into ``table``; InputError naming what differs when it was learned for another layout."""
        why = mismatch(self.meta, layout, profile)
        if why is None and self.q.shape != table.shape:
            why = f"its shape {self.q.shape} is not this run's {table.shape}"
        if why is not None:
            raise InputError(f"{self.name}: the Q-table does not fit: {why}")
        table.restore(self.q, self.visits, self.updates, float(self.meta.get("epsilon", table.epsilon)))


def load_into(path: Path, table: QTable, layout: dict[str, Any], set_aside: bool = True) -> bool:
    """Restore ``table`` from ``path`` if it matches; True if loaded. A bad file is set aside
    (``set_aside``, the live state directory's own table) or only reported (a replay reading
    a robot's table must leave it as it is); one that is no file to read (TableAccessError) is raised."""
    if not path.exists():
        return False
    try:
        meta, q, visits = read_table(path)
    except TableAccessError:
        raise
    except InputError as err:
        _unusable(path, "corrupt", str(err), set_aside)
        return False
    if meta.get("fingerprint") != fingerprint(layout) or q.shape != table.shape:
        detail = f"table is for another state/action space (fingerprint {meta.get('fingerprint')})"
        _unusable(path, "mismatch", detail, set_aside)
        return False
    table.restore(q, visits, meta["updates"], meta["epsilon"])
    log.info("qtable_loaded", path=str(path), updates=table.updates, epsilon=round(table.epsilon, 4))
    return True


def _unusable(path: Path, reason: str, detail: str, set_aside: bool) -> None:
    if set_aside:
        _set_aside(path, reason, detail)
    else:
        log.warning("qtable_not_used", path=str(path), reason=reason, detail=detail)


def _set_aside(path: Path, reason: str, detail: str) -> None:
    aside = path.with_name(f"{path.name}.{reason}-{time.strftime('%Y%m%dT%H%M%S')}")
    try:
        os.replace(path, aside)
    except OSError as err:
        log.warning("qtable_set_aside_failed", path=str(path), error=str(err))
        return
    log.warning("qtable_set_aside", path=str(path), moved_to=str(aside), reason=reason, detail=detail)
