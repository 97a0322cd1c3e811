"""Files replaced whole: the reports and tables a user reads get an ordinary file's mode, and a
failed write leaves the old file and no temporary beside it."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from respecd.atomicfile import process_umask, write_atomically


def test_the_file_gets_the_mode_open_would_give_it_not_mkstemps_0600(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "report.json"
    write_atomically(target, b"{}\n")
    ordinary = tmp_path / "ordinary"
    ordinary.write_bytes(b"")
    assert target.read_bytes() == b"{}\n"
    assert stat.S_IMODE(target.stat().st_mode) == stat.S_IMODE(ordinary.stat().st_mode)
    assert sorted(p.name for p in target.parent.iterdir()) == ["report.json"]


@pytest.mark.e2e
def test_the_umask_is_read_without_changing_it() -> None:
    code = "import os; os.umask(0o027); from respecd.atomicfile import process_umask as u; print(oct(u()))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert done.stdout.strip() == "0o27"
    current = os.umask(0o022)
    os.umask(current)
    assert process_umask() == current


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "qtable.npz"  # a folder by mistake: the data is written, the rename fails
    target.mkdir()
    (target / "kept").write_bytes(b"old")
    with pytest.raises(OSError):
        write_atomically(target, b"new table")
    assert (target / "kept").read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["qtable.npz"]  # the temporary is gone
