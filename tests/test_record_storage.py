"""A disk that refuses writes or runs low: recording pauses with one line, keeps what it
wrote readable, says what is really on disk, resumes when there is room; old recordings
make room oldest session first."""

from __future__ import annotations

import base64
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from datetime import datetime, timezone
from pathlib import Path

import pytest
import structlog
import yaml
from conftest import run_cli
from structlog.testing import capture_logs

from respecd.record import writer as writer_module
from respecd.record.codec import Message
from respecd.record.config import RecordingConfig
from respecd.record.reader import open_log
from respecd.record.storage import MIB, Retention, recordings
from respecd.record.writer import SegmentWriter

REPO = Path(__file__).resolve().parents[1]
STARTED = datetime(2026, 12, 1, 8, 0, 0, tzinfo=timezone.utc)


def _message(i: int) -> Message:
    payload = json.dumps({"i": i, "pad": base64.b64encode(os.urandom(900)).decode()}).encode()  # ~1.2 kB
    return Message("/respecd/percept", "respecd.Percept", payload, {})


class Wall:
    """The wall clock the writer waits on between retries while paused."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _writer(tmp_path: Path, wall: Wall | None = None, **config: object) -> SegmentWriter:
    settings = {"path": str(tmp_path / "rec-{time}.mcap"), "chunk_size_kib": 16, "flush_s": 0.05, "fsync": False,
                "min_free_mib": 0.0, **config}
    meta = {"respecd.session": {"segment": "0"}}
    return SegmentWriter(RecordingConfig(**settings), meta, STARTED, monotonic=wall or Wall())


def _on_disk(paths: list[Path]) -> int:
    return sum(open_log(p).message_count for p in paths if p.exists())


@pytest.fixture
def file_size_limit() -> Iterator[Callable[[int | None], None]]:
    """Lower this process's file-size limit (a real EFBIG from the kernel, no root needed)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of being killed

    def limit(size: int | None) -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft if size is None else size, hard))

    yield limit
    resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    signal.signal(signal.SIGXFSZ, previous)


def test_a_refused_write_pauses_once_keeps_what_was_written_and_resumes(
    tmp_path: Path, file_size_limit: Callable[[int | None], None]
) -> None:
    wall = Wall()
    segments = _writer(tmp_path, wall)
    with capture_logs() as logs:
        assert segments.open(0.0) is not None
        file_size_limit(200_000)
        for i in range(400):  # ~480 kB offered against a 200 kB limit
            segments.put(_message(i), i * 1_000_000, i * 0.01)
        assert segments.state == "paused" and "File too large" in (segments.reason or "")
        file_size_limit(None)
        wall.t += writer_module.RETRY_S  # the disk has room again: the next message finds out
        for i in range(400, 450):
            segments.put(_message(i), i * 1_000_000, i * 0.01)
        segments.close()
    assert segments.state == "recording" and len(segments.paths) == 2
    paused = [e for e in logs if e["event"] == "record.paused"]
    assert len(paused) == 1 and paused[0]["log_level"] == "error"  # one line, not one per message
    assert [e["event"] for e in logs].count("record.resumed") == 1
    assert open_log(segments.paths[0]).truncated  # cut back to its last complete chunk: readable
    assert _on_disk(segments.paths) == segments.messages  # the count is what is really on disk
    assert segments.messages + segments.lost == 450 and segments.lost > 0
    assert segments.on_disk_bytes == sum(p.stat().st_size for p in segments.paths)


def test_below_the_free_space_floor_nothing_is_started(tmp_path: Path) -> None:
    free_mib = shutil.disk_usage(tmp_path).free / MIB
    segments = _writer(tmp_path, min_free_mib=free_mib + 1024)
    with capture_logs() as logs:
        assert segments.open(0.0) is None
        for i in range(100):
            segments.put(_message(i), i, i * 0.01)
        segments.close()
    assert segments.state == "paused" and "below recording.min_free_mib" in (segments.reason or "")
    assert [e["event"] for e in logs] == ["record.paused"] and logs[0]["log_level"] == "warning"
    assert segments.lost == 100 and not list(tmp_path.iterdir())


@pytest.mark.skipif(os.geteuid() != 0, reason="mounts a small tmpfs")
def test_crossing_the_floor_finishes_the_file_cleanly(tmp_path: Path) -> None:
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(disk)], check=False).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        segments = _writer(disk, min_free_mib=2.0)
        with capture_logs() as logs:
            for i in range(4000):
                segments.put(_message(i), i * 1_000_000, i * 0.01)
            segments.close()
        assert segments.state == "paused" and [e["event"] for e in logs].count("record.paused") == 1
        log = open_log(segments.paths[0])
        assert not log.truncated and log.message_count == segments.messages  # summary and footer written
        assert shutil.disk_usage(disk).free >= 1.5 * MIB
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def _fake_session(directory: Path, stamp: str, sizes: list[int]) -> list[Path]:
    paths = []
    for index, size in enumerate(sizes):
        name = f"rec-{stamp}.mcap" if index == 0 else f"rec-{stamp}-{index:03d}.mcap"
        path = directory / name
        path.write_bytes(b"\0" * size)
        paths.append(path)
    return paths


def test_retention_deletes_the_oldest_session_first(tmp_path: Path) -> None:
    oldest = _fake_session(tmp_path, "20261130T080000", [300_000, 300_000])
    middle = _fake_session(tmp_path, "20261130T120000", [300_000])
    newest = _fake_session(tmp_path, "20261201T070000", [300_000])
    (tmp_path / "notes.txt").write_text("not a recording")
    open_path = tmp_path / "rec-20261201T080000.mcap"
    open_path.write_bytes(b"\0" * 100_000)
    template = str(tmp_path / "rec-{time}.mcap")
    assert [r.path for r in recordings(template)] == [*oldest, *middle, *newest, open_path]
    with capture_logs() as logs:
        deleted = Retention(template, 650_000, 0, False).enforce([open_path], open_path, 100_000)
    assert [d.path for d in deleted] == [*oldest, *middle]  # 1.3 MB -> 0.4 MB, oldest session first
    assert newest[0].exists() and open_path.exists() and (tmp_path / "notes.txt").exists()
    assert [e["reason"] for e in logs] == ["max_bytes"] * 3


def test_a_long_recording_stays_under_max_bytes(tmp_path: Path) -> None:
    _backdate(_fake_session(tmp_path, "20261130T080000", [400_000]))
    segments = _writer(tmp_path, rotate_mib=1, max_bytes=2 * MIB + 200_000)
    for i in range(4000):  # ~4.8 MB offered
        segments.put(_message(i), i * 1_000_000, i * 0.01)
    segments.close()
    on_disk = recordings(str(tmp_path / "rec-{time}.mcap"))
    assert sum(r.size for r in on_disk) <= 2 * MIB + 200_000 + MIB + 64_000  # the cap, plus the open segment
    assert all(r.session == "20261201T080000" for r in on_disk)  # the older session went first
    assert on_disk[-1].path == segments.paths[-1] and segments.state == "recording"


def _backdate(paths: list[Path], hours: float = 24.0) -> list[Path]:
    """Files last written ``hours`` before this session (what retention takes as proof they are older)."""
    when = STARTED.timestamp() - hours * 3600
    for path in paths:
        os.utime(path, (when, when))
    return paths


def test_retention_never_takes_the_live_session_for_a_name_dated_later(tmp_path: Path) -> None:
    """Three older files named as if recorded in 2099 sorted after the live session: with max_bytes set,
    21 of the live session's 22 segments were deleted and the 2099 files kept."""
    future = _backdate(_fake_session(tmp_path, "20991231T000000", [700_000, 700_000, 700_000]))
    segments = _writer(tmp_path, rotate_mib=1, max_bytes=4 * MIB)  # room for this session, not all of both
    for i in range(2500):  # ~3 MB: three segments of this session
        segments.put(_message(i), i * 1_000_000, i * 0.01)
    segments.close()
    assert all(path.exists() for path in segments.paths)  # none of the live session's segments
    assert sum(not p.exists() for p in future) >= 1 and len(segments.paths) >= 3


def test_retention_leaves_files_written_since_the_session_started(tmp_path: Path) -> None:
    """A file matching the template but written after this session began is not provably an earlier
    session's (another daemon, a copy in progress): counted, never deleted."""
    template = str(tmp_path / "rec-{time}.mcap")
    older = _backdate(_fake_session(tmp_path, "20261130T080000", [300_000]))
    stranger = _fake_session(tmp_path, "20200101T000000", [300_000])  # an old name, written just now
    mine = tmp_path / "rec-20261201T080000.mcap"
    mine.write_bytes(b"\0" * 100_000)
    retention = Retention(template, 200_000, 0, False, started=STARTED.timestamp())
    with capture_logs() as logs:
        deleted = retention.enforce([mine], mine, 100_000)
    assert [d.path for d in deleted] == older and stranger[0].exists() and mine.exists()
    assert [e["event"] for e in logs] == ["record.pruned", "record.over_max_bytes"]


@pytest.mark.parametrize("settings, problem", [
    ({"max_bytes": 1}, "max_bytes 1 is less than two segments of rotate_mib 512 MiB"),
    ({"rotate_mib": 0.001}, "greater than or equal to 1"),
])
def test_nonsensical_sizes_are_profile_errors(tmp_path: Path, settings: dict, problem: str) -> None:
    from respecd.config import read_profile
    from respecd.errors import ConfigError

    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["recording"] = settings
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(profile))
    with pytest.raises(ConfigError) as info:
        read_profile(path)
    assert any(problem in line and "recording" in line for line in info.value.problems), info.value.problems


@pytest.mark.e2e
def test_daemon_on_a_refusing_disk_runs_on_and_says_so(tmp_path: Path) -> None:
    profile = yaml.safe_load((REPO / "configs" / "sim-rover.yaml").read_text())
    profile["perception"] = {"enabled": False}
    profile["recording"] = {**profile["recording"], "min_free_mib": 0}
    config = tmp_path / "p.yaml"
    config.write_text(yaml.safe_dump(profile))
    record = tmp_path / "rec" / "x.mcap"

    def limit() -> None:  # in the child: 1.5 MB per file, EFBIG instead of SIGXFSZ
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1_500_000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    argv = [sys.executable, "-m", "respecd.cli", "--config", str(config), "--duration", "4", "--record", str(record),
            "--state-dir", str(tmp_path / "st"), "--log-format", "json"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, preexec_fn=limit)  # noqa: PLW1509
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Traceback" not in done.stdout + done.stderr
    events = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    noisy = [e for e in events if e.get("level") in ("warning", "error")]
    assert [e["event"] for e in noisy if e["event"].startswith("record.")] == ["record.paused"]
    closed = next(e for e in events if e["event"] == "record.closed")
    assert closed["messages"] == _on_disk([Path(p) for p in closed["paths"]]) > 0 and closed["lost"] > 0
    statuses = [e["recording"] for e in events if e["event"] == "status"]
    assert statuses[-1]["state"] == "paused" and statuses[-1]["messages"] <= closed["messages"]
    structlog.reset_defaults()


def test_a_segment_never_overwrites_an_existing_file(tmp_path: Path) -> None:
    earlier = tmp_path / "rec-20261201T080000.mcap"  # an earlier session's file under this session's name
    earlier.write_bytes(b"an earlier session")
    segments = _writer(tmp_path)
    with capture_logs() as logs:
        assert segments.open(0.0) is None
        for i in range(20):
            segments.put(_message(i), i, i * 0.01)
        segments.close()
    assert earlier.read_bytes() == b"an earlier session"
    assert segments.state == "paused" and "File exists" in (segments.reason or "") and segments.paths == []
    paused = [e for e in logs if e["event"] == "record.paused"]
    assert len(paused) == 1 and "MiB are free" not in paused[0]["resumes"]  # the disk is not to blame


@pytest.mark.parametrize("existing", ["run.mcap", "run-001.mcap"])
def test_the_daemon_refuses_a_recording_name_already_taken(tmp_path: Path, existing: str) -> None:
    """`--record run.mcap` twice: the second run stops at start (exit 2) instead of overwriting the first,
    also when only a later segment of an earlier session under that name is left."""
    (tmp_path / existing).write_bytes(b"yesterday's session")
    done = run_cli("--duration", "5", "--record", str(tmp_path / "run.mcap"), "--state-dir", str(tmp_path / "state"))
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert f"{tmp_path / existing} exists and a recording is never overwritten" in done.stderr
    assert (tmp_path / existing).read_bytes() == b"yesterday's session"
    assert sorted(p.name for p in tmp_path.iterdir()) == [existing]  # nothing started: no state dir, no log


@pytest.mark.parametrize("template", ["rec-{time}.mcap", "rec-{time}-{index}.mcap"])
def test_retention_sees_segments_past_999(tmp_path: Path, template: str) -> None:
    """Segment 1000 gets a four-digit number; a three-digit pattern hid it and every later one from
    max_bytes and delete_oldest, and a days-long recording filled the disk."""
    for index in (998, 999, 1000, 1001, 12345):
        writer_module.segment_path(str(tmp_path / template), STARTED, index).write_bytes(b"x")
    found = recordings(str(tmp_path / template))
    assert [r.index for r in found] == [998, 999, 1000, 1001, 12345]  # all of them, in segment order
