"""A reader that leaves early (`respecd schema | head`) ends the command quietly."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytestmark = pytest.mark.e2e  # the console script in an interpreter of its own


def test_a_closed_stdout_pipe_is_exit_141_without_a_traceback() -> None:
    command = [sys.executable, "-c", "import sys; from respecd.cli import main; sys.exit(main())", "schema"]
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE) as child:
        assert child.stdout is not None and child.stderr is not None
        child.stdout.close()  # before the child writes: its first write meets a pipe with no reader
        err = child.stderr.read().decode()
        assert child.wait(timeout=60) == 141  # 128 + SIGPIPE, as a shell pipeline reports it
    assert err == ""
