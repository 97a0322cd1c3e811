"""One learning daemon per state directory.

Two daemons learning into the same directory (a manual `respecd` beside the systemd service)
would each save their own Q-table over the other's, and whichever stopped last would silently
erase what the other learned. A learning daemon therefore holds an exclusive ``flock`` on
``DIR/.respecd.lock`` for as long as it runs; the kernel releases it when the process ends,
however it ends (kill -9 included), so there is never a stale lock to clean up. The file holds
the owner's pid, for the message the second daemon prints.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from respecd import pathkind
from respecd.errors import InputError

LOCK_NAME = ".respecd.lock"


@contextlib.contextmanager
def learning_into(state_dir: Path) -> Iterator[None]:
    """Hold the state directory for this process while the block runs; InputError (exit 2) when
    another process holds it."""
    try:
        fd = pathkind.open_fd(state_dir / LOCK_NAME, "the daemon's lock file (it holds a pid)", os.O_RDWR | os.O_CREAT)
    except OSError as err:
        raise InputError(f"--state-dir {state_dir}: cannot open {LOCK_NAME}: {err.strerror or err}") from err
    with os.fdopen(fd, "r+", encoding="ascii") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            owner = handle.read().strip()
            who = f"another respecd (pid {owner})" if owner.isdigit() else "another respecd"
            raise InputError(f"--state-dir {state_dir}: {who} is learning into this state directory and would "
                             "overwrite this one's Q-table (or this one its): stop it, or give each its own "
                             "--state-dir") from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
