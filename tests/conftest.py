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
