"""Output paths checked before the work that fills them.

A training, an evaluation, a calibration or a replay can run for minutes to hours and write
its result only at the end; an output path that cannot take the result (an existing
directory where a file goes, a file where a folder goes, a folder nobody may write) must
then be refused at the start, with the flag and the path (exit 2), not found by a traceback
that loses the finished work.

Writability is tried with a real write (a temporary file, removed again), as
``respecd.preflight.check_state_dir`` does: permission bits do not show a read-only mount,
and root writes through them. Folders made for the try are removed again, so a check leaves
nothing behind; the command makes them itself when it writes (``make_parents``) or, where it
never made parent folders, a missing one is refused here as it would be there.

What happens to an existing regular file is the command's own business (most replace it);
these checks never refuse one.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path

from respecd.errors import InputError


def output_file_problem(path: Path, make_parents: bool = True, example: str = "NAME") -> str | None:
    """Why a file cannot be written at ``path``, or None. ``make_parents``: the command creates
    missing parent folders (else a missing one is a problem). ``example``: a file name the
    message suggests inside a directory given by mistake."""
    if path.is_dir():
        return f"{path}: is a directory; expected a file name to write (e.g. {path / example})"
    return _folder_problem(path, path.parent, make_parents)


def output_dir_problem(path: Path, make_parents: bool = True, must_be_new: bool = False) -> str | None:
    """Why files cannot be written into the folder ``path``, or None. ``must_be_new``: the
    command creates the folder itself and refuses an existing one."""
    if path.exists() or path.is_symlink():
        if must_be_new:
            kind = "a directory" if path.is_dir() else "a file"
            return f"{path}: already exists ({kind}); expected a new directory name"
        if not path.is_dir():
            return f"{path}: is a file, not a directory; expected a directory to write into"
        return _try_write(path, path)
    if must_be_new:  # the command makes the folder, not its parents
        return _folder_problem(path, path.parent, make_parents)
    return _folder_problem(path, path, make_parents)


def check_output_file(flag: str, path: str | Path | None, make_parents: bool = True,
                      example: str = "NAME") -> Path | None:
    """``output_file_problem`` as the command-line error (``InputError``: ``respecd: FLAG PATH: ...``,
    exit 2); the path as a ``Path``, None for None (the flag was not given)."""
    return _checked(flag, path, lambda p: output_file_problem(p, make_parents, example))


def check_output_dir(flag: str, path: str | Path | None, make_parents: bool = True,
                     must_be_new: bool = False) -> Path | None:
    """``output_dir_problem`` as the command-line error (``InputError``, exit 2); None for None."""
    return _checked(flag, path, lambda p: output_dir_problem(p, make_parents, must_be_new))


def _checked(flag: str, path: str | Path | None, problem_of: Callable[[Path], str | None]) -> Path | None:
    if path is None:
        return None
    path = Path(path)
    problem = problem_of(path)
    if problem:
        raise InputError(f"{flag} {problem}")
    return path


def _folder_problem(path: Path, folder: Path, make_parents: bool) -> str | None:
    """``folder`` (where ``path`` goes) exists and takes a write, or can be made and then does."""
    blocker = next((p for p in (folder, *folder.parents) if p.exists() or p.is_symlink()), None)
    if blocker is not None and not blocker.is_dir():
        return f"{path}: {blocker} is a file, not a directory"
    if blocker != folder and not make_parents:
        return f"{path}: no such directory {folder} (this command does not create it)"
    return _try_write(path, folder)


def _try_write(path: Path, folder: Path) -> str | None:
    """A real write into ``folder`` (made for the try when missing, and removed again)."""
    made = [p for p in (folder, *folder.parents) if not os.path.exists(p)]
    err = write_error(folder)
    if err is None:
        return None
    where = next((p for p in (folder, *folder.parents) if p not in made), folder)
    reason = err.strerror or str(err)
    if err.errno == errno.ENOENT and where.is_dir():  # /proc, /sys: a folder that takes no new files
        reason = "it takes no new files"
    return f"{path}: cannot write in {where} ({reason})"


def write_error(folder: Path, keep: bool = False) -> OSError | None:
    """The error a real write into ``folder`` meets, or None. Missing folders are made for it and,
    unless ``keep``, removed again (deepest first, only those this call made)."""
    made = [p for p in (folder, *folder.parents) if not os.path.exists(p)]  # deepest first
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".respecd-write-check-"):
            pass
    except OSError as err:
        return err
    finally:
        for made_folder in made if not keep else ():
            if not made_folder.exists():
                continue  # the mkdir stopped above it
            try:
                made_folder.rmdir()
            except OSError:
                break  # not made by us after all, or not empty: leave it and its parents
    return None


def recording_problem(template: str) -> str | None:
    """Why a recording cannot open its first file, or None. ``template`` is ``--record`` or the
    profile's ``recording.path``: the file is named as the recorder names it (``{time}`` the UTC
    start, ``{index}`` 000; later segments go into the same folder) and its folders are made.
    Without this check the recorder pauses at the first write and the session goes unrecorded.
    A recording never overwrites another: any file of this session's names (the first, or a later
    segment ``-NNN`` of an earlier session with the same name) already there is a problem too."""
    from datetime import datetime, timezone

    from respecd.record.storage import recordings
    from respecd.record.writer import segment_path, session_stamp

    now = datetime.now(timezone.utc)
    first = segment_path(template, now, 0)
    problem = _not_a_new_file(first) or output_file_problem(first, make_parents=True, example="respecd-{time}.mcap")
    session = session_stamp(now) if "{time}" in template else ""
    taken = [r.path for r in recordings(template) if r.session == session]
    if problem is None and taken:
        problem = (f"{first}: {taken[0]} exists and a recording is never overwritten; move it away, or put "
                   "{time} in the name for one file per session (e.g. run-{time}.mcap)")
    if problem and str(first) != template:  # name the template as given, then the file it makes now
        problem = f"{template} (now {first}){problem[len(str(first)):]}"
    return problem


def _not_a_new_file(path: Path) -> str | None:
    """A name no file system takes (NUL, a name over 255 bytes; the same for a later segment's longer
    name), or a device or FIFO already there: a recording writes new regular files (``/dev/null``
    recorded nothing, and said nothing)."""
    from respecd import pathkind

    longest = path.with_name(f"{path.stem}-99999{path.suffix}")  # a days-long session's segment names
    problem = pathkind.name_problem(path) or pathkind.name_problem(longest)
    if problem:
        return problem
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None  # a file already there, or a directory: said below as for any output
    return f"{path}: is {pathkind.describe(mode)}; a recording is written to new regular files"
