"""Shared fixtures: paths to shared data, one torch thread, the command line in-process, and a
guard against leaked threads."""

from __future__ import annotations

import contextlib
import io
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
import structlog

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data" / "real"


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared captures not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def one_torch_thread():
    """One intra-op torch thread (perception tests: on a shared 2-core runner, two
    spin-waiting threads run slower)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@dataclass(frozen=True)
class Ran:
    """What a command did: its exit status and what it printed."""

    returncode: int
    stdout: str
    stderr: str


def run_cli(*args: str) -> Ran:
    """``respecd ARGS`` through its own parser and ``main`` in this process: argument checks and
    start-up refusals without an interpreter each. The logging the command configured is undone."""
    from respecd.cli import main

    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(list(args))
            except SystemExit as exited:  # argparse: a bad argument (2) or --help (0)
                code = int(exited.code or 0)
    finally:
        structlog.reset_defaults()
        root.handlers[:] = handlers
        root.setLevel(level)
    return Ran(code, out.getvalue(), err.getvalue())


@pytest.fixture
def cli() -> Callable[..., Ran]:
    """``run_cli``, for a test that asks for it by name."""
    return run_cli


@pytest.fixture(autouse=True)
def no_leaked_threads():
    """Fail a test that leaves non-daemon worker threads running (they would outlive a stop)."""
    before = set(threading.enumerate())
    yield
    leaked = []
    for thread in set(threading.enumerate()) - before:
        if isinstance(thread, threading._DummyThread):
            continue  # a foreign (Rust, C) thread that called into Python: not ours to join
        thread.join(timeout=2.0)
        if thread.is_alive() and not thread.daemon:
            leaked.append(thread.name)
    assert not leaked, f"threads left running: {leaked}"


@pytest.fixture
def radar(tmp_path: Path):
    """An IWR6843 on two pseudo-terminals streaming the real capture (tests/fake_radar.py)."""
    from fake_radar import FakeRadar, capture_frames

    fake = FakeRadar(tmp_path, capture_frames())
    yield fake
    fake.unplug()


FLEET_RATES = [(30, 9, 30), (15, 5, 10), (10, 9, 15), (5, 3, 30), (30, 5, 5), (15, 9, 10)]  # rgb, thermal, radar Hz


@pytest.fixture(scope="session")
def fleet_logs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Six short simulated sessions recorded through ``respecd --record``, each at other sensor
    rates (so each log's recorded rates differ), detector off; recorded two at a time."""
    import subprocess
    import sys

    import yaml

    root = tmp_path_factory.mktemp("fleet")
    (root / "logs").mkdir()
    base = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    jobs = []
    for i, (rgb, thermal, radar) in enumerate(FLEET_RATES):
        profile = dict(base, name="sim-rover-fleet")
        sensors = {s["name"]: dict(s) for s in base["sensors"] if s["name"] != "depth"}
        sensors["rgb"].update(rate_hz=rgb, resolution=[640, 360])
        sensors["thermal"]["rate_hz"] = thermal
        sensors["radar"]["rate_hz"] = radar
        profile.update(sensors=list(sensors.values()), perception={"enabled": False},
                       controller={"decision_period_s": 0.5, "window_s": 0.5, "min_dwell_s": 0.5},
                       recording={"chunk_size_kib": 256})
        profile["simulation"] = dict(base["simulation"], scenario_duration_s=1.5)
        config = root / f"profile{i}.yaml"
        config.write_text(yaml.safe_dump(profile))
        log = root / "logs" / f"rover{i}.mcap"
        argv = [sys.executable, "-m", "respecd.cli", "--config", str(config), "--duration", "3", "--seed", str(i),
                "--record", str(log), "--state-dir", str(root / f"state{i}"), "--log-level", "warning"]
        jobs.append((log, argv))
    for pair in (jobs[i:i + 2] for i in range(0, len(jobs), 2)):
        running = [(log, subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
                   for log, argv in pair]
        for log, proc in running:
            out, _ = proc.communicate(timeout=180)
            assert proc.returncode == 0 and log.is_file(), out[-2000:]
    return [log for log, _ in jobs]
