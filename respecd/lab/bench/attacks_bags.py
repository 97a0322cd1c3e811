"""Attacks through logs and the state directory: bad messages in a robot's bag, a lying
metadata.yaml, bit-flipped MCAP logs, a state directory that turns read-only after start
(``respecd bench attacks``)."""

from __future__ import annotations

import json
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from respecd.lab.bench.attacks import Context, Kind, escape

T0 = 1_700_000_000 * 10**9
TOPIC = "/cam/image_raw"
IMAGE = "sensor_msgs/msg/Image"


def _bag(folder: Path, kind: str, bad: dict[int, str]) -> Path:
    """30 small images; ``bad``: index -> how that message is spoiled (cut, short, junk, empty)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if kind == "ros1" else store.serialize_cdr

    def raw(k: int) -> bytes:
        ns = T0 + k * 100_000_000
        stamp = types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        rows = 2 if bad.get(k) == "short" else 36
        image = types[IMAGE](header=types["std_msgs/msg/Header"](stamp=stamp, frame_id="cam"), height=36, width=64,
                             encoding="rgb8", is_bigendian=0, step=192, data=np.zeros(rows * 192, np.uint8))
        data = bytes(serialize(image, IMAGE))
        spoiled = {"cut": data[:40], "junk": random.Random(k).randbytes(len(data)), "empty": b""}
        return spoiled.get(bad.get(k, ""), data)

    if kind == "ros1":
        path = folder / "b.bag"
        with Writer1(path) as w1:
            conn1 = w1.add_connection(TOPIC, IMAGE, typestore=store)
            for k in range(30):
                w1.write(conn1, T0 + k * 100_000_000, raw(k))
        return path
    path = folder / "bag"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3) as w:
        conn = w.add_connection(TOPIC, IMAGE, typestore=store)
        for k in range(30):
            w.write(conn, T0 + k * 100_000_000, raw(k))
    return path


def bag_bad_messages(ctx: Context, i: int) -> str | None:
    """One or three spoiled messages: exactly those skipped and reported, the rest of the sensor replayed."""
    from respecd.record.rosbag_in import open_bag

    kind = ("mcap", "sqlite3", "ros1")[i % 3]
    how = ("cut", "short", "junk", "empty")[(i // 3) % 4]
    rng = random.Random(i)
    spoiled = sorted(rng.sample(range(30), 1 if i % 2 else 3))
    bag = open_bag(_bag(ctx.fresh("bag"), kind, dict.fromkeys(spoiled, how)), {"rgb": TOPIC})
    seqs = [frame.seq for frame in bag.frames("rgb")]
    lost = sorted(set(range(30)) - set(seqs))
    if lost != sorted(bag.skipped.get(TOPIC, {})):
        return f"{kind}/{how}: lost {lost}, reported {sorted(bag.skipped.get(TOPIC, {}))}"
    return None if set(lost) <= set(spoiled) else f"{kind}/{how}: lost {lost}, spoiled only {spoiled}"


LIES: list[dict[str, Any]] = [
    {"duration": 900_000_000_000_000_000}, {"duration": -5_000_000_000}, {"count": 7}, {"count": 9_999_999},
    {"twice": True}, {"total": 3}, {"start": 0}]


def bag_metadata_lies(ctx: Context, i: int) -> str | None:
    """metadata.yaml's numbers edited: the storage's numbers win, each lie is warned about."""
    from respecd.record.rosbag_in import open_bag

    kind = ("mcap", "sqlite3")[i % 2]
    lie = LIES[(i // 2) % len(LIES)]
    path = _bag(ctx.fresh("lie"), kind, {})
    meta = path / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    info = doc["rosbag2_bagfile_information"]
    if "duration" in lie:
        info["duration"]["nanoseconds"] = lie["duration"]
    if "count" in lie:
        info["topics_with_message_count"][0]["message_count"] = lie["count"]
    if "total" in lie:
        info["message_count"] = lie["total"]
    if "start" in lie:
        info["starting_time"]["nanoseconds_since_epoch"] = lie["start"]
    if "twice" in lie:
        info["relative_file_paths"] *= 2
    meta.write_text(yaml.safe_dump(doc))
    bag = open_bag(path, {"rgb": TOPIC}, warn=False)
    frames = len(list(bag.frames("rgb")))
    if frames != 30 or abs(bag.duration_s - 2.9) > 1e-3 or bag.frame_count("rgb") != 30:
        return f"{kind} {lie}: {frames} frames, {bag.duration_s:.3f} s, count {bag.frame_count('rgb')}"
    return None if bag.metadata_notes else f"{kind} {lie}: no warning"


def bag_replay_huge_duration(ctx: Context, i: int) -> str | None:
    """--replay --speed max of a bag whose metadata.yaml claims 28 years: it ends."""
    path = _bag(ctx.fresh("huge"), ("mcap", "sqlite3")[i % 2], {})
    meta = path / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    doc["rosbag2_bagfile_information"]["duration"]["nanoseconds"] = 900_000_000_000_000_000
    meta.write_text(yaml.safe_dump(doc))
    result = ctx.respecd("--replay", str(path), "--topics", f"rgb={TOPIC}", "--speed", "max", timeout=180)
    if result is None:
        return "still replaying after 180 s"
    return None if result.returncode == 0 else f"exit {result.returncode}: {result.stderr.strip()[-160:]}"


def mcap_damage(ctx: Context, i: int) -> str | None:
    """A byte flipped in a recorded session: log info and the reader say so, never a traceback."""
    from respecd.errors import InputError
    from respecd.record.reader import open_log

    source = ctx.root / "session.mcap"
    if not source.exists():
        result = ctx.respecd("--profile", str(ctx.profile), "--duration", "5", "--record", str(source),
                             "--state-dir", str(ctx.fresh("rec")), timeout=120)
        if result is None or not source.exists():
            return "could not record the session to damage"
    data = bytearray(source.read_bytes())
    rng = random.Random(i)
    data[rng.randrange(len(data))] ^= 0xFF
    path = ctx.fresh("dmg") / "d.mcap"
    path.write_bytes(bytes(data))

    def read_whole() -> None:
        log = open_log(path, verify=True, warn=False)
        for sensor in log.sensors:
            for _ in log.frames(sensor):
                pass

    return escape(read_whole, InputError)


def statedir_fills_up(ctx: Context, i: int) -> str | None:
    """The state directory (a 1-MiB tmpfs) filled 6 s into a learning run, emptied again at 14 s: one
    error line, the status line flags the table unsaved, one line when saves succeed again (needs root
    for the mount; otherwise counted as held)."""
    import os

    if os.geteuid() != 0:
        return None
    state = ctx.fresh("full")
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(state)], capture_output=True).returncode:
        return "cannot mount a tmpfs"
    try:
        profile = dict(ctx.base)
        profile["controller"] = {**profile.get("controller", {}), "save_every": 1}
        path = ctx.fresh("fullp") / "p.yaml"
        path.write_text(yaml.safe_dump(profile))
        child = subprocess.Popen([sys.executable, "-m", "respecd.cli", "--profile", str(path), "--duration", "22",
                                  "--state-dir", str(state), "--log-format", "json"], stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
        time.sleep(6)
        filler = state / "filler"
        with open(filler, "wb") as out:
            try:
                while True:
                    out.write(b"\0" * 65536)
                    out.flush()
            except OSError:
                pass  # full
        time.sleep(8)
        filler.unlink()
        out_text, _ = child.communicate(timeout=60)
    finally:
        subprocess.run(["umount", "-l", str(state)], capture_output=True)
    events = [json.loads(line) for line in out_text.splitlines() if line.startswith("{")]
    errors = [e["event"] for e in events if e.get("level") == "error"]
    flagged = any(e.get("qtable") for e in events if e["event"] == "status")
    recovered = [e for e in events if e["event"] == "qtable_save_recovered"]
    if errors != ["qtable_save_failed"] or not flagged or len(recovered) != 1:
        return f"error lines {errors}, status flag {'set' if flagged else 'missing'}, {len(recovered)} recovery lines"
    return None


KINDS = [
    Kind("bag-bad-messages", "bags", 24, bag_bad_messages,
         "1 or 3 messages cut, short, random or empty in ROS 1, rosbag2 sqlite3 and MCAP bags"),
    Kind("bag-metadata-lies", "bags", 14, bag_metadata_lies,
         "metadata.yaml duration huge or negative, counts wrong, start wrong, a file listed twice"),
    Kind("bag-replay-huge", "bags", 2, bag_replay_huge_duration, "--replay --speed max, metadata claims 28 years"),
    Kind("mcap-damage", "logs", 20, mcap_damage, "a recorded session with one byte flipped, read whole"),
    Kind("statedir-full", "state", 2, statedir_fills_up,
         "the state directory full for 8 s of a learning run (saves refused), then emptied"),
]
