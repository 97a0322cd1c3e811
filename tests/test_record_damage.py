"""Damaged logs: a flipped byte anywhere, or a cut anywhere, never raises and never passes
altered data off as good — whatever differs from what was recorded is reported as damage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from respecd.cli import main
from respecd.clock import ManualClock
from respecd.errors import InputError
from respecd.messages import Frame
from respecd.record.config import RecordingConfig
from respecd.record.reader import SessionLog, open_log
from respecd.record.recorder import Recorder

PROFILE = {"name": "bench-rig", "sensors": [{"name": "front", "modality": "rgb"}]}


@pytest.fixture(scope="module")
def small_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 s of a small RGB camera and a radar in 16 KiB chunks: a few dozen records to damage."""
    import asyncio

    root = tmp_path_factory.mktemp("damage")
    clock = ManualClock()
    config = RecordingConfig(path=str(root / "s.mcap"), chunk_size_kib=16, flush_s=0.25, fsync=False)
    recorder = Recorder(config, PROFILE, clock)
    recorder.start()
    rng = np.random.default_rng(0)
    for i in range(31):
        clock.set(i / 10)
        image = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
        recorder.on_frame("front", Frame("rgb", i / 10, i, image, {"gt": [[1.0, 2.0, 3.0, 4.0]]}))
        raw = bytes(rng.integers(0, 255, 300, dtype=np.uint8))
        recorder.on_frame("radar", Frame("radar", i / 10, i, np.ones((3, 5), np.float32), {"raw": raw}))
    asyncio.run(recorder.close())
    return recorder.paths[0]


def _contents(session: SessionLog, decode: bool = True) -> tuple[set[tuple[str, int, bytes]], dict | None]:
    messages = {(topic, ns, data) for topic, _, ns, data in session.messages()}
    for sensor in session.sensors if decode else ():  # the decoding path a replay takes
        for _ in session.frames(sensor):
            pass
    return messages, session.profile_dict()


def _read(path: Path, decode: bool) -> tuple[SessionLog, set[tuple[str, int, bytes]], dict | None] | None:
    try:
        session = open_log(path, verify=True, warn=False)
        messages, profile = _contents(session, decode)
    except InputError:  # a clear error (exit 2): the magic, or nothing readable
        return None
    return session, messages, profile


@pytest.mark.slow
def test_a_flipped_byte_anywhere_is_reported_never_passed_on(small_log: Path, tmp_path: Path) -> None:
    original = open_log(small_log, verify=True, warn=False)
    good, profile = _contents(original)
    assert not original.damage and len(good) == original.message_count > 90
    data = small_log.read_bytes()
    # every byte of the header and metadata (before the first chunk) and of the footer; a sample between
    offsets = sorted({*range(0, 360), *range(360, len(data), 149), *range(len(data) - 100, len(data))})
    silent, reported = [], 0
    for n, offset in enumerate(offsets):
        bad = bytearray(data)
        bad[offset] ^= 0xFF
        path = tmp_path / "bad.mcap"
        path.write_bytes(bad)
        result = _read(path, decode=n % 5 == 0)
        if result is None:
            assert offset < 8, f"offset {offset}: the file became unreadable"  # only a bad magic may do that
            continue
        session, messages, got_profile = result
        assert messages <= good, f"offset {offset}: a message was altered and passed on"
        if session.damage:
            reported += 1
        elif messages != good or got_profile != profile:
            silent.append(offset)
    assert not silent, f"data lost or altered without a damage report at offsets {silent}"
    assert reported > len(offsets) * 0.8  # nearly every byte is covered by some CRC


def test_a_cut_anywhere_reads_what_is_before_it(small_log: Path, tmp_path: Path) -> None:
    data = small_log.read_bytes()
    good = {(t, ns, d) for t, _, ns, d in open_log(small_log).messages()}
    counts = []
    for end in range(9, len(data), 157):
        path = tmp_path / "cut.mcap"
        path.write_bytes(data[:end])
        try:
            session = open_log(path, verify=True, warn=False)
        except InputError:
            continue
        messages = {(t, ns, d) for t, _, ns, d in session.messages()}
        assert messages <= good and (session.truncated or messages == good)
        assert not session.damage  # a cut is a cut, not damage
        counts.append(len(messages))
    assert counts == sorted(counts) and counts[-1] == len(good)


def test_replay_skips_a_damaged_chunk_with_one_warning(small_log: Path, tmp_path: Path) -> None:
    data = bytearray(small_log.read_bytes())
    data[len(data) // 3] ^= 0xFF
    path = tmp_path / "bad.mcap"
    path.write_bytes(data)
    session = open_log(path)  # as a replay opens it: the summary is intact, the chunk is not
    assert not session.damage
    for _ in range(3):  # a replay makes several passes (first frames, side data, frames)
        list(session.frames("front"))
    assert len(session.damage) == 1
    damage = session.damage[0]
    assert damage.start < len(data) // 3 < damage.end and "CRC" in damage.reason or "decompress" in damage.reason


def test_log_info_lists_damage_and_exits_1(small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    data = bytearray(small_log.read_bytes())
    data[len(data) // 2] ^= 0x01
    path = tmp_path / "bad.mcap"
    path.write_bytes(data)
    assert main(["log", "info", "--json", str(path)]) == 1
    captured = capsys.readouterr()
    info = json.loads(captured.out)  # stdout stays one JSON document
    assert info["damaged"] is True and len(info["damage"]) == 1
    assert "DAMAGED bytes" in captured.err and "Traceback" not in captured.err
    assert main(["log", "info", str(small_log)]) == 0
    data = bytearray(small_log.read_bytes())
    data[len(data) - 8 - 29 - 40] ^= 0x01  # inside the summary (its offsets), just before the footer
    path.write_bytes(data)
    assert main(["log", "info", str(path)]) == 1
    assert "summary section CRC mismatch" in capsys.readouterr().err


def test_damaged_profile_metadata_is_a_clear_error(small_log: Path, tmp_path: Path) -> None:
    data = small_log.read_bytes()
    at = data.index(b'"name":"bench-rig"')
    path = tmp_path / "bad.mcap"
    path.write_bytes(data[:at] + b"{" + data[at + 1:])  # the JSON no longer parses
    session = open_log(path)
    with pytest.raises(InputError, match="recorded profile is damaged"):
        session.profile_dict()
