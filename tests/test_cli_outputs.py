"""Output paths are checked before the work that fills them: a directory where a file goes,
a file where a folder goes, a folder that cannot be made or written is exit 2 at start with the
flag and the path, not a traceback after a finished evaluation, calibration, training or replay."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import Ran

from respecd.errors import InputError
from respecd.outputs import (
    check_output_dir,
    check_output_file,
    output_dir_problem,
    output_file_problem,
    recording_problem,
)
from respecd.preflight import check_state_dir

REPO = Path(__file__).resolve().parents[1]
RESPECD = [sys.executable, "-m", "respecd.cli"]


@pytest.fixture
def places(tmp_path: Path) -> dict[str, Path]:
    """An existing directory, an existing file, and a path below that file (its folder cannot exist)."""
    folder = tmp_path / "adir.pt"  # .pt: train's own suffix check must not be what refuses it
    folder.mkdir()
    file = tmp_path / "good.yaml"
    file.write_text("a: 1\n")
    return {"dir": folder, "file": file, "under_file": file / "sub" / "x.json", "tmp": tmp_path}


# -- the shared checks ------------------------------------------------------------------------
def test_a_file_path_that_is_a_directory_is_refused(places: dict[str, Path]) -> None:
    problem = output_file_problem(places["dir"], example="out.json")
    assert problem == f"{places['dir']}: is a directory; expected a file name to write (e.g. {places['dir']}/out.json)"
    with pytest.raises(InputError, match=f"^--json {places['dir']}: is a directory"):
        check_output_file("--json", places["dir"])


def test_a_file_below_a_file_is_refused(places: dict[str, Path]) -> None:
    problem = output_file_problem(places["under_file"])
    assert problem is not None and f"{places['file']} is a file, not a directory" in problem


def test_missing_folders_are_refused_only_where_the_command_does_not_make_them(tmp_path: Path) -> None:
    target = tmp_path / "new" / "deeper" / "out.json"
    assert output_file_problem(target, make_parents=False) == \
        f"{target}: no such directory {target.parent} (this command does not create it)"
    assert output_file_problem(target, make_parents=True) is None
    assert not (tmp_path / "new").exists()  # the folders made for the write test are gone again


def test_an_existing_file_is_never_refused(places: dict[str, Path]) -> None:
    assert output_file_problem(places["file"], make_parents=False) is None  # replacing it is the command's rule
    assert check_output_file("--out", None) is None  # the flag was not given


def test_a_pseudo_file_system_that_takes_no_files_is_refused() -> None:
    problem = output_file_problem(Path("/proc/respecd-x.json"))
    assert problem == "/proc/respecd-x.json: cannot write in /proc (it takes no new files)"


def test_a_directory_path_that_is_a_file_is_refused(places: dict[str, Path]) -> None:
    assert output_dir_problem(places["file"]) == \
        f"{places['file']}: is a file, not a directory; expected a directory to write into"
    with pytest.raises(InputError, match="^--keep "):
        check_output_dir("--keep", places["file"])
    assert output_dir_problem(places["dir"]) is None


def test_a_directory_that_must_be_new(places: dict[str, Path]) -> None:
    assert output_dir_problem(places["dir"], must_be_new=True) == \
        f"{places['dir']}: already exists (a directory); expected a new directory name"
    new = places["tmp"] / "a" / "bag"
    assert output_dir_problem(new, must_be_new=True) is None and not (places["tmp"] / "a").exists()
    assert output_dir_problem(new, make_parents=False, must_be_new=True) is not None


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through directory permissions")
def test_a_read_only_folder_is_caught_by_a_real_write(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert output_file_problem(ro / "x.json") == f"{ro / 'x.json'}: cannot write in {ro} (Permission denied)"
        assert output_dir_problem(ro / "new" / "dir") == f"{ro / 'new' / 'dir'}: cannot write in {ro} " \
                                                         "(Permission denied)"
    finally:
        ro.chmod(0o755)


def test_a_recording_template_is_checked_as_the_recorder_names_its_file(places: dict[str, Path]) -> None:
    assert recording_problem(str(places["dir"])) is not None
    template = f"{places['file']}/rec-{{time}}.mcap"
    problem = recording_problem(template)
    assert problem is not None and problem.startswith(f"{template} (now {places['file']}/rec-")
    assert f"{places['file']} is a file, not a directory" in problem
    assert recording_problem(str(places["tmp"] / "new" / "rec-{time}-{index}.mcap")) is None


def test_a_state_dir_that_is_a_file_says_so(places: dict[str, Path]) -> None:
    assert check_state_dir(places["file"]) == \
        f"{places['file']}: is a file, not a directory; the state directory holds the Q-table"


# -- every command that writes, through the real CLI (in this process; e2e: the console script) --
def _respecd(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*RESPECD, *args], capture_output=True, text=True, timeout=timeout, cwd=REPO)


def _refused(result: Ran | subprocess.CompletedProcess[str], flag: str, path: Path, what: str) -> None:
    assert result.returncode == 2, result.stderr[-2000:]
    assert "Traceback" not in result.stderr, result.stderr[-2000:]
    assert f"{flag} {path}: {what}" in result.stderr, result.stderr[-2000:]


IS_DIR = "is a directory"
IS_FILE = "is a file, not a directory"

# (command line with {dir}, {file}, {under_file}, {log}, {state}; the flag; which path; what is said)
CASES = [
    (["schema", "--out", "{dir}"], "--out", "dir", IS_DIR),
    (["schema", "--out", "{tmp}/no/such/s.json"], "--out", "tmp", "no such directory"),
    (["--duration", "2", "--record", "{dir}", "--state-dir", "{state}"], "--record", "dir", IS_DIR),
    (["--duration", "2", "--record", "{under_file}", "--state-dir", "{state}"], "--record", "under_file",
     "{file} " + IS_FILE),
    (["--duration", "2", "--state-dir", "{file}"], "--state-dir:", "file", IS_FILE),
    (["--replay", "{log}", "--speed", "max", "--report", "{dir}"], "--report", "dir", IS_DIR),
    (["--replay", "{log}", "--speed", "max", "--save-table", "{dir}"], "--save-table", "dir", IS_DIR),
    (["eval", "--data", "sim", "--out", "{file}", "--frames", "1", "--no-progress"], "--out", "file", IS_FILE),
    (["train", "--data", "sim", "--out", "{dir}", "--epochs", "1", "--steps", "1", "--eval-frames", "0",
      "--no-progress"], "--out", "dir", IS_DIR),
    (["calibrate", "--weights", "builtin:sim-rover", "--out", "{dir}", "--frames", "2", "--no-progress"],
     "--out", "dir", IS_DIR),
    (["calibrate", "--weights", "builtin:sim-rover", "--out", "{tmp}/c.pt", "--json", "{dir}", "--frames", "2",
      "--no-progress"], "--json", "dir", IS_DIR),
    (["train-policy", "--state-dir", "{state}", "--cache-dir", "{tmp}/cache", "--random-detector", "--out", "{dir}"],
     "--out", "dir", IS_DIR),
    (["train-policy", "--state-dir", "{under_file}", "--cache-dir", "{tmp}/cache", "--random-detector"],
     "--state-dir", "under_file", "{file} " + IS_FILE),
    (["train-policy", "--state-dir", "{state}", "--cache-dir", "{file}", "--random-detector"],
     "--cache-dir", "file", IS_FILE),
    (["log", "export", "--to", "rosbag2", "{log}", "{under_file}"], "OUT_DIR", "under_file", "{file} " + IS_FILE),
    (["bench", "pipeline", "--seconds", "1", "--json", "{dir}"], "--json", "dir", IS_DIR),
    (["bench", "replay", "--keep", "{file}", "--seconds", "1", "--record-seconds", "1"], "--keep", "file", IS_FILE),
    (["bench", "scenarios", "--figure", "{dir}"], "--figure", "dir", IS_DIR),
    (["bench", "soak", "--minutes", "0.05", "--record", "{file}"], "--record", "file", IS_FILE),
]


@pytest.mark.parametrize(("argv", "flag", "which", "what"), CASES, ids=[" ".join(c[0][:2]) + " " + c[1]
                                                                          for c in CASES])
def test_a_bad_output_path_is_refused_before_the_work(places: dict[str, Path], argv: list[str], flag: str,
                                                      which: str, what: str, cli: Callable[..., Ran]) -> None:
    log = places["tmp"] / "session.mcap"
    log.write_bytes(b"not a log")  # the output check comes first: the log is never opened
    state = places["tmp"] / "state"
    names = {k: str(v) for k, v in places.items()} | {"log": str(log), "state": str(state)}
    path = places[which] if which != "tmp" else places["tmp"] / "no" / "such" / "s.json"
    _refused(cli(*(a.format(**names) for a in argv)), flag, path, what.format(**names))
    assert not state.exists() and not (places["tmp"] / "cache").exists()  # nothing was started or left behind
    assert not list(places["tmp"].glob("*.tmp")) and not list(places["dir"].iterdir())


@pytest.mark.e2e
def test_a_recording_profile_whose_path_cannot_be_written_is_refused_with_its_line(places: dict[str, Path]) -> None:
    profile = places["tmp"] / "p.yaml"
    profile.write_text((REPO / "configs" / "sim-rover.yaml").read_text()
                       .replace("\nrecording:\n", f"\nrecording:\n  enabled: true\n  path: {places['dir']}\n", 1))
    line = profile.read_text().splitlines().index(f"  path: {places['dir']}") + 1
    expected = f"{profile}:{line}: recording.path: {places['dir']}: {IS_DIR}"
    for argv in (["check-config", str(profile)], ["--profile", str(profile), "--duration", "2", "--state-dir",
                                                   str(places["tmp"] / "state")]):
        result = _respecd(*argv, timeout=30)
        assert result.returncode == 2 and "Traceback" not in result.stderr and expected in result.stderr, \
            result.stderr[-2000:]
    good = places["tmp"] / "rec.mcap"
    result = _respecd("--profile", str(profile), "--duration", "1", "--state-dir", str(places["tmp"] / "state"),
                      "--record", str(good), "--log-format", "json", timeout=120)  # --record replaces the path
    assert result.returncode == 0 and good.is_file(), result.stderr[-2000:]


def test_a_lab_tool_refuses_a_directory_as_its_output_file(places: dict[str, Path], cli: Callable[..., Ran]) -> None:
    _refused(cli("experiment", "latency", "--repeats", "1", str(places["dir"])), "OUT", places["dir"], IS_DIR)
