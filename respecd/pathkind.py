"""Paths checked for their kind before they are opened: a FIFO, a device, a socket or a
directory where a regular file is expected is refused at once, naming the path (exit 2).

Why not simply ``open``: open(2) of a FIFO blocks in the kernel until a writer comes, and a
signal cannot end it — Python retries the call after the handler ran (PEP 475), and the
daemon's handlers only note a stop request — so SIGTERM never stopped a daemon whose profile
or Q-table was a FIFO, and a load in a worker thread kept the interpreter from exiting. A
device is no better: /dev/zero never ends, a tty waits for a line. So files are opened with
``O_NONBLOCK`` (which a FIFO's open honours) and checked by ``fstat`` on the descriptor that
was opened: nothing can swap the file between the check and the read. ``problem`` is the same
check for paths another library opens (rosbags) and for ``check-config``.
"""

from __future__ import annotations

import fcntl
import os
import stat
from pathlib import Path
from typing import BinaryIO

from respecd.errors import InputError

NAME_MAX = 255  # bytes in one path component (ext4, xfs, btrfs, tmpfs, vfat's long names)
PATH_MAX = 4096  # bytes in a whole path (Linux)
_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a directory"),
          (stat.S_ISREG, "a file"))


def describe(mode: int) -> str:
    """'a FIFO (named pipe)', 'a character device', ... for an ``st_mode``."""
    return next((name for test, name in _KINDS if test(mode)), "a special file")


def name_problem(path: str | Path) -> str | None:
    """Why the file system could not even look ``path`` up (NUL, a name over NAME_MAX bytes), or None."""
    text = os.fspath(path)
    if "\x00" in text:
        return f"{text!r}: contains a NUL character, which no file name may hold"
    encoded = os.fsencode(text)
    if len(encoded) >= PATH_MAX:
        return f"{text[:60]}...: path is {len(encoded)} bytes, longer than the {PATH_MAX - 1} Linux allows"
    longest = max(encoded.split(b"/"), key=len)
    if len(longest) > NAME_MAX:
        return (f"{text[:60]}...: a file name of {len(longest)} bytes, longer than the {NAME_MAX} a file "
                "system allows in one name")
    return None


def problem(path: str | Path, expected: str) -> str | None:
    """Why ``path`` is not a regular file to read (a FIFO, a device, a directory, a name no file
    system takes), or None — also None when it does not exist (the caller says what that means)."""
    bad_name = name_problem(path)
    if bad_name:
        return bad_name
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None  # missing, or not ours to look at: opening it says which
    if stat.S_ISREG(mode):
        return None
    return f"{path}: is {describe(mode)}, not a regular file; expected {expected}"


def open_fd(path: str | Path, expected: str, flags: int = os.O_RDONLY, mode: int = 0o644) -> int:
    """``os.open`` that never blocks and refuses anything but a regular file (InputError naming
    ``path``, what it is and ``expected``); OSError as ``open`` raises it otherwise."""
    bad_name = name_problem(path)
    if bad_name:
        raise InputError(f"{bad_name}; expected {expected}")
    try:
        fd = os.open(path, flags | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC, mode)
    except IsADirectoryError as err:  # asked to write: the kernel refuses a directory before fstat could
        raise InputError(f"{path}: is a directory, not a regular file; expected {expected}") from err
    try:
        file_mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(file_mode):
            raise InputError(f"{path}: is {describe(file_mode)}, not a regular file; expected {expected}")
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
    except BaseException:
        os.close(fd)
        raise
    return fd


def open_regular(path: str | Path, expected: str) -> BinaryIO:
    """``open(path, "rb")`` through ``open_fd``: a regular file or InputError, at once."""
    return os.fdopen(open_fd(path, expected), "rb")
