"""``respecd log info LOG`` through the real CLI entry point."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from respecd.cli import main
from respecd.clock import ManualClock
from respecd.messages import Frame
from respecd.record.config import RecordingConfig
from respecd.record.recorder import Recorder


@pytest.fixture
async def small_log(tmp_path: Path) -> Path:
    clock = ManualClock()
    recorder = Recorder(RecordingConfig(path=str(tmp_path / "s.mcap")), {"name": "bench-rig", "sensors": []}, clock)
    recorder.start()
    for i in range(21):  # 2 s at 10 Hz
        clock.set(i / 10)
        meta = {"gt": [[1.0, 2.0, 3.0, 4.0]]}
        recorder.on_frame("front", Frame("rgb", i / 10, i, np.full((36, 64, 3), i, np.uint8), meta))
        recorder.on_frame("radar", Frame("radar", i / 10, i, np.ones((3, 5), np.float32), {"raw": b"\x02\x01"}))
    await recorder.close()
    return recorder.paths[0]


def test_info_lists_channels_sensors_duration_and_profile(small_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", "info", str(small_log)]) == 0
    out = capsys.readouterr().out
    assert "profile:   bench-rig" in out
    assert "duration:  2.00 s" in out
    assert "ground truth: yes" in out
    assert "front        rgb" in out and "21 frames" in out and "10.0 Hz" in out
    assert "/sensors/radar/raw" in out and "respecd.RawBytes" in out


def test_info_json_and_truncated(small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = tmp_path / "cut.mcap"
    data = small_log.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.8)])
    assert main(["log", "info", "--json", str(cut)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["truncated"] is True
    assert info["sensors"]["front"]["modality"] == "rgb"
    assert 0 < info["sensors"]["front"]["frames"] <= 21


def test_info_on_missing_file_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", "info", str(tmp_path / "none.mcap")]) == 2
    err = capsys.readouterr().err
    assert "none.mcap: no such file" in err and "Traceback" not in err


@pytest.mark.e2e
def test_a_log_that_cannot_be_read_is_exit_2_without_traceback(small_log: Path) -> None:
    """chmod 000 as a user who may not read it (root reads anyway: uid 65534 through setpriv)."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    if os.geteuid() == 0 and shutil.which("setpriv") is None:
        pytest.skip("root reads through permissions and setpriv is missing")
    folder = Path(tempfile.mkdtemp(prefix="respecd-noperm-"))
    try:
        folder.chmod(0o755)
        log = folder / "noperm.mcap"
        shutil.copy(small_log, log)
        log.chmod(0)
        writable = folder / "w"  # the export's folder may be written by that user: only the log is refused
        writable.mkdir(mode=0o777)
        writable.chmod(0o777)
        drop = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] if os.geteuid() == 0 else []
        cli = [*drop, sys.executable, "-m", "respecd.cli"]
        env = {**os.environ, "HOME": str(folder), "XDG_STATE_HOME": str(folder), "XDG_CACHE_HOME": str(folder)}
        for args in (["log", "info", str(log)], ["--replay", str(log), "--speed", "max"],
                     ["log", "export", str(log), "--to", "rosbag2", str(writable / "out")]):
            result = subprocess.run([*cli, *args], capture_output=True, text=True, timeout=120, env=env,
                                    cwd=folder)
            assert result.returncode == 2, (args, result.stderr)
            assert "Traceback" not in result.stderr
            assert f"respecd: {log}: cannot read session log: Permission denied" in result.stderr
    finally:
        shutil.rmtree(folder)
