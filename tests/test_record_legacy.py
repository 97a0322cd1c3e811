"""Logs written by respecd 0.1.0's first format (JSON messages, base64 payloads, labels in
the overlays) stay readable: ``log info`` describes them and their frames decode exactly.

``tests/data/legacy-v1.mcap`` was recorded by that version from a small sim-rover profile
(RGB 640x360, the sim's smallest, at 5 Hz, thermal, radar, depth at 2 Hz, IMU; controller off), 2.5 s.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from conftest import run_cli

from respecd.record.reader import open_log

LEGACY = Path(__file__).parent / "data" / "legacy-v1.mcap"


def test_log_info_describes_a_first_format_log() -> None:
    done = run_cli("log", "info", str(LEGACY), "--json")
    assert done.returncode == 0, done.stderr
    info = json.loads(done.stdout)
    assert info["profile"] == "sim-rover-legacy" and info["ground_truth"] is True
    assert {name: s["frames"] for name, s in info["sensors"].items()} == {
        "depth": 5, "imu": 76, "radar": 25, "rgb": 10, "thermal": 23}


def test_first_format_frames_decode_with_their_times_and_ground_truth() -> None:
    log = open_log(LEGACY)
    rgb = list(log.frames("rgb"))
    assert len(rgb) == 10 and rgb[0].data.shape == (360, 640, 3) and "gt" in rgb[0].meta
    assert all(b.t > a.t for a, b in zip(rgb, rgb[1:], strict=False))
    thermal = next(iter(log.frames("thermal")))
    assert thermal.data.dtype == np.uint16 and thermal.data.min() > 20000  # centikelvin
    radar = next(iter(log.frames("radar")))
    assert radar.data.dtype == np.float32 and radar.data.shape[1] == 5
    imu = next(iter(log.frames("imu")))
    assert imu.data.shape == (6,)
