"""Attacks through files and processes: special files where files are read, damaged and hostile
Q-tables, bags and profiles, paths no file system takes, a state directory that fails, retention
fooled by names, signals and kill -9 (``respecd bench attacks``)."""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from respecd.lab.bench.attacks import Context, Kind, at_once, escape, refused

SPECIALS = ("fifo", "/dev/zero", "/dev/null", "dir", "socket")


def _special(ctx: Context, kind: str, name: str) -> Path:
    if kind.startswith("/dev/"):
        return Path(kind)
    path = ctx.fresh("special") / name
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "dir":
        path.mkdir()
    else:
        with socket.socket(socket.AF_UNIX) as sock:
            sock.bind(str(path))
    return path


def special_file_reads(ctx: Context, i: int) -> str | None:
    """Every reader of a file given a FIFO, a device, a directory or a socket: refused at once."""
    from respecd.config import read_profile
    from respecd.control.persist import read_table
    from respecd.errors import ConfigError, InputError
    from respecd.record.reader import open_log
    from respecd.record.rosbag_in import open_bag

    readers: list[tuple[str, Callable[[Path], Any]]] = [
        ("p.yaml", read_profile), ("q.npz", read_table), ("x.mcap", open_log), ("x.bag", lambda p: open_bag(p, None))]
    name, reader = readers[i % len(readers)]
    kind = SPECIALS[(i // len(readers)) % len(SPECIALS)]
    path = _special(ctx, kind, name)
    outcome, blocked = at_once(lambda: reader(path), unblock=path if kind == "fifo" else None)
    if blocked:
        return f"{reader.__name__}({kind}): {blocked}"
    if not isinstance(outcome, (ConfigError, InputError)):
        return f"{reader.__name__}({kind}): {type(outcome).__name__}: {outcome}"[:200]
    return None


def fifo_in_the_state_dir(ctx: Context, i: int) -> str | None:
    """The daemon with a FIFO as its Q-table, its lock file, or its profile: exit 2 at once."""
    state = ctx.fresh("state")
    where = ("qtable-sim-rover.npz", ".respecd.lock", "profile")[i % 3]
    profile = ctx.profile
    if where == "profile":
        profile = state / "p.yaml"
        os.mkfifo(profile)
    else:
        os.mkfifo(state / where)
    return refused(ctx.respecd("--profile", str(profile), "--duration", "5", "--state-dir", str(state),
                               timeout=30), said="is a FIFO")


def fifo_check_config_and_log_info(ctx: Context, i: int) -> str | None:
    folder = ctx.fresh("cc")
    if i % 2 == 0:
        os.mkfifo(folder / "p.yaml")
        return refused(ctx.respecd("check-config", str(folder / "p.yaml"), timeout=30), said="is a FIFO")
    bag = folder / "bag"
    bag.mkdir()
    os.mkfifo(bag / "bag_0.mcap")
    info = {"version": 8, "storage_identifier": "mcap", "relative_file_paths": ["bag_0.mcap"],
            "duration": {"nanoseconds": 1}, "starting_time": {"nanoseconds_since_epoch": 1}, "message_count": 0,
            "topics_with_message_count": []}
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))
    return refused(ctx.respecd("log", "info", str(bag), timeout=30), said="is a FIFO")


# -- Q-tables -------------------------------------------------------------------------------
LAYOUT = {"states": {"factors": ["x"], "bins": [["a", "b", "c"]]}, "actions": {"names": ["k", "u"]}}
BAD_META: list[dict[str, Any]] = [
    {"updates": None}, {"updates": "12"}, {"updates": -1}, {"updates": True}, {"updates": 1.5},
    {"epsilon": float("nan")}, {"epsilon": float("inf")}, {"epsilon": -0.1}, {"epsilon": 2}, {"epsilon": "x"},
    {"epsilon": None}, {"fingerprint": 5}, {"fingerprint": None}, {"fingerprint": ""}, {"layout": []},
    {"layout": None}, {"format": "other"}, {"version": 99}, {"version": "1"}]
BAD_ARRAYS: list[dict[str, Any]] = [
    {"visits": np.full((3, 2), -1, np.int64)}, {"visits": np.zeros((3, 2))}, {"visits": np.zeros((2, 2), np.int64)},
    {"q": np.array([[np.nan, 0], [0, 0], [0, 0]])}, {"q": np.array([[np.inf, 0], [0, 0], [0, 0]])},
    {"q": np.zeros((3, 2), np.float32)}, {"q": np.zeros(6)}, {"q": np.zeros((0, 2))},
    {"q": np.array([["a", "b"]] * 3)}, {"visits": np.array([[1, 2]] * 3, np.uint8)}]


def _saved_table(ctx: Context) -> tuple[Path, Any]:
    from respecd.control.config import Learning
    from respecd.control.persist import save_table
    from respecd.control.qlearning import QTable

    table = QTable(3, 2, Learning(init="zero"))
    table.update(0, 1, 1.0, 2)
    path = ctx.fresh("q") / "q.npz"
    save_table(path, table, LAYOUT, {})
    return path, table


def _rewrite(path: Path, meta_changes: dict[str, Any], arrays: dict[str, Any]) -> None:
    with np.load(path) as data:
        parts = {"q": data["q"], "visits": data["visits"], "meta": json.loads(data["meta"].tobytes())}
    parts["meta"].update(meta_changes)
    parts["meta"] = np.frombuffer(json.dumps(parts["meta"]).encode(), np.uint8)
    parts.update(arrays)
    np.savez_compressed(path, **parts)


def _loads_fresh_or_aside(path: Path) -> str | None:
    """load_into a hostile table: it must return False and set the file aside, never raise."""
    from respecd.control.config import Learning
    from respecd.control.persist import load_into
    from respecd.control.qlearning import QTable

    fresh = QTable(3, 2, Learning(init="zero"))
    try:
        loaded = load_into(path, fresh, LAYOUT)
    except Exception as err:  # noqa: BLE001 - the outcome under test
        return f"load_into raised {type(err).__name__}: {err}"[:200]
    if loaded:
        try:
            fresh.update(1, 0, 0.5, 2)  # what the controller does next: a bad count divided by zero here
        except Exception as err:  # noqa: BLE001
            return f"loaded, then the first update raised {type(err).__name__}"
        return None
    if path.exists() or not list(path.parent.glob(f"{path.name}.corrupt-*")):
        return "not set aside"
    return None


def qtable_bad_fields(ctx: Context, i: int) -> str | None:
    path, _ = _saved_table(ctx)
    changes = BAD_META[i % len(BAD_META)] if i < len(BAD_META) else {}
    arrays = BAD_ARRAYS[(i - len(BAD_META)) % len(BAD_ARRAYS)] if i >= len(BAD_META) else {}
    _rewrite(path, changes, arrays)
    return _loads_fresh_or_aside(path)


def qtable_damage(ctx: Context, i: int) -> str | None:
    """Cut at, or a bit flipped at, a random offset: set aside or loaded intact, never a crash."""
    path, _ = _saved_table(ctx)
    data = bytearray(path.read_bytes())
    rng = random.Random(i)
    if i % 2:
        data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    else:
        del data[rng.randrange(len(data)):]
    path.write_bytes(bytes(data))
    return _loads_fresh_or_aside(path)


def qtable_unreadable(ctx: Context, i: int) -> str | None:
    """Mode 000 under an unprivileged user: exit 2 at start, the table left as it is."""
    from respecd.config import read_profile
    from respecd.preflight import check_profile

    state = ctx.fresh("perm")
    os.chmod(state, 0o777)
    path, _ = _saved_table(ctx)
    table = state / "qtable-sim-rover.npz"
    os.replace(path, table)
    os.chmod(table, 0)
    profile = read_profile(str(ctx.profile))
    check_profile(profile, state)  # imports, while the interpreter's files can still be read
    if os.geteuid() == 0:
        os.setegid(65534)
        os.seteuid(65534)
    try:
        problems = check_profile(profile, state)
    finally:
        if os.getuid() == 0:
            os.seteuid(0)
            os.setegid(0)
    if not any("cannot read the Q-table" in p for p in problems):
        return f"not refused at start: {problems}"
    return None if table.exists() else "table renamed"


# -- recording, profiles, paths -------------------------------------------------------------
def retention_future_names(ctx: Context, i: int) -> str | None:
    """Older sessions named as if from 2099 (or 1970) beside a live session under max_bytes."""
    from datetime import datetime, timezone

    from respecd.record.codec import Message
    from respecd.record.config import RecordingConfig
    from respecd.record.writer import SegmentWriter

    folder = ctx.fresh("ret")
    started = datetime.now(timezone.utc)
    for k in range(3):
        old = folder / f"r-{('20991231T000000', '19700101T000000')[i % 2]}{'' if k == 0 else f'-00{k}'}.mcap"
        old.write_bytes(b"\0" * 700_000)
        os.utime(old, (started.timestamp() - 86400, started.timestamp() - 86400))
    config = RecordingConfig(path=str(folder / "r-{time}.mcap"), rotate_mib=1, max_bytes=4 << 20,
                             min_free_mib=0, fsync=False, chunk_size_kib=16)
    writer = SegmentWriter(config, {"respecd.session": {"segment": "0"}}, started)
    payload = os.urandom(1200)
    for k in range(2500):
        writer.put(Message("/respecd/percept", "respecd.Percept", payload, {}), k, k * 0.01)
    writer.close()
    gone = [p.name for p in writer.paths if not p.exists()]
    return f"live segments deleted: {gone}" if gone else None


BAD_SIZES: list[dict[str, Any]] = [
    {"max_bytes": 1}, {"max_bytes": 1000}, {"rotate_mib": 0.001}, {"rotate_mib": 0}, {"rotate_mib": -1},
    {"max_bytes": -5}, {"rotate_mib": 4, "max_bytes": 5 << 20}]
BAD_PATHS: list[dict[str, Any]] = [{"recording": {"enabled": True, "path": "r/" + "x" * 300 + ".mcap"}},
             {"recording": {"enabled": True, "path": "r/a\x00b.mcap"}}, {"name": "n" * 5000},
             {"name": "n" * 250}, {"controller": {"table_file": "t" * 300 + ".npz"}},
             {"recording": {"enabled": True, "path": "/dev/null"}},
             {"recording": {"enabled": True, "path": "/dev/zero"}}]


def profile_values(ctx: Context, i: int) -> str | None:
    """Nonsensical recording sizes and paths no file system takes: check-config's refusal, no traceback."""
    from respecd.config import read_profile
    from respecd.errors import ConfigError
    from respecd.preflight import check_profile

    cases = [{"recording": s} for s in BAD_SIZES] + BAD_PATHS
    profile = dict(ctx.base)
    for key, value in cases[i % len(cases)].items():
        profile[key] = {**profile.get(key, {}), **value} if isinstance(value, dict) else value
    path = ctx.fresh("prof") / "p.yaml"
    path.write_text(yaml.safe_dump(profile))
    try:
        problems = check_profile(read_profile(str(path)), path.parent / "st")
    except ConfigError:
        return None
    except Exception as err:  # noqa: BLE001 - the outcome under test
        return f"{type(err).__name__}: {err}"[:200]
    return None if problems else f"accepted: {cases[i % len(cases)]}"[:200]


def hostile_profiles(ctx: Context, i: int) -> str | None:
    """A random mutation of the shipped profile (types, ranges, structure, bytes): ConfigError or ok."""
    from respecd.config import read_profile
    from respecd.errors import ConfigError

    rng = random.Random(i)
    text = yaml.safe_dump(ctx.base)
    lines = text.splitlines()
    k = rng.randrange(len(lines))
    key, sep, _ = lines[k].partition(":")
    junk = rng.choice(["-1", "1e309", ".nan", "yes", "'30'", "[1, [2]]", "{a: 1}", "~", "&a [*a]", "!!binary AAA",
                       "9" * 400, "\"\\x00\"", "2026-01-01", "0x1F", "[]"])
    lines[k] = f"{key}{sep} {junk}" if sep else lines[k] + rng.choice(["\t", "\x85", ": :", " &x"])
    if i % 7 == 0:
        lines.insert(k, lines[k])  # a duplicate key
    path = ctx.fresh("hostile") / "p.yaml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8", errors="surrogateescape")
    return escape(lambda: read_profile(str(path)), ConfigError, where=f"line {k + 1} = {junk!r}: ")


def record_special(ctx: Context, i: int) -> str | None:
    from respecd.outputs import recording_problem

    target = ["/dev/null", "/dev/zero", "fifo", "socket"][i % 4]
    path = str(_special(ctx, target, "r.mcap")) if not target.startswith("/dev/") else target
    return None if recording_problem(path) else f"--record {target} accepted"


def topic_maps(ctx: Context, i: int) -> str | None:
    from respecd.errors import InputError
    from respecd.record.rosbag_in import parse_topics

    bad = ["rgb=/a,rgb=/b", "rgb", "rgb=", "=/a", "rgb=a", "sonar=/a", "rgb=/a,,", "rgb=/a,thermal", ",", "rgb==/a"]
    try:
        parse_topics(bad[i % len(bad)])
    except InputError:
        return None
    return f"{bad[i % len(bad)]!r} accepted"


# -- processes --------------------------------------------------------------------------------
def signal_at_random(ctx: Context, i: int) -> str | None:
    """SIGTERM, SIGINT or SIGHUP at a random moment of start or run: exit 0 within 3 s, table saved if up."""
    state = ctx.fresh("sig")
    rng = random.Random(i)
    sig = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)[i % 3]
    child = subprocess.Popen([sys.executable, "-m", "respecd.cli", "--profile", str(ctx.profile), "--duration", "30",
                              "--state-dir", str(state), "--log-format", "json"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, preexec_fn=_usual_dispositions)  # noqa: PLW1509
    time.sleep(rng.uniform(0.0, 6.0))
    sent = time.monotonic()
    child.send_signal(sig)
    try:
        out, err = child.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()
        return f"{sig.name}: still running 15 s later"
    took = time.monotonic() - sent
    if child.returncode == -sig and took < 1.0 and not err:
        return None  # the interpreter was still starting: ended by the signal itself, nothing to save yet
    if child.returncode not in (0, 130) or "Traceback" in err:
        return f"{sig.name}: exit {child.returncode}: {err.strip()[-120:]}"
    if took > 3.0:
        return f"{sig.name}: {took:.1f} s to stop"
    if '"pipeline_up"' in out and not (state / "qtable-sim-rover.npz").exists():
        return f"{sig.name}: stopped after start, no Q-table saved"
    return None


def _usual_dispositions() -> None:
    """In the child: the signals as a terminal or systemd leave them (the bench may run under nohup)."""
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def kill_mid_recording(ctx: Context, i: int) -> str | None:
    """kill -9 while recording: what is on disk still opens (cut at its last complete chunk)."""
    from respecd.record.reader import open_log

    folder = ctx.fresh("kill")
    child = subprocess.Popen([sys.executable, "-m", "respecd.cli", "--profile", str(ctx.profile), "--duration", "30",
                              "--record", str(folder / "r.mcap"), "--state-dir", str(folder / "st")],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(4.0 + random.Random(i).uniform(0, 3))
    child.kill()
    child.wait()
    try:
        log = open_log(folder / "r.mcap")
    except Exception as err:  # noqa: BLE001 - the outcome under test
        return f"{type(err).__name__}: {err}"[:200]
    return None if log.message_count > 0 else "no message readable"


KINDS = [
    Kind("special-file-reads", "files", 40, special_file_reads,
         "FIFO, /dev/zero, /dev/null, directory or socket given to the profile, Q-table, MCAP log, ROS 1 bag "
         "readers"),
    Kind("fifo-state-or-profile", "files", 6, fifo_in_the_state_dir,
         "the daemon with a FIFO as its Q-table, its lock file or its profile"),
    Kind("fifo-cli", "files", 4, fifo_check_config_and_log_info,
         "check-config FIFO; log info BAG whose metadata.yaml lists a FIFO"),
    Kind("qtable-bad-fields", "state", 29, qtable_bad_fields,
         "Q-table meta fields of the wrong type, out of range, not finite; arrays of the wrong shape, dtype, sign"),
    Kind("qtable-damage", "state", 40, qtable_damage, "Q-table cut or with one bit flipped at a random offset"),
    Kind("qtable-unreadable", "state", 2, qtable_unreadable, "Q-table mode 000 under an unprivileged user"),
    Kind("retention-names", "recording", 4, retention_future_names,
         "older sessions named 2099 or 1970 beside a live session under max_bytes"),
    Kind("record-special", "recording", 4, record_special, "--record /dev/null, /dev/zero, a FIFO, a socket"),
    Kind("profile-values", "profiles", 14, profile_values,
         "nonsensical recording sizes; paths with NUL, names over 255 bytes, a 5,000-character name, devices"),
    Kind("hostile-profiles", "profiles", 96, hostile_profiles, "random mutations of the shipped profile"),
    Kind("topic-maps", "profiles", 10, topic_maps, "malformed --topics maps (a sensor twice, no topic, ...)"),
    Kind("signals", "process", 9, signal_at_random, "SIGTERM/SIGINT/SIGHUP at a random moment in the first 6 s"),
    Kind("kill-9-recording", "process", 3, kill_mid_recording, "kill -9 4-7 s into a recording"),
]
