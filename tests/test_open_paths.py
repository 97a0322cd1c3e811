"""A FIFO, a device or a directory where respecd expects a regular file is refused at once,
naming the path (exit 2): opening a FIFO for reading waits for a writer in the kernel, where
SIGTERM could not end it (issue "Open doors", item 1)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

from respecd import pathkind
from respecd.control.persist import TableAccessError, load_into
from respecd.control.qlearning import QTable
from respecd.control.statelock import learning_into
from respecd.errors import InputError

REPO = Path(__file__).resolve().parents[1]
RESPECD = [sys.executable, "-m", "respecd.cli"]


def _respecd(*args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
    """A hang is a failure: the timeout ends the child and raises."""
    return subprocess.run([*RESPECD, *args], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def _at_once(work, *args):
    """``work(*args)`` in a thread; fails the test if it is still waiting after 10 s (a blocked open)."""
    out: dict[str, object] = {}

    def run() -> None:
        try:
            out["value"] = work(*args)
        except BaseException as err:  # noqa: BLE001 - handed back to the test
            out["error"] = err

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(10)
    if thread.is_alive():
        with open(args[0], "wb"):  # a writer ends the blocked open, so the thread does not outlive the test
            pass
        thread.join(5)
        pytest.fail(f"{work.__name__}({args[0]}) blocked")
    if "error" in out:
        raise out["error"]  # type: ignore[misc]
    return out.get("value")


def test_open_regular_refuses_a_fifo_a_device_and_a_directory_without_waiting(tmp_path: Path) -> None:
    fifo = tmp_path / "p.yaml"
    os.mkfifo(fifo)
    for path, kind in ((fifo, "a FIFO (named pipe)"), (Path("/dev/zero"), "a character device"),
                       (tmp_path, "a directory")):
        with pytest.raises(InputError, match=re.escape(f"{path}: is {kind}, not a regular file; expected a profile")):
            _at_once(pathkind.open_regular, path, "a profile")
    assert pathkind.problem(fifo, "x") == f"{fifo}: is a FIFO (named pipe), not a regular file; expected x"
    assert pathkind.problem(tmp_path / "missing", "x") is None
    assert "NUL" in (pathkind.problem("a\x00b", "x") or "")
    assert "300 bytes" in (pathkind.problem(tmp_path / ("n" * 300), "x") or "")


def test_a_fifo_as_the_q_table_is_raised_not_set_aside(tmp_path: Path) -> None:
    from respecd.control.config import Learning

    fifo = tmp_path / "qtable.npz"
    os.mkfifo(fifo)
    with pytest.raises(TableAccessError, match="is a FIFO"):
        _at_once(load_into, fifo, QTable(3, 2, Learning()), {})
    assert fifo.exists() and not list(tmp_path.glob("*.corrupt-*"))


def test_a_fifo_or_a_directory_as_the_lock_file_is_an_input_error(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / ".respecd.lock")
    with pytest.raises(InputError, match="is a FIFO"), _at_once(learning_into, tmp_path):
        pass
    os.unlink(tmp_path / ".respecd.lock")
    (tmp_path / ".respecd.lock").mkdir()
    with pytest.raises(InputError, match="is a directory"), learning_into(tmp_path):
        pass


@pytest.mark.e2e
def test_the_daemon_refuses_a_fifo_q_table_or_profile_with_exit_2(tmp_path: Path) -> None:
    state = tmp_path / "st"
    state.mkdir()
    os.mkfifo(state / "qtable-sim-rover.npz")
    result = _respecd("--duration", "5", "--state-dir", str(state), "--log-format", "json")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert f"--state-dir: {state}/qtable-sim-rover.npz: is a FIFO (named pipe)" in result.stderr
    check = _respecd("check-config", "builtin:sim-rover", "--state-dir", str(state))
    assert check.returncode == 2 and "qtable-sim-rover.npz: is a FIFO" in check.stderr
    os.mkfifo(tmp_path / "p.yaml")
    result = _respecd("--profile", str(tmp_path / "p.yaml"), "--duration", "5", "--state-dir", str(tmp_path / "s2"))
    assert result.returncode == 2 and f"{tmp_path}/p.yaml: is a FIFO (named pipe)" in result.stderr


@pytest.mark.e2e
def test_log_info_refuses_a_bag_whose_metadata_names_a_fifo(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    os.mkfifo(bag / "bag_0.mcap")
    meta = {"rosbag2_bagfile_information": {
        "version": 8, "storage_identifier": "mcap", "relative_file_paths": ["bag_0.mcap"],
        "duration": {"nanoseconds": 1}, "starting_time": {"nanoseconds_since_epoch": 1}, "message_count": 0,
        "topics_with_message_count": []}}
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    result = _respecd("log", "info", str(bag))
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert f"relative_file_paths.0: {bag}/bag_0.mcap: is a FIFO (named pipe)" in result.stderr
    os.unlink(bag / "metadata.yaml")
    os.mkfifo(bag / "metadata.yaml")
    result = _respecd("log", "info", str(bag))
    assert result.returncode == 2 and f"{bag}/metadata.yaml: is a FIFO" in result.stderr
    os.mkfifo(tmp_path / "x.bag")
    os.mkfifo(tmp_path / "x.mcap")
    for name in ("x.bag", "x.mcap"):
        result = _respecd("log", "info", str(tmp_path / name))
        assert result.returncode == 2 and f"{tmp_path / name}: is a FIFO" in result.stderr


def _profile(tmp_path: Path, **changes: object) -> Path:
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["perception"] = {"enabled": False}
    profile.update(changes)
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(profile))
    return path


@pytest.mark.e2e
@pytest.mark.parametrize("changes, line, said", [
    ({"recording": {"enabled": True, "path": "rec/" + "x" * 300 + ".mcap"}}, "recording.path",
     "a file name of 305 bytes, longer than the 255"),
    ({"recording": {"enabled": True, "path": "rec/a\x00b.mcap"}}, "recording.path", "contains a NUL character"),
    ({"name": "n" * 5000}, "name", "the Q-table is named after the profile: shorten name"),
])
def test_check_config_and_the_daemon_refuse_paths_no_file_system_takes(tmp_path: Path, changes: dict, line: str,
                                                                       said: str) -> None:
    """A 300-character recording.path name was a check-config traceback; a NUL in it or a 5,000-character
    name passed check-config and then was a traceback in the daemon."""
    profile = _profile(tmp_path, **changes)
    for argv in (["check-config", str(profile)], ["--profile", str(profile), "--duration", "3"]):
        result = _respecd(*argv, "--state-dir", str(tmp_path / "st"))
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
        assert re.search(rf"p\.yaml:\d+: {line}: .*{re.escape(said)}", result.stderr), result.stderr[-2000:]


@pytest.mark.e2e
def test_record_refuses_a_device_or_a_fifo(tmp_path: Path) -> None:
    """--record /dev/null or a FIFO recorded nothing, with exit 0."""
    os.mkfifo(tmp_path / "f.mcap")
    for target, kind in (("/dev/null", "a character device"), (str(tmp_path / "f.mcap"), "a FIFO (named pipe)")):
        result = _respecd("--record", target, "--duration", "3", "--state-dir", str(tmp_path / "st"))
        assert result.returncode == 2, result.stderr[-2000:]
        assert f"--record {target}: is {kind}; a recording is written to new regular files" in result.stderr
