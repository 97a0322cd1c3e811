"""Q-table persistence: state dir resolution, atomic save/load, corrupt and mismatched files."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from respecd.control.config import Learning
from respecd.control.persist import load_into, read_table, resolve_state_dir, save_table, table_path
from respecd.control.qlearning import QTable
from respecd.errors import InputError

LAYOUT = {"states": {"factors": ["illumination"], "bins": [["dark", "dim", "bright"]]},
          "actions": {"space": {"mode": "moves"}, "names": ["keep", "up"]}}


def _table() -> QTable:
    table = QTable(3, 2, Learning(init="zero"), seed=1)
    table.update(0, 1, 1.0, 2)
    table.update(2, 0, -0.5, 0)
    return table


def test_resolve_state_dir_precedence(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("STATE_DIRECTORY", f"{tmp_path}/sd:{tmp_path}/other")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert resolve_state_dir(str(tmp_path / "cli")) == tmp_path / "cli"
    assert resolve_state_dir(None) == tmp_path / "sd"
    monkeypatch.delenv("STATE_DIRECTORY")
    assert resolve_state_dir(None) == tmp_path / "xdg" / "respecd"
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert resolve_state_dir(None) == tmp_path / "home" / ".local" / "state" / "respecd"


def test_table_path_is_named_after_the_profile(tmp_path: Path) -> None:
    assert table_path(tmp_path, "", "sim rover/1") == tmp_path / "qtable-sim_rover_1.npz"
    assert table_path(tmp_path, "mine.npz", "x") == tmp_path / "mine.npz"


def test_save_then_load_round_trips_and_leaves_no_temp_files(tmp_path: Path) -> None:
    path = tmp_path / "state" / "q.npz"
    table = _table()
    save_table(path, table, LAYOUT, {"profile": "toy"})
    save_table(path, table, LAYOUT, {"profile": "toy"})  # overwrite in place
    assert sorted(p.name for p in path.parent.iterdir()) == ["q.npz"]
    meta, q, visits = read_table(path)
    assert meta["profile"] == "toy" and meta["updates"] == 2 and meta["layout"] == LAYOUT
    fresh = QTable(3, 2, Learning(init="zero"))
    assert load_into(path, fresh, LAYOUT)
    assert np.array_equal(fresh.q, table.q) and np.array_equal(fresh.visits, table.visits)
    assert fresh.updates == 2 and fresh.epsilon == pytest.approx(table.epsilon)


def test_a_failed_write_keeps_the_old_table(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "q.npz"
    save_table(path, _table(), LAYOUT, {})
    before = path.read_bytes()

    def disk_full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    with pytest.raises(OSError):
        save_table(path, QTable(3, 2, Learning()), LAYOUT, {})
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["q.npz"]


def _torn(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _garbage(path: Path) -> None:
    path.write_bytes(b"not a zip at all")


def _bare_npy(path: Path) -> None:
    with path.open("wb") as f:
        np.save(f, np.zeros(3))


def _broken_meta(path: Path) -> None:
    with path.open("wb") as f:
        np.savez(f, q=np.zeros((3, 2)), visits=np.zeros((3, 2)), meta=np.frombuffer(b"{broken", np.uint8))


@pytest.mark.parametrize("damage", [_torn, _garbage, _bare_npy, _broken_meta])
def test_corrupt_file_is_set_aside_and_learning_starts_fresh(tmp_path: Path, damage) -> None:
    path = tmp_path / "q.npz"
    save_table(path, _table(), LAYOUT, {})
    damage(path)
    fresh = QTable(3, 2, Learning(init="zero"))
    assert not load_into(path, fresh, LAYOUT)
    assert not path.exists()
    aside = [p.name for p in tmp_path.iterdir()]
    assert len(aside) == 1 and aside[0].startswith("q.npz.corrupt-")
    assert fresh.updates == 0 and not fresh.q.any()
    with pytest.raises(InputError, match="q.npz"):
        read_table(tmp_path / aside[0])


def test_mismatched_space_is_set_aside(tmp_path: Path) -> None:
    path = tmp_path / "q.npz"
    save_table(path, _table(), LAYOUT, {})
    other = {**LAYOUT, "actions": {"space": {"mode": "product"}, "names": ["a", "b"]}}
    assert not load_into(path, QTable(3, 2, Learning()), other)
    assert [p.name.split("-")[0] for p in tmp_path.iterdir()] == ["q.npz.mismatch"]


def test_missing_file_is_a_fresh_start(tmp_path: Path) -> None:
    assert not load_into(tmp_path / "none.npz", QTable(1, 1, Learning()), LAYOUT)
    with pytest.raises(InputError, match="no such file"):
        read_table(tmp_path / "none.npz")


def test_factored_table_round_trips_and_a_moves_layout_does_not_load_it(tmp_path: Path) -> None:
    from respecd.config import load_profile
    from respecd.control.controller import Controller
    from respecd.control.qlearning import FactoredQTable
    from respecd.control.state import Observation

    profile = load_profile("builtin:sim-rover")
    actions = profile.controller.actions

    def controller(mode: str) -> Controller:
        config = profile.controller.model_copy(update={"actions": actions.model_copy(update={"mode": mode})})
        return Controller.from_profile(config, profile)

    learned = controller("factored")
    for step in range(5):
        learned.step(Observation(t=float(step), illumination=0.6, conf_agg=0.5))
    assert isinstance(learned.table, FactoredQTable)
    path = tmp_path / "q.npz"
    save_table(path, learned.table, learned.layout(), {})
    fresh = controller("factored")
    assert fresh.table is not None and load_into(path, fresh.table, fresh.layout())
    assert np.array_equal(fresh.table.q, learned.table.q) and fresh.table.updates == 4
    moves = controller("moves")
    assert moves.table is not None and not load_into(path, moves.table, moves.layout())


def test_a_file_of_random_bytes_is_not_passed_off_with_numpys_pickle_advice(tmp_path: Path) -> None:
    path = tmp_path / "garbage.npz"
    path.write_bytes(np.random.default_rng(3).bytes(20_000))
    with pytest.raises(InputError) as info:
        read_table(path)
    message = str(info.value)
    assert message.startswith(f"{path}: not a respecd Q-table: it looks like unrecognised binary data")
    assert "an .npz of plain arrays q, visits and meta" in message
    assert "allow_pickle" not in message and "pickle.load" not in message


def test_an_npz_with_an_object_array_is_refused_without_suggesting_unsafe_loading(tmp_path: Path) -> None:
    path = tmp_path / "objects.npz"
    with path.open("wb") as f:
        np.savez(f, q=np.array([{"a": 1}], dtype=object), visits=np.zeros(1), meta=np.zeros(1, np.uint8))
    with pytest.raises(InputError) as info:
        read_table(path)
    message = str(info.value)
    assert "objects.npz: not a respecd Q-table: array 'q' holds Python objects" in message
    assert "allow_pickle" not in message and "trust" not in message


def test_policy_show_on_garbage_exits_2(tmp_path: Path) -> None:
    path = tmp_path / "garbage2.npz"
    path.write_bytes(np.random.default_rng(4).bytes(20_000))
    result = run_cli("policy", "show", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{path}: not a respecd Q-table" in result.stderr and "allow_pickle" not in result.stderr


def _rewrite(path: Path, meta_changes: dict | None = None, **arrays: np.ndarray) -> None:
    """The saved table with some meta fields or arrays replaced (as a hand edit or a bad writer would)."""
    import json

    with np.load(path) as data:
        q, visits, meta = data["q"], data["visits"], json.loads(data["meta"].tobytes())
    meta.update(meta_changes or {})
    raw = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez_compressed(path, **{"q": q, "visits": visits, "meta": raw, **arrays})


@pytest.mark.parametrize("change, named", [
    ({"updates": None}, "meta.updates: expected a whole number >= 0, got None"),
    ({"updates": "12"}, "meta.updates: expected a whole number >= 0, got '12'"),
    ({"updates": -3}, "meta.updates"),
    ({"updates": True}, "meta.updates"),
    ({"epsilon": float("nan")}, "meta.epsilon: expected a number from 0 to 1"),
    ({"epsilon": 7}, "meta.epsilon"),
    ({"fingerprint": 5}, "meta.fingerprint"),
    ({"layout": []}, "meta.layout"),
])
def test_a_bad_meta_field_sets_the_table_aside_with_the_reason(tmp_path: Path, change: dict, named: str,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    from structlog.testing import capture_logs

    path = tmp_path / "q.npz"
    save_table(path, _table(), LAYOUT, {})
    _rewrite(path, change)
    fresh = QTable(3, 2, Learning(init="zero"))
    with capture_logs() as logs:
        assert not load_into(path, fresh, LAYOUT)  # no crash: learning starts fresh
    assert not path.exists() and len(list(tmp_path.glob("q.npz.corrupt-*"))) == 1
    assert named in logs[0]["detail"] and logs[0]["event"] == "qtable_set_aside"
    assert fresh.updates == 0


@pytest.mark.parametrize("arrays, named", [
    ({"visits": np.full((3, 2), -1, np.int64)}, "visits: expected counts >= 0, got -1 at state 0, action 0"),
    ({"visits": np.zeros((3, 2), np.float64)}, "visits: expected whole numbers"),
    ({"q": np.array([[0.0, np.inf], [0, 0], [0, 0]])}, "q: expected finite values, got inf at state 0, action 1"),
    ({"q": np.zeros((3, 2), np.float32)}, "q: expected a non-empty float64 matrix"),
])
def test_bad_arrays_are_named_with_the_cell(tmp_path: Path, arrays: dict, named: str) -> None:
    path = tmp_path / "q.npz"
    save_table(path, _table(), LAYOUT, {})
    _rewrite(path, **arrays)
    with pytest.raises(InputError) as info:
        read_table(path)
    assert named in str(info.value)


@pytest.mark.e2e
def test_a_table_with_negative_visits_no_longer_crashes_the_daemon(tmp_path: Path) -> None:
    """visits -1 made the controller divide by zero at its first update, on every restart."""
    import subprocess
    import sys

    state = tmp_path / "st"
    state.mkdir()
    run = [sys.executable, "-m", "respecd.cli", "--duration", "4", "--state-dir", str(state), "--log-format", "json"]
    first = subprocess.run(run, capture_output=True, text=True, timeout=180)
    assert first.returncode == 0, first.stderr[-2000:]
    table = state / "qtable-sim-rover.npz"
    with np.load(table) as data:
        shape = data["visits"].shape
    _rewrite(table, {"updates": None}, visits=np.full(shape, -1, np.int64))
    second = subprocess.run(run, capture_output=True, text=True, timeout=180)
    assert second.returncode == 0 and "Traceback" not in second.stdout + second.stderr, second.stderr[-2000:]
    assert "qtable_set_aside" in second.stdout and list(state.glob("qtable-sim-rover.npz.corrupt-*"))


@contextlib.contextmanager
def _not_root() -> Iterator[None]:
    """Root reads any file: as root (CI containers), act as nobody for the block (effective ids)."""
    if os.geteuid() != 0:
        yield
        return
    os.setegid(65534)
    os.seteuid(65534)
    try:
        yield
    finally:
        os.seteuid(0)
        os.setegid(0)


def test_an_unreadable_table_is_an_error_not_corruption() -> None:
    """Mode 000 under the daemon's user was renamed .corrupt-... and learning restarted from zero."""
    import tempfile

    with tempfile.TemporaryDirectory(dir="/tmp") as folder:  # pytest's tmp_path is in a root-only folder
        state = Path(folder)
        state.chmod(0o777)
        path = state / "qtable-sim-rover.npz"
        save_table(path, _table(), LAYOUT, {})
        path.chmod(0)
        _refused_not_set_aside(state, path)


def _refused_not_set_aside(state: Path, path: Path) -> None:
    from respecd.config import read_profile
    from respecd.control.persist import TableAccessError
    from respecd.preflight import check_profile

    profile = read_profile("builtin:sim-rover")
    check_profile(profile, state)  # imports what it needs while it may still read the interpreter's files
    with _not_root():
        with pytest.raises(TableAccessError, match="cannot read the Q-table: Permission denied"):
            load_into(path, QTable(3, 2, Learning()), LAYOUT)
        problems = check_profile(profile, state)
    assert path.exists() and not list(state.glob("*.corrupt-*"))
    assert f"--state-dir: {path}: cannot read the Q-table (permission denied); fix its permissions" in problems


def test_a_bit_flipped_in_a_compressed_array_is_damage_not_a_crash(tmp_path: Path) -> None:
    """`respecd bench attacks` found it: a flipped bit inside the deflated q array was a zlib.error out of
    load_into (not a zipfile error), so the daemon crashed at start instead of setting the table aside."""
    path = tmp_path / "q.npz"
    table = QTable(40, 30, Learning(init="zero"), seed=1)
    for k in range(300):
        table.update(k % 40, k % 30, float(k % 7) - 3.0, (k + 1) % 40)
    save_table(path, table, LAYOUT, {})
    data = path.read_bytes()
    start = data.index(b"q.npy") + 40  # inside the q member's deflated bytes
    crashes = 0
    for offset in range(start, start + 200, 5):
        spoiled = bytearray(data)
        spoiled[offset] ^= 0x10
        path.write_bytes(bytes(spoiled))
        try:
            load_into(path, QTable(40, 30, Learning(init="zero")), LAYOUT)
        except Exception:  # noqa: BLE001 - what the test counts
            crashes += 1
        for aside in tmp_path.glob("q.npz.*"):
            aside.unlink()
    assert crashes == 0
