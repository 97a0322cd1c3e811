"""A valid profile checked against this machine before anything starts: files it names,
the torch device, the Q-table of a frozen policy, a writable state directory."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import Ran, run_cli

from respecd.config import read_profile
from respecd.preflight import check_profile, check_state_dir, device_problem

REPO = Path(__file__).resolve().parents[1]
SIM = (REPO / "configs" / "sim-rover.yaml").read_text()
RESPECD = [sys.executable, "-m", "respecd.cli"]


def _profile(tmp_path: Path, extra: str, name: str = "p.yaml") -> Path:
    """sim-rover.yaml plus ``extra``; an extra ``controller:`` block's keys go into the profile's own."""
    path = tmp_path / name
    if extra.startswith("controller:\n"):
        path.write_text(SIM.replace("\ncontroller:\n", "\n" + extra, 1))
    else:
        path.write_text(SIM + extra)
    return path


def _line(path: Path, text: str) -> int:
    return path.read_text().splitlines().index(text) + 1


def _run(*args: str) -> Ran:
    """The command's start-up checks, in this process (they refuse before anything runs)."""
    return run_cli(*args)


def _spawn(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """The console script in an interpreter of its own: a run that gets past its start-up checks."""
    return subprocess.run([*RESPECD, *args], capture_output=True, text=True, timeout=timeout)


def test_shipped_sim_profiles_pass_the_machine_checks(tmp_path: Path) -> None:
    lab = REPO / "respecd" / "lab" / "profiles"
    for path in (REPO / "configs" / "sim-rover.yaml", lab / "sim-rover-no-load.yaml",
                 lab / "sim-rover-paper-reward.yaml"):
        assert check_profile(read_profile(path), tmp_path) == []


def test_missing_weights_are_named_with_their_line(tmp_path: Path) -> None:
    path = _profile(tmp_path, "perception:\n  weights: /nonexistent/rover.pt\n")
    line = _line(path, "  weights: /nonexistent/rover.pt")
    assert check_profile(read_profile(path)) == [
        f"{path}:{line}: perception.weights: /nonexistent/rover.pt: no such checkpoint file"
    ]
    result = _run("check-config", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr and "perception.weights" in result.stderr


def test_a_builtin_checkpoint_name_cannot_leave_the_package(tmp_path: Path) -> None:
    path = _profile(tmp_path, "perception:\n  weights: builtin:../../control/tables/x\n")
    problem, = check_profile(read_profile(path))
    assert "perception.weights: builtin:../../control/tables/x: a built-in checkpoint is named by a plain" in problem


def test_files_a_sensor_names_must_exist(tmp_path: Path) -> None:
    extra = (
        "  - {name: radar2, driver: iwr6843, modality: radar, cli_port: /dev/null, data_port: /dev/null,\n"
        "     base_cfg: /nonexistent/my.cfg}\n"
        "  - {name: cam2, driver: uvc, device: /nonexistent/clip.mp4}\n"
    )
    path = _profile(tmp_path, extra)
    problems = check_profile(read_profile(path))
    radar_line = _line(path, extra.splitlines()[1])  # the key's own line
    cam_line = _line(path, extra.splitlines()[2])
    assert problems == [
        f"{path}:{radar_line}: sensors.5.base_cfg: /nonexistent/my.cfg: no such file",
        f"{path}:{cam_line}: sensors.6.device: /nonexistent/clip.mp4: no such video file",
    ]


def test_a_frozen_policy_needs_the_table_it_names(tmp_path: Path) -> None:
    path = _profile(tmp_path, "controller:\n  policy: exploit\n  table_file: rover.npz\n")
    problem, = check_profile(read_profile(path), tmp_path / "state")
    assert f"controller.table_file: {tmp_path / 'state' / 'rover.npz'}: no such Q-table" in problem
    result = _run("check-config", "--state-dir", str(tmp_path / "state"), str(path))
    assert result.returncode == 2 and "rover.npz: no such Q-table" in result.stderr
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "rover.npz").write_bytes(b"")
    assert check_profile(read_profile(path), tmp_path / "state") == []


@pytest.mark.parametrize("device", ["cuda:99", "tpu", "cuda:x"])
def test_a_device_this_torch_cannot_use_is_a_profile_error(tmp_path: Path, device: str) -> None:
    path = _profile(tmp_path, f"perception:\n  device: {device}\n")
    problem, = check_profile(read_profile(path))
    assert problem.startswith(f"{path}:{_line(path, f'  device: {device}')}: perception.device: ")
    assert device_problem("cpu") is None


def test_the_daemon_refuses_an_unusable_device_at_start(tmp_path: Path) -> None:
    path = _profile(tmp_path, "perception:\n  device: cuda:99\n")
    result = _run("--config", str(path), "--duration", "5", "--state-dir", str(tmp_path / "st"))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{path}:{_line(path, '  device: cuda:99')}: perception.device: 'cuda:99' cannot be used" in result.stderr


@pytest.mark.skipif(torch.version.cuda is not None, reason="this torch has CUDA: spec-rover's device is usable")
def test_check_config_of_the_real_rover_profile_says_cuda_is_missing() -> None:
    result = _run("check-config", str(REPO / "configs" / "spec-rover.yaml"))
    profile = REPO / "configs" / "spec-rover.yaml"
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"spec-rover.yaml:{_line(profile, '  device: cuda')}: perception.device: 'cuda' cannot be used: " \
           "this torch" in result.stderr


def test_state_dir_that_cannot_be_created_stops_the_daemon_at_start(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    result = _run("--duration", "5", "--state-dir", str(blocker / "state"))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"--state-dir: {blocker / 'state'}: state directory is not writable" in result.stderr


def test_check_config_refuses_the_state_dir_the_daemon_would_refuse(tmp_path: Path) -> None:
    """check-config's ok means the daemon starts: a learning profile needs a state directory it can make."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    result = _run("check-config", "--state-dir", str(blocker / "state"), "builtin:sim-rover")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"--state-dir: {blocker / 'state'}: state directory is not writable (Not a directory)" in result.stderr
    result = _run("check-config", "--state-dir", str(blocker / "state"), str(_profile(tmp_path, "controller:\n"
                  "  policy: static\n")))
    assert result.returncode == 0, result.stderr  # nothing is learned, nothing is saved


def test_asking_about_a_missing_state_dir_leaves_nothing_behind(tmp_path: Path) -> None:
    state = tmp_path / "new" / "state"
    assert check_state_dir(state, create=False) is None
    assert not (tmp_path / "new").exists()
    assert check_state_dir(state) is None and state.is_dir() and not list(state.iterdir())  # the daemon keeps it


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes through directory permissions (the hardening check "
                    "mounts a read-only tmpfs instead)")
def test_read_only_state_dir_is_caught_by_a_real_write(tmp_path: Path) -> None:
    state = tmp_path / "ro"
    state.mkdir()
    state.chmod(0o555)
    try:
        assert check_state_dir(state) is not None
    finally:
        state.chmod(0o755)
    assert check_state_dir(state) is None and not list(state.iterdir())  # the probe leaves nothing behind


@pytest.mark.e2e
def test_a_frozen_policy_runs_from_a_read_only_state_dir(tmp_path: Path) -> None:
    """Only learning writes the state directory; exploit may run from a read-only image."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    result = _spawn("--duration", "1", "--policy", "exploit", "--state-dir", str(blocker / "state"), timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]


@pytest.mark.skipif(os.geteuid() != 0, reason="mounts a read-only tmpfs")
def test_read_only_mounted_state_dir_is_exit_2_at_start(tmp_path: Path) -> None:
    state = tmp_path / "ro"
    state.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(state)], check=False).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        result = _run("--duration", "3", "--state-dir", str(state))
    finally:
        subprocess.run(["umount", str(state)], check=False)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"--state-dir: {state}: state directory is not writable (Read-only file system)" in result.stderr


def test_a_replay_sensor_outside_replay_is_a_profile_error(tmp_path: Path) -> None:
    extra = "  - {name: imu2, driver: replay, source: nope.mcap, modality: imu, rate_hz: 30}\n"
    path = _profile(tmp_path, extra)
    problem, = check_profile(read_profile(path))
    assert problem.startswith(f"{path}:{_line(path, extra.rstrip())}: sensors.5.driver: driver 'replay' serves a "
                              "recorded log and works only under `respecd --replay LOG`")
    result = _run("check-config", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "sensors.5.driver: driver 'replay'" in result.stdout + result.stderr


def test_weights_that_are_a_directory_or_no_torch_file_are_named(tmp_path: Path) -> None:
    (tmp_path / "adir").mkdir()
    path = _profile(tmp_path, f"perception:\n  weights: {tmp_path / 'adir'}\n")
    problem, = check_profile(read_profile(path))
    assert problem.endswith(f"perception.weights: {tmp_path / 'adir'}: is a directory, expected a checkpoint file")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(os.urandom(20_000).replace(b"PK", b"pk").lstrip(b"\x80"))
    path = _profile(tmp_path, f"perception:\n  weights: {garbage}\n", "q.yaml")
    problem, = check_profile(read_profile(path))
    assert f"perception.weights: {garbage}: not a torch checkpoint: it looks like" in problem
    assert "expected a respecd checkpoint written by `respecd train`" in problem


@pytest.mark.e2e
def test_a_second_learning_daemon_on_the_same_state_dir_is_refused(tmp_path: Path) -> None:
    """Each would save its Q-table over the other's; the first holds the directory until it ends."""
    import signal
    import time

    state = tmp_path / "state"
    argv = [*RESPECD, "--state-dir", str(state), "--log-format", "json"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True) as first:
        try:
            assert first.stdout is not None
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and "driver_started" not in first.stdout.readline():
                assert first.poll() is None
            second = _spawn("--duration", "2", "--state-dir", str(state))
            assert second.returncode == 2 and "Traceback" not in second.stderr
            assert f"another respecd (pid {first.pid}) is learning into this state directory" in second.stderr
            static = _spawn("--duration", "1", "--policy", "static", "--state-dir", str(state))
            assert static.returncode == 0  # a policy that only reads the table runs beside it
            first.send_signal(signal.SIGTERM)
            assert first.wait(timeout=30) == 0
        finally:
            if first.poll() is None:
                first.kill()
    assert _spawn("--duration", "1", "--state-dir", str(state), timeout=120).returncode == 0  # released at exit


def test_portable_check_config_passes_the_jetson_profile_and_names_what_it_left_out() -> None:
    """Studying the robot's profile on a laptop: the profile's own checks, not this machine's."""
    result = _run("check-config", "--portable", str(REPO / "configs" / "spec-rover.yaml"))
    assert result.returncode == 0, result.stderr
    assert "spec-rover.yaml: ok (spec-rover, 5 sensors, portable)" in result.stdout
    assert "left out (this machine's checks, not the profile's):" in result.stdout
    assert "    perception.device: 'cuda'" in result.stdout and "Q-table" in result.stdout
    if torch.version.cuda is None:
        assert "(here: 'cuda' cannot be used: this torch" in result.stdout  # what the plain check would say


def test_portable_check_takes_each_runtimes_own_devices(tmp_path: Path) -> None:
    """tensorrt and gpu are devices of onnxruntime and openvino, not of torch: a machine without them
    skips the check; a device the runtime never names is the profile's mistake."""
    for runtime, device in [("onnxruntime", "tensorrt"), ("openvino", "gpu")]:
        robot = _profile(tmp_path, f"perception:\n  runtime: {runtime}\n  device: {device}\n  precision: f16\n")
        result = _run("check-config", "--portable", str(robot))
        assert result.returncode == 0, result.stderr
        assert f"perception.device: '{device}'" in result.stdout
    typo = _profile(tmp_path, "perception:\n  runtime: openvino\n  device: cuda\n", "typo.yaml")
    result = _run("check-config", "--portable", str(typo))
    assert result.returncode == 2 and "'cuda' is not a device of runtime openvino" in result.stderr


def test_portable_check_skips_the_robots_files_but_not_the_profiles_mistakes(tmp_path: Path) -> None:
    robot = _profile(tmp_path, "perception:\n  weights: /var/lib/respecd/mine.pt\n  device: cuda:1\n")
    robot.write_text(robot.read_text().replace(  # the profile's own recording section, switched on
        "recording:\n", "recording:\n  enabled: true\n  path: /var/lib/respecd/rec/r-{time}.mcap\n", 1))
    result = _run("check-config", "--portable", str(robot))
    assert result.returncode == 0, result.stderr
    assert "perception.weights: /var/lib/respecd/mine.pt (not on this machine)" in result.stdout
    assert "recording.path: /var/lib/respecd/rec/r-{time}.mcap" in result.stdout
    assert _run("check-config", str(robot)).returncode == 2  # the plain check stays this machine's
    for extra, found in [("perception:\n  device: cdua\n", "perception.device: 'cdua' is not a torch device"),
                         ("perception:\n  weights: builtin:nope\n", "no built-in checkpoint named 'nope'"),
                         ("perception:\n  score_threshold: 2\n", "perception.score_threshold")]:
        result = _run("check-config", "--portable", str(_profile(tmp_path, extra, "bad.yaml")))
        assert result.returncode == 2 and found in result.stderr and "Traceback" not in result.stderr
